"""
DS-SLAC variants on the CPU learning preset: the thesis's risk-neutral DS-SLAC, a CVaR(0.5) safety term, the PID
multiplier, and the Safe SLAC baseline (expectation cost critic), each over several seeds. Prints the final
evaluation reward and cost per variant and saves a table (CSV) and a plot (PNG).

    python benchmarks/variants.py                                  # 3 seeds, 80k agent steps, 2 worker processes
    python benchmarks/variants.py --timesteps 30000 --seeds 0 1    # a quicker look

Each finished run is saved at once (``<out>/variants/<variant>_seed<n>_<timesteps>.npz``); a rerun with the same
settings reuses the saved runs, so a killed benchmark continues where it stopped. Runs go seed by seed, so a partial
benchmark still compares every variant. A run's file may hold per-evaluation means only (``rewards`` and ``costs`` of
shape (n_evaluations, 1)): the table and the plot use only the means.
"""

import argparse
import csv
import re
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
from learning import LearningCurve, train_and_evaluate

VARIANTS: dict[str, dict[str, Any]] = {
    "DS-SLAC (mean)": {},
    "DS-SLAC (CVaR 0.5)": {"cvar_risk_level": 0.5},
    "DS-SLAC (PID)": {"lagrange": "pid"},
    "Safe SLAC": {"cost_critic": "mean"},
}


def run(job: tuple[str, int, str, int, int, int]) -> tuple[str, int, Any]:
    """One variant and seed in a worker process with one torch thread."""
    import torch as th

    variant, seed, env_id, timesteps, eval_freq, eval_episodes = job
    th.set_num_threads(1)
    curve = train_and_evaluate(env_id, "state", timesteps, eval_freq, eval_episodes, seed, **VARIANTS[variant])
    return variant, seed, curve


def run_path(out: Path, variant: str, seed: int, timesteps: int) -> Path:
    """Where one finished run is saved: the name carries the variant, seed and length."""
    slug = re.sub(r"[^a-z0-9]+", "_", variant.lower()).strip("_")
    return out / "variants" / f"{slug}_seed{seed}_{timesteps}.npz"


def save_run(path: Path, curve: LearningCurve) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{field: np.asarray(value) for field, value in vars(curve).items()})


def load_run(path: Path) -> LearningCurve:
    with np.load(path) as data:
        fields = {field: data[field] for field in data.files}
    return LearningCurve(**{**fields, "minutes": float(fields["minutes"]), "cost_limit": float(fields["cost_limit"])})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="SafetyGym/PointGoal1-v0")
    parser.add_argument("--timesteps", type=int, default=80_000, help="agent steps per run")
    parser.add_argument("--eval-freq", type=int, default=10_000, help="agent steps between evaluations")
    parser.add_argument("--eval-episodes", type=int, default=5)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    curves_by_seed: dict[str, dict[int, LearningCurve]] = {variant: {} for variant in args.variants}
    jobs = []
    for seed in args.seeds:
        for variant in args.variants:
            path = run_path(args.out, variant, seed, args.timesteps)
            if path.exists():
                curves_by_seed[variant][seed] = load_run(path)
                print(f"reusing {path}", flush=True)
            else:
                jobs.append((variant, seed, args.env, args.timesteps, args.eval_freq, args.eval_episodes))
    with ProcessPoolExecutor(args.workers) as pool:
        for future in as_completed([pool.submit(run, job) for job in jobs]):
            variant, seed, curve = future.result()
            save_run(run_path(args.out, variant, seed, args.timesteps), curve)
            curves_by_seed[variant][seed] = curve
            final_reward, final_cost = curve.rewards[-1].mean(), curve.costs[-1].mean()
            print(f"done: {variant}, seed {seed}: final reward {final_reward:.2f}, cost {final_cost:.2f}", flush=True)

    curves = {variant: [runs[seed] for seed in sorted(runs)] for variant, runs in curves_by_seed.items()}
    budget = next(iter(curves.values()))[0].cost_limit
    rows = []
    for variant, runs in curves.items():
        final_rewards = np.array([curve.rewards[-1].mean() for curve in runs])
        final_costs = np.array([curve.costs[-1].mean() for curve in runs])
        minutes = np.nanmean([curve.minutes for curve in runs]) if any(np.isfinite(c.minutes) for c in runs) else np.nan
        under_budget = f"{int((final_costs <= budget).sum())}/{len(runs)}"
        per_seed = " ".join(f"{reward:.1f}/{cost:.1f}" for reward, cost in zip(final_rewards, final_costs, strict=True))
        reward, reward_std, cost, cost_std = final_rewards.mean(), final_rewards.std(), final_costs.mean(), final_costs.std()
        rows.append((variant, reward, reward_std, cost, cost_std, minutes, under_budget, per_seed))
    header = f"{'variant':<22}{'final eval reward':>22}{'final eval cost':>22}{'under budget':>14}{'min/run':>9}"
    print(f"\n{args.env} (state), {args.timesteps} agent steps, seeds {args.seeds}, budget {budget:g}")
    print(header)
    for variant, reward, reward_std, cost, cost_std, minutes, under_budget, _ in rows:
        print(
            f"{variant:<22}{reward:>14.2f} ± {reward_std:<5.2f}{cost:>14.2f} ± {cost_std:<5.2f}{under_budget:>14}"
            f"{minutes:>9.1f}"
        )
    print(f"final reward/cost of seeds {sorted(args.seeds)}:")
    for variant, *_, per_seed in rows:
        print(f"  {variant:<22}{per_seed}")
    with open(args.out / "variants.csv", "w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["variant", "reward_mean", "reward_std", "cost_mean", "cost_std", "minutes_per_run", "under_budget"])
        writer.writerows([(row[0], *(f"{value:.4f}" for value in row[1:6]), row[6]) for row in rows])
    plot(args.out / "variants.png", curves, budget)
    print(f"wrote {args.out / 'variants.csv'} and variants.png")


def plot(path: Path, curves: dict[str, list[Any]], budget: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_reward, ax_cost) = plt.subplots(1, 2, figsize=(11, 4))
    for variant, runs in curves.items():
        steps = runs[0].sim_steps
        for ax, field in ((ax_reward, "rewards"), (ax_cost, "costs")):
            per_seed = np.array([getattr(curve, field).mean(axis=1) for curve in runs])
            ax.plot(steps, per_seed.mean(axis=0), marker="o", label=variant)
            ax.fill_between(steps, per_seed.min(axis=0), per_seed.max(axis=0), alpha=0.15)
    ax_cost.axhline(budget, color="red", linestyle="--", label=f"budget {budget:g}")
    for ax, label in ((ax_reward, "reward"), (ax_cost, "cost")):
        ax.set_xlabel("simulator steps")
        ax.set_ylabel(f"evaluation episode {label}")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
