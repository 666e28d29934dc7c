"""
Learning evidence on the CPU: DS-SLAC on a safety_envs task must raise the evaluation reward above the random
policy's while bringing the evaluation episode cost under the budget.

The ``cpu_learning`` preset (vector observations, small networks, sequences of 4, 0.4 updates per agent step) finishes
in under 30 minutes on a 2-core machine. It writes a CSV and a PNG of the evaluation curve and prints a table.

    python benchmarks/learning.py                      # PointGoal1, state observations, 80k agent steps
    python benchmarks/learning.py --timesteps 20000    # a quicker look
"""

import argparse
import ast
import csv
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

import safety_envs  # noqa: F401  (registers the SafetyGym/* ids)
from sb3_dsslac import DSSLAC, CostEvalCallback
from sb3_dsslac.presets import preset_hyperparams


class RecordMultiplier(BaseCallback):
    """Keep the Lagrange multiplier at each evaluation (called by the eval callback after it evaluates)."""

    def __init__(self) -> None:
        super().__init__()
        self.values: list[float] = []

    def _on_step(self) -> bool:
        self.values.append(self.model.lagrange_multiplier)  # type: ignore[attr-defined]
        return True


@dataclass
class LearningCurve:
    """Evaluations of one training run: ``rewards`` and ``costs`` are (n_evaluations, n_episodes)."""

    sim_steps: np.ndarray
    rewards: np.ndarray
    costs: np.ndarray
    multipliers: np.ndarray
    minutes: float
    cost_limit: float


def train_and_evaluate(
    env_id: str, obs_type: str, timesteps: int, eval_freq: int, eval_episodes: int, seed: int, **overrides: Any
) -> LearningCurve:
    """
    Train DS-SLAC with the ``cpu_learning`` preset (``overrides`` on top) and evaluate it every ``eval_freq`` agent steps
    on a separate env seeded ``10_000 + seed`` with the deterministic policy.
    """
    eval_env = gym.make(env_id, obs_type=obs_type)
    eval_env.reset(seed=10_000 + seed)
    multipliers = RecordMultiplier()
    evaluation = CostEvalCallback(
        eval_env, eval_freq=eval_freq, n_eval_episodes=eval_episodes, callback_after_eval=multipliers, verbose=1
    )
    hyperparams = preset_hyperparams("cpu_learning", overrides)
    model = DSSLAC("LatentPolicy", gym.make(env_id, obs_type=obs_type), seed=seed, **hyperparams)
    start = time.time()
    model.learn(timesteps, callback=evaluation)
    return LearningCurve(
        sim_steps=np.array(evaluation.evaluations_timesteps) * model.action_repeat,
        rewards=np.array(evaluation.evaluations_results),
        costs=np.array(evaluation.evaluations_costs),
        multipliers=np.array(multipliers.values),
        minutes=(time.time() - start) / 60,
        cost_limit=model.cost_limit,
    )


def random_policy_results(env_id: str, obs_type: str, n_episodes: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Episode rewards and costs of uniform random actions on the evaluation seeds."""
    env = gym.make(env_id, obs_type=obs_type)
    env.action_space.seed(seed)
    rewards, costs = [], []
    for episode in range(n_episodes):
        env.reset(seed=seed + episode)
        total_reward = total_cost = 0.0
        done = False
        while not done:
            _, reward, terminated, truncated, info = env.step(env.action_space.sample())
            total_reward += float(reward)
            total_cost += float(info["cost"])
            done = terminated or truncated
        rewards.append(total_reward)
        costs.append(total_cost)
    return np.array(rewards), np.array(costs)


def write_csv(path: Path, curve: LearningCurve) -> None:
    with open(path, "w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["sim_steps", "eval_reward_mean", "eval_reward_std", "eval_cost_mean", "eval_cost_std", "lagrange"])
        columns = (curve.rewards.mean(1), curve.rewards.std(1), curve.costs.mean(1), curve.costs.std(1), curve.multipliers)
        for step, *values in zip(curve.sim_steps, *columns, strict=True):
            writer.writerow([int(step), *(f"{value:.4f}" for value in values)])


def plot(path: Path, curve: LearningCurve, random: tuple[np.ndarray, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_reward, ax_cost) = plt.subplots(1, 2, figsize=(10, 3.8))
    panels = ((ax_reward, curve.rewards, random[0], "reward"), (ax_cost, curve.costs, random[1], "cost"))
    for ax, values, baseline, label in panels:
        mean, std = values.mean(axis=1), values.std(axis=1)
        ax.plot(curve.sim_steps, mean, marker="o", label="DS-SLAC")
        ax.fill_between(curve.sim_steps, mean - std, mean + std, alpha=0.25)
        ax.axhline(baseline.mean(), color="gray", linestyle=":", label="random policy")
        ax.set_xlabel("simulator steps")
        ax.xaxis.set_major_formatter(lambda steps, _: f"{steps / 1000:.0f}k")
        ax.set_ylabel(f"evaluation episode {label}")
    ax_cost.axhline(curve.cost_limit, color="red", linestyle="--", label=f"budget {curve.cost_limit:g}")
    ax_reward.legend()
    ax_cost.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="SafetyGym/PointGoal1-v0")
    parser.add_argument("--obs-type", default="state", choices=["state", "pixels"])
    parser.add_argument("--timesteps", type=int, default=80_000, help="agent steps (2 simulator steps each)")
    parser.add_argument("--eval-freq", type=int, default=10_000, help="agent steps between evaluations")
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (small networks run fastest on one; 2 can be 10x slower)"
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="DSSLAC keywords over the preset")
    args = parser.parse_args()
    overrides = {key: ast.literal_eval(value) for key, value in (item.split("=", 1) for item in args.set)}
    th.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = f"learning_{args.env.split('/')[-1].split('-')[0]}_{args.obs_type}_seed{args.seed}"

    curve = train_and_evaluate(
        args.env, args.obs_type, args.timesteps, args.eval_freq, args.eval_episodes, args.seed, **overrides
    )
    random = random_policy_results(args.env, args.obs_type, 10, 10_000 + args.seed)
    write_csv(args.out / f"{stem}.csv", curve)
    plot(args.out / f"{stem}.png", curve, random)

    print(f"\n{args.env} ({args.obs_type}), seed {args.seed}: {args.timesteps} agent steps in {curve.minutes:.1f} min")
    print(f"preset cpu_learning with {overrides or 'no overrides'}")
    print(f"{'policy':<28}{'eval reward':>16}{'eval cost':>16}")
    rows = [("random (10 episodes)", *random)]
    rows += [(f"DS-SLAC @ {s:,} sim steps", r, c) for s, r, c in zip(curve.sim_steps, curve.rewards, curve.costs, strict=True)]
    for label, reward, cost in rows:
        print(f"{label:<28}{reward.mean():>9.2f} ± {reward.std():<5.2f}{cost.mean():>9.2f} ± {cost.std():.2f}")
    print(f"budget {curve.cost_limit:g}; final Lagrange multiplier {curve.multipliers[-1]:.3f}")
    print(f"wrote {args.out / stem}.csv and .png")


if __name__ == "__main__":
    main()
