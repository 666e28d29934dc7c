"""Random-policy sanity numbers: episode return, cost and goals per episode.

Usage: ``python benchmarks/random_policy.py [--episodes 100] [--ids SafetyGym/PointGoal1-v0 ...]``. A fresh uniform random
action every simulator step (``action_repeat=1``, as the Safety-Gym and Safety-Gymnasium random-policy numbers were
taken), ``obs_type="state"`` (same dynamics as pixels, no rendering), episode ``i`` reset with seed ``i``.
"""

import argparse
import sys
from pathlib import Path

# Run from a checkout without installing.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gymnasium as gym
import numpy as np

import safety_envs  # noqa: F401  (registers the ids)


def evaluate(env_id: str, episodes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-episode (returns, costs, goals met) of a uniform random policy, one action per simulator step."""
    env = gym.make(env_id, obs_type="state", action_repeat=1)
    env.action_space.seed(0)
    stats = np.zeros((episodes, 3))
    for episode in range(episodes):
        env.reset(seed=episode)
        done = False
        while not done:
            _, reward, terminated, truncated, info = env.step(env.action_space.sample())
            stats[episode] += (reward, info["cost"], info["goal_met"])
            done = terminated or truncated
    env.close()
    return stats[:, 0], stats[:, 1], stats[:, 2]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--ids", nargs="+", default=["SafetyGym/PointGoal1-v0"])
    args = parser.parse_args()
    print("| task | episodes | return (mean ± std) | cost (mean ± std) | goals per episode |")
    print("|---|---|---|---|---|")
    for env_id in args.ids:
        returns, costs, goals = evaluate(env_id, args.episodes)
        name = env_id.removeprefix("SafetyGym/").removesuffix("-v0")
        print(
            f"| {name} | {args.episodes} | {returns.mean():.2f} ± {returns.std():.2f} | "
            f"{costs.mean():.1f} ± {costs.std():.1f} | {goals.mean():.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
