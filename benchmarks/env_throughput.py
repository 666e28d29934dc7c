"""Agent steps per second of every ``SafetyGym/*`` id, single env and with 2 ``SubprocVecEnv`` workers.

Usage: ``python benchmarks/env_throughput.py [--steps N] [--quick] [--ids SafetyGym/PointButton1-v0 ...]``. Actions are
uniform random; one agent step is ``action_repeat`` (2) simulator steps. Prints a markdown table.
"""

import argparse
import os
import sys
import time
from pathlib import Path

# Run from a checkout without installing: make the repository importable here and in the workers.
ROOT = str(Path(__file__).resolve().parents[1])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [ROOT, os.environ.get("PYTHONPATH")]))

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from stable_baselines3.common.vec_env import SubprocVecEnv  # noqa: E402

import safety_envs  # noqa: E402


def single_env_rate(env_id: str, obs_type: str, steps: int) -> tuple[float, float]:
    """Agent steps per wall-clock second and per CPU second of one env stepped in this process (resets included).

    The CPU-time rate is what one idle core would give; it is less sensitive to other load on the machine.
    """
    env = gym.make(env_id, obs_type=obs_type)
    env.reset(seed=0)
    env.action_space.seed(0)
    actions = [env.action_space.sample() for _ in range(steps)]
    start, cpu_start = time.perf_counter(), time.process_time()
    for action in actions:
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            env.reset()
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    env.close()
    return steps / wall, steps / cpu


def vec_env_rate(env_id: str, obs_type: str, steps: int, n_envs: int = 2) -> float:
    """Agent steps per second summed over ``n_envs`` SubprocVecEnv workers (start-up excluded)."""
    vec_env = SubprocVecEnv([lambda: gym.make(f"safety_envs:{env_id}", obs_type=obs_type) for _ in range(n_envs)])
    vec_env.seed(0)
    vec_env.reset()
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(steps // n_envs, n_envs, *vec_env.action_space.shape)).astype(np.float32)
    vec_env.step(actions[0])  # warm-up
    start = time.perf_counter()
    for action in actions:
        vec_env.step(action)
    rate = len(actions) * n_envs / (time.perf_counter() - start)
    vec_env.close()
    return rate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=2000, help="agent steps per measurement")
    parser.add_argument("--quick", action="store_true", help="200 steps per measurement, Goal1 ids only")
    parser.add_argument("--ids", nargs="+", help="ids to measure (default: every registered id)")
    args = parser.parse_args()
    steps = 200 if args.quick else args.steps
    ids = args.ids or [env_id for env_id in safety_envs.env_ids() if not args.quick or "Goal1" in env_id]
    unknown = sorted(set(ids) - set(safety_envs.env_ids()))
    if unknown:
        parser.error(f"unknown ids {unknown}; registered: {safety_envs.env_ids()}")

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"MUJOCO_GL={os.environ.get('MUJOCO_GL')}, LP_NUM_THREADS={os.environ.get('LP_NUM_THREADS')}, "
        f"{os.cpu_count()} CPUs, load average {load:.1f}, {steps} agent steps per cell (action_repeat=2)"
    )
    print()
    print("| id | obs | 1 env (steps/s) | 1 env (steps/CPU-s) | 2 x SubprocVecEnv (steps/s) |")
    print("|---|---|---:|---:|---:|")
    for env_id in ids:
        for obs_type in ("pixels", "state"):
            single, single_cpu = single_env_rate(env_id, obs_type, steps)
            vec = vec_env_rate(env_id, obs_type, steps)
            print(f"| {env_id} | {obs_type} | {single:,.0f} | {single_cpu:,.0f} | {vec:,.0f} |", flush=True)


if __name__ == "__main__":
    main()
