"""
A run killed with SIGKILL while it writes a checkpoint's replay buffer, then resumed: each try runs
``python -m sb3_dsslac train --preset cpu --checkpoint-every N``, waits for its first complete checkpoint, kills it as
soon as the next checkpoint's replay buffer is on disk and growing (its temporary file, ``common.atomic``), then runs
``train --resume`` and checks that it finished: exit 0, the final model at the run's steps, the evaluations on their
grid. Nothing in the run is slowed or patched: the kill lands in a real write.

    python benchmarks/tools/kill_during_checkpoint.py                   # 3 tries, PointGoal1 from pixels
    python benchmarks/tools/kill_during_checkpoint.py --tries 5 --checkpoint-every 4000 --sim-steps 12000
"""

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

# The benchmarks' shared modules (machine.py)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine import cpu_model

from sb3_dsslac.app.checkpoints import CHECKPOINT_DIR, find_checkpoint
from sb3_dsslac.app.runs import CONFIG_FILE, FINAL_MODEL
from sb3_dsslac.common.atomic import PARTIAL_SUFFIX
from sb3_dsslac.dsslac import DSSLAC


def growing_buffer(folder: Path) -> Path | None:
    """The replay buffer being written in ``folder`` (its temporary file, with bytes on disk), if any."""
    for path in folder.glob(f".dsslac_replay_buffer_*{PARTIAL_SUFFIX}"):
        try:
            if path.stat().st_size > 0:
                return path
        except FileNotFoundError:  # renamed into place since the listing
            continue
    return None


def one_try(args: argparse.Namespace, run_dir: Path, seed: int) -> dict[str, str]:
    """Train, kill while a replay buffer is written, resume; the row of the table."""
    command = [sys.executable, "-m", "sb3_dsslac", "train"]
    flags = ["--env", args.env, "--preset", "cpu", "--sim-steps", str(args.sim_steps), "--seed", str(seed)]
    flags += ["--checkpoint-every", str(args.checkpoint_every), "--eval-every", str(args.eval_every), "--eval-episodes=1"]
    flags += ["--threads=1", "--out", str(run_dir), "--quiet", "--no-progress-bar"]
    row = {"killed while writing": "-", "on disk at the kill": "-", "resumed from": "-", "resume exit": "-"}
    log = run_dir.parent / f"{run_dir.name}.log"
    with log.open("w") as output:
        process = subprocess.Popen([*command, *flags], stdout=output, stderr=subprocess.STDOUT)
        folder, partial, deadline = run_dir / CHECKPOINT_DIR, None, time.monotonic() + args.timeout
        while process.poll() is None and time.monotonic() < deadline:
            if find_checkpoint(run_dir) is not None and (partial := growing_buffer(folder)) is not None:
                process.send_signal(signal.SIGKILL)
                break
            time.sleep(0.002)
        if process.poll() is None and partial is None:  # past the timeout
            process.kill()
        status = process.wait()
    if status != -signal.SIGKILL or partial is None:
        row["killed while writing"] = f"not killed (exit {status}): see {log}"
        return row
    row["killed while writing"] = partial.name.removeprefix(".").rsplit(".", 2)[0]
    row["on disk at the kill"] = f"{partial.stat().st_size / 2**20:.1f} MB" if partial.exists() else "renamed"
    checkpoint = find_checkpoint(run_dir)
    row["resumed from"] = f"{checkpoint.timesteps}" if checkpoint is not None else "none"
    with log.open("a") as output:
        resumed = subprocess.run(
            [*command, "--resume", str(run_dir), "--quiet", "--no-progress-bar"],
            stdout=output,
            stderr=subprocess.STDOUT,
            timeout=args.timeout,
        )
    row["resume exit"] = str(resumed.returncode)
    expected = yaml.safe_load((run_dir / CONFIG_FILE).read_text())["resolved"]["agent_steps"]
    agent_steps = DSSLAC.load(run_dir / FINAL_MODEL).num_timesteps if (run_dir / FINAL_MODEL).exists() else 0
    evaluations = np.load(run_dir / "evaluations.npz")["timesteps"].tolist() if resumed.returncode == 0 else []
    row["final agent steps"] = str(agent_steps)
    row["evaluations at"] = " ".join(map(str, evaluations))
    row["finished"] = "yes" if resumed.returncode == 0 and agent_steps == expected else "no"
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--tries", type=int, default=3)
    parser.add_argument("--env", default="SafetyGym/PointGoal1-v0")
    parser.add_argument("--sim-steps", type=int, default=6000)
    parser.add_argument("--checkpoint-every", type=int, default=2000, help="simulator steps")
    parser.add_argument("--eval-every", type=int, default=3000, help="simulator steps")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds a run or a resume may take")
    parser.add_argument("--out", help="folder of the runs and their logs (default: a temporary one)")
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.out or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for index in range(args.tries):
            start = time.perf_counter()
            row = one_try(args, folder / f"try{index}", seed=index)
            rows.append({"try": str(index), **row, "wall s": f"{time.perf_counter() - start:.0f}"})
            print(" | ".join(rows[-1].values()), flush=True)
    finished = sum(row.get("finished") == "yes" for row in rows)
    print(
        f"\n{cpu_model()}; {args.env}, --preset cpu --sim-steps {args.sim_steps} --checkpoint-every "
        f"{args.checkpoint_every} --eval-every {args.eval_every}; SIGKILL while a replay buffer was written, then "
        "train --resume\n"
    )
    columns = list(dict.fromkeys(name for row in rows for name in row))
    print("| " + " | ".join(columns) + " |\n|" + "---|" * len(columns))
    for row in rows:
        print("| " + " | ".join(row.get(name, "-") for name in columns) + " |")
    print(f"\n{finished} of {len(rows)} resumed and finished")
    if finished < len(rows):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
