"""Optuna search: the sampler, pruning with the cost constraint, storages, and two workers sharing one study."""

import importlib.util
import os
import signal
import subprocess
import sys
import time
import uuid
import warnings
from pathlib import Path

import numpy as np
import optuna
import pytest
import torch as th
from optuna.storages import JournalStorage, RDBStorage, RetryHeartbeatStaleTrialCallback
from optuna.trial import TrialState

from sb3_dsslac import DSSLAC
from sqlalchemy.exc import IntegrityError, OperationalError

from sb3_dsslac.app.cli import main
from sb3_dsslac.app.hpo import (
    COST_CONSTRAINT,
    StorageError,
    TuneSpec,
    make_storage,
    objective,
    retry_storage_race,
    sample_dsslac_params,
    storage_name,
    storage_url,
    tune,
)
from tests.synthetic_envs import HazardPointEnv
from tests.test_cli import TINY_ENV, TINY_FLAGS
from tests.test_dsslac import SMALL_POLICY

TINY = dict(
    learning_starts=20, latent_pretrain_steps=2, train_freq=10, gradient_steps=1, buffer_size=500, policy_kwargs=SMALL_POLICY
)
REPO = Path(__file__).resolve().parents[1]
# The tiny trial of the start-race test (tests.test_cli's sizes, as tune --hyperparams)
RACE_TRIAL = ["batch_size=8", "latent_batch_size=4", "sequence_length=3", "n_quantiles=8", "buffer_size=2000"]
RACE_TRIAL += ["learning_starts=40", "train_freq=10"]
# Set by .ci/postgres.sh, which starts a server on 127.0.0.1
POSTGRES_URL = os.environ.get("DSSLAC_TEST_POSTGRES_URL")


@pytest.fixture(autouse=True)
def one_thread():
    threads = th.get_num_threads()
    th.set_num_threads(1)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    yield
    th.set_num_threads(threads)


def test_sampler_gives_valid_dsslac_keywords() -> None:
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0), direction="maximize")
    for _ in range(5):
        trial = study.ask()
        params = sample_dsslac_params(trial)
        assert 0.95 <= params["gamma"] < 1.0 and 0.98 <= params["cost_gamma"] < 1.0
        assert params["batch_size"] in (16, 32, 64, 128) and params["latent_batch_size"] in (8, 16, 32, 64)
        assert trial.user_attrs["gamma"] == params["gamma"]
        model = DSSLAC("LatentPolicy", HazardPointEnv(), **{**params, "policy_kwargs": SMALL_POLICY})
        assert model.n_quantiles == params["n_quantiles"] and model.sequence_length == params["sequence_length"]


def test_the_pid_rule_searches_its_gains() -> None:
    trial = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0)).ask()
    params = sample_dsslac_params(trial, lagrange="pid")
    assert {"pid_kp", "pid_ki", "pid_kd"} <= set(trial.params) and "lagrange_learning_rate" not in params
    model = DSSLAC("LatentPolicy", HazardPointEnv(), lagrange="pid", **{**params, "policy_kwargs": SMALL_POLICY})
    assert model.pid_gains == (params["pid_kp"], params["pid_ki"], params["pid_kd"])


def test_a_pruned_trial_stops_early_and_records_its_cost() -> None:
    spec = TuneSpec(env=TINY_ENV, sim_steps=120, hyperparams=TINY, n_evaluations=4, eval_episodes=1)
    study = optuna.create_study(direction="maximize", pruner=optuna.pruners.ThresholdPruner(lower=1e9))
    study.optimize(lambda trial: objective(trial, spec), n_trials=1)
    trial = study.trials[0]
    assert trial.state == optuna.trial.TrialState.PRUNED
    assert list(trial.intermediate_values) == [1]  # stopped at the first of four evaluations
    costs = trial.user_attrs["eval_mean_costs"]
    assert len(costs) == 1
    assert trial.constraints[COST_CONSTRAINT] == pytest.approx(costs[0] - 25.0)


def test_make_storage(tmp_path: Path) -> None:
    assert make_storage(None) is None
    assert isinstance(make_storage(str(tmp_path / "study.log")), JournalStorage)
    sqlite = make_storage(f"sqlite:///{tmp_path / 'study.db'}", heartbeat_interval=5)
    assert isinstance(sqlite, RDBStorage) and (sqlite.heartbeat_interval, sqlite.grace_period) == (5, None)
    assert isinstance(sqlite.get_heartbeat_stale_trial_callback(), RetryHeartbeatStaleTrialCallback)


def test_an_rdb_storage_warns_of_nothing(tmp_path: Path) -> None:
    # Optuna 4.9 deprecated RetryFailedTrialCallback (a FutureWarning on every SQLite tune); heartbeats are experimental
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        make_storage(f"sqlite:///{tmp_path / 'study.db'}", heartbeat_interval=5)
    assert [str(warning.message) for warning in caught] == []


def test_a_plain_postgresql_url_gets_an_installed_driver() -> None:
    assert storage_url("sqlite:///study.db") == "sqlite:///study.db"
    assert storage_url("postgresql+psycopg2://user:password@host/db") == "postgresql+psycopg2://user:password@host/db"
    plain = storage_url("postgresql://user:password@host/db")
    if importlib.util.find_spec("psycopg2") is not None or importlib.util.find_spec("psycopg") is None:
        assert plain == "postgresql://user:password@host/db"
    else:
        assert plain == "postgresql+psycopg://user:password@host/db"


def test_sqlite_study_is_continued_by_a_second_call(tmp_path: Path) -> None:
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    spec = TuneSpec(env=TINY_ENV, sim_steps=40, hyperparams=TINY, n_evaluations=1, eval_episodes=1)
    for _ in range(2):
        study = tune(spec, n_trials=1, storage=storage, study_name="s", show_progress_bar=False)
    assert len(study.trials) == 2
    assert all(trial.state == optuna.trial.TrialState.COMPLETE for trial in study.trials)
    # The best trial is a feasible one (the tiny env's cost stays far below 25)
    assert study.best_trial.constraints[COST_CONSTRAINT] <= 0


def test_two_workers_share_one_study(tmp_path: Path) -> None:
    # About 10 s: two tune processes, each importing torch and training a tiny trial
    journal = tmp_path / "study.log"
    command = [sys.executable, "-m", "sb3_dsslac", "tune", "--env", TINY_ENV, "--timesteps=60", "--n-trials=1"]
    command += ["--storage", str(journal), "--study-name", "shared", "--n-evaluations=2", "--eval-episodes=1"]
    command += [*TINY_FLAGS]
    workers = [
        subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for _ in range(2)
    ]
    outputs = [worker.communicate()[0] for worker in workers]
    assert [worker.returncode for worker in workers] == [0, 0], outputs
    study = optuna.load_study(study_name="shared", storage=make_storage(str(journal)))
    assert len(study.trials) == 2
    for trial in study.trials:
        assert trial.state == optuna.trial.TrialState.COMPLETE
        assert len(trial.intermediate_values) == 2
        assert trial.constraints[COST_CONSTRAINT] == pytest.approx(trial.user_attrs["eval_mean_costs"][-1] - 25.0)
    assert np.unique([trial.params["learning_rate"] for trial in study.trials]).size == 2


@pytest.mark.skipif(POSTGRES_URL is None, reason="no PostgreSQL server: set DSSLAC_TEST_POSTGRES_URL (.ci/postgres.sh)")
def test_a_killed_worker_s_trial_is_retried_on_postgresql() -> None:
    """Two workers on one PostgreSQL study, one SIGKILLed mid-trial: its trial fails by heartbeat and the other reruns it."""
    # About 15 s: the killed trial is only seen as failed once its heartbeat goes stale
    study_name = f"killed_{uuid.uuid4().hex[:8]}"
    command = [sys.executable, "-m", "sb3_dsslac", "tune", "--env", TINY_ENV, "--timesteps=200", "--total-trials=2"]
    command += ["--storage", POSTGRES_URL, "--study-name", study_name, "--n-evaluations=4", "--eval-episodes=1"]
    command += ["--heartbeat-interval=1", *TINY_FLAGS]
    env = {**os.environ, "PYTHONPATH": str(REPO)}

    def start() -> subprocess.Popen:
        return subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    def trials() -> list[optuna.trial.FrozenTrial]:
        try:
            return optuna.load_study(study_name=study_name, storage=make_storage(POSTGRES_URL)).trials
        except KeyError:  # the study is not created yet
            return []

    def wait_for(condition, what: str) -> None:
        # No deadline of its own on a loaded machine: the first worker's end stops the wait
        while not condition():
            assert doomed.poll() is None, f"the first worker ended before {what}: {trials()}"
            time.sleep(0.2)

    doomed = start()
    wait_for(lambda: len(trials()) == 1, "the first worker's trial")
    survivor = start()
    # Kill the first worker between two evaluations of its trial
    wait_for(lambda: len(trials()[0].intermediate_values) >= 1, "the first evaluation")
    doomed.send_signal(signal.SIGKILL)
    doomed.wait(timeout=10)
    output = survivor.communicate()[0]
    assert survivor.returncode == 0, output
    killed, *rest = trials()
    assert doomed.returncode == -signal.SIGKILL
    assert killed.state == TrialState.FAIL and 1 <= len(killed.intermediate_values) < 4
    assert [trial.state for trial in rest] == [TrialState.COMPLETE, TrialState.COMPLETE]
    retries = [trial for trial in rest if RetryHeartbeatStaleTrialCallback.retried_trial_number(trial) == killed.number]
    assert len(retries) == 1 and retries[0].params == killed.params and len(retries[0].intermediate_values) == 4


def test_storage_races_are_retried_then_reported_by_name() -> None:
    attempts = []

    def lose_twice() -> str:
        attempts.append(1)
        if len(attempts) < 3:
            raise IntegrityError("INSERT INTO alembic_version", {}, Exception("UNIQUE constraint failed"))
        return "created"

    assert retry_storage_race(lose_twice, "sqlite:///x.db") == "created" and len(attempts) == 3

    def always_locked() -> None:
        raise OperationalError("BEGIN", {}, Exception("database is locked"))

    url = "postgresql://dsslac:secret@127.0.0.1:1/db"
    with pytest.raises(StorageError, match=r"postgresql://dsslac:\*\*\*@127.0.0.1:1/db: still failing after 3 tries"):
        retry_storage_race(always_locked, url, attempts=3)
    assert storage_name(url) == "postgresql://dsslac:***@127.0.0.1:1/db"


def test_a_storage_that_cannot_be_opened_ends_tune_with_its_name(tmp_path: Path, capsys) -> None:
    storage = f"sqlite:///{tmp_path / 'missing_folder' / 'study.db'}"
    assert main(["tune", "--env", TINY_ENV, "--timesteps=40", "--n-trials=1", "--storage", storage, *TINY_FLAGS]) == 2
    assert f"error: Optuna storage {storage}" in capsys.readouterr().err


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_workers_released_together_on_a_new_storage_all_run(kind: str) -> None:
    """Four tune workers released by one barrier on a new storage: all exit 0 and the study holds their four trials."""
    # About 20 s per storage: four worker processes, each importing torch and training one tiny trial
    if kind == "postgresql" and POSTGRES_URL is None:
        pytest.skip("no PostgreSQL server: set DSSLAC_TEST_POSTGRES_URL (.ci/postgres.sh)")
    command = [sys.executable, "benchmarks/tools/tune_start_race.py", "--rounds=1", "--workers=4", "--storages", kind]
    command += ["--env", TINY_ENV, "--timesteps=60", "--hyperparams", *RACE_TRIAL]
    env = {**os.environ, "PYTHONPATH": str(REPO), "MUJOCO_GL": "egl"}
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert f"| {kind} | 0 | 0 0 0 0 | 4 |" in result.stdout
