"""
Workers started at the same moment on a new Optuna storage: ``--workers`` processes, released by one barrier once each
has imported everything, each run ``python -m sb3_dsslac tune --n-trials 1`` on a new study of a new storage; every
round checks that all exit 0 and that the study holds one finished trial per worker.

    python benchmarks/tools/tune_start_race.py                                     # 4 workers, 5 rounds on a new SQLite file
    python benchmarks/tools/tune_start_race.py --storages sqlite postgresql --postgres-url postgresql://u:p@127.0.0.1/db

On PostgreSQL each round gets a new schema of the database (``search_path``), so the workers race to create the tables
as on a new database. The trials are tiny (``--preset cpu``, state observations, ``--timesteps`` simulator steps).
"""

import argparse
import multiprocessing
import os
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

# The benchmarks' shared modules (machine.py)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine import cpu_model
from multiprocessing.synchronize import Barrier

TINY = ["--preset", "cpu", "--obs-type", "state", "--n-evaluations", "1", "--eval-episodes", "1", "--threads", "1"]
TINY += ["--learning-starts", "100", "--latent-pretrain-steps", "2", "--gradient-steps", "1", "--n-startup-trials", "1"]


def worker(barrier: Barrier, command: list[str], log: str) -> None:
    """Import everything, wait for the others, then run ``tune``; its exit status is the process's."""
    import optuna

    from sb3_dsslac.app import cli  # the heavy imports happen before the barrier, so the workers meet the storage together

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    with open(log, "w") as out:
        sys.stdout = sys.stderr = out
        barrier.wait()
        try:
            status = cli.main(command)
        except Exception as error:  # any crash is this round's finding: write it, exit non-zero
            print(f"{type(error).__name__}: {error}")
            status = 1
        sys.stdout, sys.stderr = sys.__stdout__, sys.__stderr__
    sys.exit(status)


@contextmanager
def new_storage(kind: str, folder: Path, postgres_url: str | None) -> Iterator[str]:
    """A storage URL nothing has touched yet: a new SQLite file, or a new schema of the PostgreSQL database."""
    if kind == "sqlite":
        yield f"sqlite:///{folder / f'{uuid.uuid4().hex[:8]}.db'}"
        return
    if postgres_url is None:
        raise SystemExit("--storages postgresql needs --postgres-url (or DSSLAC_TEST_POSTGRES_URL)")
    import sqlalchemy

    from sb3_dsslac.app.hpo import storage_url

    schema = f"race_{uuid.uuid4().hex[:8]}"
    engine = sqlalchemy.create_engine(storage_url(postgres_url))
    with engine.begin() as connection:
        connection.execute(sqlalchemy.text(f"CREATE SCHEMA {schema}"))
    separator = "&" if "?" in postgres_url else "?"
    try:
        yield f"{postgres_url}{separator}options=-csearch_path%3D{schema}"
    finally:
        with engine.begin() as connection:
            connection.execute(sqlalchemy.text(f"DROP SCHEMA {schema} CASCADE"))
        engine.dispose()


def one_round(args: argparse.Namespace, storage: str, folder: Path, round_index: int) -> tuple[list[int], int, float]:
    """The workers' exit statuses, the study's finished trials and the round's wall seconds."""
    import optuna

    from sb3_dsslac.app.hpo import make_storage

    study_name = f"race{round_index}"
    command = ["tune", "--env", args.env, "--timesteps", str(args.timesteps), "--n-trials", "1", "--storage", storage]
    command += ["--study-name", study_name, *TINY, *(["--hyperparams", *args.hyperparams] if args.hyperparams else [])]
    context = multiprocessing.get_context("spawn")
    barrier = context.Barrier(args.workers)
    logs = [str(folder / f"round{round_index}_worker{index}.log") for index in range(args.workers)]
    start = time.perf_counter()
    processes = [context.Process(target=worker, args=(barrier, command, log)) for log in logs]
    for process in processes:
        process.start()
    for process in processes:
        process.join(timeout=args.timeout)
        if process.is_alive():
            process.kill()
            process.join()
    seconds = time.perf_counter() - start
    statuses = [process.exitcode for process in processes]
    for status, log in zip(statuses, logs, strict=True):
        if status != 0:
            print(f"  a worker exited {status}:\n    " + "\n    ".join(Path(log).read_text().splitlines()[-5:]))
    trials = optuna.load_study(study_name=study_name, storage=make_storage(storage)).get_trials(deepcopy=False)
    finished = sum(trial.state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED) for trial in trials)
    return statuses, finished, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--workers", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--storages", nargs="+", default=["sqlite"], choices=["sqlite", "postgresql"])
    parser.add_argument("--postgres-url", default=os.environ.get("DSSLAC_TEST_POSTGRES_URL"))
    parser.add_argument("--env", default="SafetyGym/PointGoal1-v0")
    parser.add_argument("--timesteps", type=int, default=400, help="simulator steps per trial")
    parser.add_argument("--hyperparams", nargs="*", default=[], metavar="KEY=VALUE", help="more tune --hyperparams")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds a worker may take")
    args = parser.parse_args()

    rows, failed = [], False
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for kind in args.storages:
            for round_index in range(args.rounds):
                with new_storage(kind, folder, args.postgres_url) as storage:
                    statuses, finished, seconds = one_round(args, storage, folder, round_index)
                ok = statuses == [0] * args.workers and finished == args.workers
                failed = failed or not ok
                rows.append(f"| {kind} | {round_index} | {' '.join(map(str, statuses))} | {finished} | {seconds:.0f} |")
                print(rows[-1], flush=True)
    print(f"\n{cpu_model()}; {args.workers} tune workers released together, --n-trials 1, --timesteps {args.timesteps}\n")
    print("| storage | round | exit statuses | finished trials | wall s |\n|---|---:|---|---:|---:|")
    print("\n".join(rows))
    if failed:
        raise SystemExit(f"a round failed: every worker must exit 0 and each study end with {args.workers} trials")


if __name__ == "__main__":
    main()
