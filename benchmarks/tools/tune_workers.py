"""
Seconds per trial of ``python -m sb3_dsslac tune`` with one worker alone and with several workers at once on this
machine (default flags: one torch thread per worker), beside a control: a fixed single-threaded torch workload run
alone and as as many copies at once, which shows how much running side by side costs on this machine whatever runs.

    python benchmarks/tools/tune_workers.py  # 2 workers, a 2,000-step cpu-preset trial each
    python benchmarks/tools/tune_workers.py --workers 2 --timesteps 4000 --threads 2  # the old default of torch's threads

Every sampled keyword that changes a trial's cost is fixed (``--hyperparams``), so all trials do the same work.
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# The benchmarks' shared modules (machine.py)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine import cpu_model

# Same work in every trial: the keywords the sampler would vary that change the time per update
FIXED = ["batch_size=32", "latent_batch_size=16", "sequence_length=4", "n_quantiles=16", "cvar_risk_level=1.0"]
CONTROL = """
import time, torch
torch.set_num_threads(1)
a = torch.randn(256, 256)
start = time.perf_counter()
for _ in range(3000):
    a @ a
sum(i * i for i in range(5_000_000))
print(time.perf_counter() - start)
"""


def run_at_once(commands: list[list[str]], env: dict[str, str]) -> list[float]:
    """Start every command together; the wall seconds of each."""
    start = time.perf_counter()
    processes = [subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE) for command in commands]
    seconds = []
    for process in processes:
        _, stderr = process.communicate()
        if process.returncode != 0:
            raise SystemExit(f"{' '.join(commands[0])} failed:\n{stderr.decode()[-3000:]}")
        seconds.append(time.perf_counter() - start)
    return seconds


def control_seconds(copies: int) -> list[float]:
    """The control workload's own timing in ``copies`` processes at once."""
    processes = [subprocess.Popen([sys.executable, "-c", CONTROL], stdout=subprocess.PIPE) for _ in range(copies)]
    return [float(process.communicate()[0]) for process in processes]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--timesteps", type=int, default=2000, help="simulator steps per trial")
    parser.add_argument("--threads", type=int, help="tune's --threads (default: tune's own default)")
    parser.add_argument("--env", default="SafetyGym/PointGoal1-v0")
    args = parser.parse_args()

    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    with tempfile.TemporaryDirectory() as folder:

        def tune_command(study: str) -> list[str]:
            command = [sys.executable, "-m", "sb3_dsslac", "tune", "--env", args.env, "--preset", "cpu"]
            command += ["--obs-type", "state", "--timesteps", str(args.timesteps), "--n-trials", "1"]
            command += ["--storage", str(Path(folder) / f"{study}.log"), "--study-name", study, "--hyperparams", *FIXED]
            return command + (["--threads", str(args.threads)] if args.threads is not None else [])

        alone = run_at_once([tune_command("alone")], env)
        together = run_at_once([tune_command("together")] * args.workers, env)
    control_alone = control_seconds(1)
    control_together = control_seconds(args.workers)

    cpu = cpu_model()
    threads = args.threads if args.threads is not None else "default (1)"
    print(f"\n{cpu}; tune --preset cpu --obs-type state --timesteps {args.timesteps} --n-trials 1, --threads {threads}\n")
    print(f"| what | one alone, s | each of {args.workers} at once, s | ratio |\n|---|---:|---:|---:|")
    for label, single, several in (
        ("tune trial (wall, process start included)", alone, together),
        ("control: fixed single-thread torch workload", control_alone, control_together),
    ):
        mean = sum(several) / len(several)
        print(f"| {label} | {single[0]:.1f} | {', '.join(f'{s:.1f}' for s in several)} | {mean / single[0]:.2f}x |")


if __name__ == "__main__":
    main()
