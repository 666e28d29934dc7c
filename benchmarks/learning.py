"""
Learning evidence: DS-SLAC on a safety_envs task must raise the evaluation reward above the random policy's while
bringing the evaluation episode cost under the budget.

Every seed is a `python -m sb3_dsslac train` run in its own process with one torch thread (``--parallel`` at once),
checkpointed every ``--checkpoint-every`` simulator steps. The benchmark is resumable: started again after any stop,
it continues each unfinished seed from its last checkpoint and reuses the finished ones; a finished seed asked
for more ``--sim-steps`` than it ran is extended from its last checkpoint. It writes, under
``benchmarks/results/learning_<task>_<obs>_<preset>/`` (plus ``_<key>_<value>`` per ``--hyperparams`` override), a CSV
per seed, ``curves.png`` (reward and cost against simulator steps: each seed, their mean, the budget and the random
policy's level; and each seed's Lagrange multiplier), ``table.md`` (with each seed's wall and CPU minutes and the
normalised scores of thesis Eq. 5.1) and ``seed<S>_run/``, each seed's record without its weights (``config.yaml``,
``progress.csv``, ``evaluations.npz``, ``time_account.json``, ``wall_minutes.json``: small enough to commit, and what
``python -m sb3_dsslac plot`` reads to compare tasks). On
pixels it also shows what the first seed's agent sees and believes: ``beliefs.png`` (frames beside the latent model's
reconstructions, with the predicted probability of cost) and ``episode.mp4`` (an evaluation episode,
first-person beside third-person).

    python benchmarks/learning.py                                           # cpu_learning, state, 160k steps, seed 0
    python benchmarks/learning.py --seeds 0 1 2 --parallel 2                # three seeds, two at a time
    python benchmarks/learning.py --preset cpu_pixels --obs-type pixels --sim-steps 300000 --seeds 0 1 2 --parallel 2
    python benchmarks/learning.py ... --sim-steps 600000 --report-at 300000    # the table at 600k, and at 300k
    python benchmarks/learning.py ... --report-only                             # the table of stopped runs, as they stand

``train_and_evaluate`` trains one seed in this process (the variants benchmark uses it).
"""

import argparse
import csv
import json
import resource
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import IO, Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

import safety_envs  # noqa: F401  (registers the SafetyGym/* ids)
from sb3_dsslac import DSSLAC, CostEvalCallback
from sb3_dsslac.app.beliefs import episode_beliefs, mean_cost_probabilities, plot_beliefs
from sb3_dsslac.app.plotting import RunResults, load_run, score_table, task_name
from sb3_dsslac.app.rollouts import evaluate
from sb3_dsslac.app.runs import FINAL_MODEL, find_checkpoint, load_config, read_time_account
from sb3_dsslac.common.envs import make_env
from sb3_dsslac.common.evaluation import eval_policy_name
from sb3_dsslac.common.timing import ACTIVITIES
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


def random_policy_results(
    env_id: str, obs_type: str, env_kwargs: dict[str, Any], n_episodes: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Episode rewards and costs of uniform random actions on the evaluation seeds, in the runs' env settings."""
    env = make_env(env_id, obs_type, env_kwargs=env_kwargs)
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


# ----------------------------------------------------------------------------------------------------------------------
# Several seeds, each a resumable `python -m sb3_dsslac train` run in its own process
# ----------------------------------------------------------------------------------------------------------------------

RUNS_DIR = "runs"
TIMING_FILE = "wall_minutes.json"
# A run folder's files that make its record: everything but the weights, the replay buffer and the TensorBoard events
RECORD_FILES = ("config.yaml", "progress.csv", "evaluations.npz", "time_account.json", TIMING_FILE)


def seed_state(run_dir: Path, sim_steps: int) -> str:
    """
    ``"finished"`` (the final model of at least ``sim_steps`` simulator steps is there), ``"resume"`` (a checkpoint to
    continue from: a stopped run, or a finished one asked for more steps) or ``"fresh"``.
    """
    if (run_dir / FINAL_MODEL).is_file() and load_config(run_dir).sim_steps >= sim_steps:
        return "finished"
    if (run_dir / "config.yaml").is_file() and find_checkpoint(run_dir) is not None:
        return "resume"
    return "fresh"


def seed_command(run_dir: Path, seed: int, args: argparse.Namespace) -> list[str]:
    """The ``train`` command of one seed: a fresh run (an unfinished one without a checkpoint is redone) or a resume."""
    train = [sys.executable, "-m", "sb3_dsslac", "train", "--quiet", "--no-progress-bar"]
    if seed_state(run_dir, args.sim_steps) == "resume":
        return [*train, "--resume", str(run_dir), "--sim-steps", str(args.sim_steps)]
    if run_dir.exists():
        shutil.rmtree(run_dir)  # stopped before its first checkpoint: nothing to continue from
    command = [*train, "--env", args.env, "--obs-type", args.obs_type, "--preset", args.preset, "--seed", str(seed)]
    command += ["--sim-steps", str(args.sim_steps), "--eval-every", str(args.eval_every)]
    command += ["--eval-episodes", str(args.eval_episodes), "--checkpoint-every", str(args.checkpoint_every)]
    command += ["--threads", "1", "--out", str(run_dir)]
    command += ["--env-kwargs", *args.env_kwargs] if args.env_kwargs else []
    return command + (["--hyperparams", *args.hyperparams] if args.hyperparams else [])


def run_seeds(args: argparse.Namespace, runs_root: Path) -> None:
    """
    Run every unfinished seed, ``args.parallel`` at a time; a stop (Ctrl-C, SIGTERM) ends them all. A seed that fails
    does not stop the others: the benchmark exits with an error naming it once they have ended.
    """
    pending = [seed for seed in args.seeds if seed_state(runs_root / f"seed{seed}", args.sim_steps) != "finished"]
    failed: dict[int, int] = {}
    for seed in sorted(set(args.seeds) - set(pending)):
        print(f"seed {seed}: finished earlier, reused")
    running: dict[int, tuple[subprocess.Popen, float, IO[str]]] = {}
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    try:
        while pending or running:
            while pending and len(running) < args.parallel:
                seed = pending.pop(0)
                run_dir = runs_root / f"seed{seed}"
                command = seed_command(run_dir, seed, args)
                print(f"seed {seed}: {'resuming' if '--resume' in command else 'starting'} ({' '.join(command[2:])})")
                log = open(runs_root / f"seed{seed}.log", "a")  # closed when its process ends
                running[seed] = (subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT), time.time(), log)
            time.sleep(args.poll)
            for seed, (process, started, log) in list(running.items()):
                cpu_before = children_cpu_seconds()
                if process.poll() is None:  # reaped when it ended: its CPU time joins the children's
                    continue
                del running[seed]
                log.close()
                run_dir = runs_root / f"seed{seed}"
                add_minutes(run_dir, (time.time() - started) / 60, (children_cpu_seconds() - cpu_before) / 60)
                if process.returncode != 0:
                    failed[seed] = process.returncode
                    print(f"seed {seed}: failed (exit {process.returncode}), the others go on")
                    continue
                wall, cpu = read_minutes(run_dir)
                print(f"seed {seed}: finished, {wall:.1f} wall and {cpu:.1f} CPU minutes in all")
    finally:
        for process, _, _ in running.values():
            process.terminate()
        for seed, (process, started, log) in running.items():
            cpu_before = children_cpu_seconds()
            process.wait()
            log.close()
            add_minutes(runs_root / f"seed{seed}", (time.time() - started) / 60, (children_cpu_seconds() - cpu_before) / 60)
    if failed:
        logs = ", ".join(f"seed {seed} (exit {code}): {runs_root / f'seed{seed}.log'}" for seed, code in failed.items())
        raise SystemExit(f"failed: {logs}; run the benchmark again to resume them from their last checkpoints")


def add_minutes(run_dir: Path, wall: float, cpu: float) -> None:
    """Add one process's wall and CPU minutes to the run's totals (a resumed run adds up its sessions)."""
    if run_dir.is_dir():
        totals = read_minutes(run_dir)
        (run_dir / TIMING_FILE).write_text(json.dumps({"minutes": totals[0] + wall, "cpu_minutes": totals[1] + cpu}))


def read_minutes(run_dir: Path) -> tuple[float, float]:
    """The run's wall and CPU minutes so far (CPU minutes: user + system time of its processes)."""
    path = run_dir / TIMING_FILE
    saved = json.loads(path.read_text()) if path.is_file() else {}
    return float(saved.get("minutes", 0.0)), float(saved.get("cpu_minutes", 0.0))


def run_minutes(run_dir: Path) -> tuple[float, float]:
    """
    The run's wall and CPU minutes by its time account, which its checkpoints carry, so a stop that kills every
    process loses nothing; the benchmark's own count of its processes (``read_minutes``) for a run without one.
    """
    account = read_time_account(run_dir)
    return (account["wall"] / 60, account["cpu"] / 60) if account is not None else read_minutes(run_dir)


def children_cpu_seconds() -> float:
    """User + system seconds of every child process reaped so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def keep_record(run_dir: Path, record_dir: Path) -> None:
    """Copy the ``RECORD_FILES`` the run has into ``record_dir`` (created), replacing older copies."""
    record_dir.mkdir(parents=True, exist_ok=True)
    for name in RECORD_FILES:
        if (run_dir / name).is_file():
            shutil.copy2(run_dir / name, record_dir / name)


def random_level(args: argparse.Namespace, out: Path, env_kwargs: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """
    The random policy's episode rewards and costs on the evaluation seeds with the runs' env keywords (action repeat,
    frame size), kept in ``out`` and computed again when those keywords change.
    """
    path = out / "random_policy.json"
    if path.is_file():
        saved = json.loads(path.read_text())
        if saved.get("env_kwargs") == env_kwargs and len(saved["rewards"]) == args.random_episodes:
            return np.array(saved["rewards"]), np.array(saved["costs"])
    rewards, costs = random_policy_results(args.env, args.obs_type, env_kwargs, args.random_episodes, 10_000)
    path.write_text(json.dumps({"env_kwargs": env_kwargs, "rewards": rewards.tolist(), "costs": costs.tolist()}))
    return rewards, costs


def write_seed_csv(path: Path, run: RunResults) -> None:
    """One row per evaluation: simulator steps, mean and std of the episode rewards and costs."""
    with open(path, "w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["sim_steps", "eval_reward_mean", "eval_reward_std", "eval_cost_mean", "eval_cost_std"])
        columns = (run.rewards.mean(1), run.rewards.std(1), run.costs.mean(1), run.costs.std(1))
        for step, *values in zip(run.sim_steps, *columns, strict=True):
            writer.writerow([int(step), *(f"{value:.4f}" for value in values)])


def read_multiplier(run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """The Lagrange multiplier logged during training, and the simulator steps at which it was logged."""
    import pandas as pd

    progress = pd.read_csv(run_dir / "progress.csv")
    if "train/lagrange_multiplier" not in progress:
        return np.zeros(0), np.zeros(0)
    logged = progress[["time/sim_steps", "train/lagrange_multiplier"]].dropna()
    return logged["time/sim_steps"].to_numpy(), logged["train/lagrange_multiplier"].to_numpy()


def plot_seeds(
    path: Path,
    runs: dict[int, RunResults],
    random: tuple[np.ndarray, np.ndarray],
    multipliers: dict[int, tuple[np.ndarray, np.ndarray]],
    title: str,
) -> None:
    """
    Reward and cost against simulator steps (each seed thin, their mean bold, the budget and the random level), and
    each seed's Lagrange multiplier.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_reward, ax_cost, ax_multiplier) = plt.subplots(1, 3, figsize=(14, 3.8))
    n_evals = min(len(run.sim_steps) for run in runs.values())
    steps = next(iter(runs.values())).sim_steps[:n_evals]
    for ax, field, baseline, label in ((ax_reward, "rewards", random[0], "reward"), (ax_cost, "costs", random[1], "cost")):
        means = np.stack([getattr(run, field).mean(axis=1)[:n_evals] for run in runs.values()])
        for seed, values in zip(runs, means, strict=True):
            ax.plot(steps, values, linewidth=0.8, alpha=0.6, label=f"seed {seed}")
        ax.plot(steps, means.mean(axis=0), color="black", linewidth=2.2, marker="o", label="mean over seeds")
        ax.axhline(baseline.mean(), color="gray", linestyle=":", label="random policy")
        ax.set_ylabel(f"evaluation episode {label}")
    budget = next(iter(runs.values())).cost_limit
    ax_cost.axhline(budget, color="red", linestyle="--", label=f"budget {budget:g}")
    for seed, (logged_steps, values) in multipliers.items():
        ax_multiplier.plot(logged_steps, values, linewidth=0.8, label=f"seed {seed}")
    ax_multiplier.set_ylabel("Lagrange multiplier (training)")
    for ax in (ax_reward, ax_cost, ax_multiplier):
        ax.set_xlabel("simulator steps")
        ax.xaxis.set_major_formatter(lambda value, _: f"{value / 1000:.0f}k")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


LATE_EVALUATIONS = 3  # the table's late level: the last evaluations of each seed, pooled


def summary_table(
    runs: dict[int, RunResults], random: tuple[np.ndarray, np.ndarray], minutes: dict[int, tuple[float, float]] | None
) -> str:
    """
    Markdown: each seed's final evaluation and its late level (the last evaluations' episodes pooled), their mean and
    sample std over seeds, and the random policy; each seed's wall and CPU minutes when ``minutes`` has them.
    """
    lines = [
        f"| policy | sim steps | eval reward | eval cost | reward, last {LATE_EVALUATIONS} evals "
        f"| cost, last {LATE_EVALUATIONS} evals | wall minutes | CPU minutes |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    levels = []
    for seed, run in runs.items():
        level = (run.rewards[-1].mean(), run.costs[-1].mean())
        level += (run.rewards[-LATE_EVALUATIONS:].mean(), run.costs[-LATE_EVALUATIONS:].mean())
        levels.append(level)
        wall, cpu = (f"{value:.1f}" for value in minutes[seed]) if minutes else ("-", "-")
        lines.append(
            f"| DS-SLAC, seed {seed} | {int(run.sim_steps[-1]):,} | {level[0]:.2f} | {level[1]:.1f} | {level[2]:.2f} "
            f"| {level[3]:.1f} | {wall} | {cpu} |"
        )
    means = np.mean(levels, axis=0)
    stds = np.std(levels, axis=0, ddof=1) if len(levels) > 1 else np.zeros_like(means)
    lines.append(
        f"| DS-SLAC, mean ± sample std of {len(levels)} seeds | | {means[0]:.2f} ± {stds[0]:.2f} "
        f"| {means[1]:.1f} ± {stds[1]:.1f} | {means[2]:.2f} ± {stds[2]:.2f} | {means[3]:.1f} ± {stds[3]:.1f} | | |"
    )
    lines.append(f"| random policy ({len(random[0])} episodes) | | {random[0].mean():.2f} | {random[1].mean():.1f} | | | | |")
    return "\n".join(lines)


def protocol_note(run: RunResults) -> str:
    """What an evaluation is, what the late level pools, and what the minutes count."""
    return (
        f"Each evaluation: {run.rewards.shape[1]} episodes of a separate env, {run.eval_policy} policy "
        f"(`train`'s default protocol); budget {run.cost_limit:g}. The last {LATE_EVALUATIONS} evaluations "
        f"({LATE_EVALUATIONS * run.rewards.shape[1]} episodes) show each seed's level with less of one "
        "evaluation's noise. The minutes are each seed's time account (`time_account.json`, carried in its checkpoints): "
        "every simulator step counted once across resumes, without the steps a run redid after a stop."
    )


def truncated(run: RunResults, sim_steps: int) -> RunResults:
    """The run as it stood at ``sim_steps``: its evaluations up to and including that step."""
    kept = run.sim_steps <= sim_steps
    if not kept.any():
        raise SystemExit(f"{run.path} has no evaluation at or before {sim_steps:,} simulator steps (--report-at)")
    return replace(run, sim_steps=run.sim_steps[kept], rewards=run.rewards[kept], costs=run.costs[kept])


def normalised_line(runs: dict[int, RunResults]) -> str:
    """
    A sentence with the seeds' normalised (Jr, Jc) of thesis Eq. 5.1 over the last evaluations and at the final one,
    beside the thesis's DS-SLAC and LAMBDA (Table 5.1, 1M simulator steps); empty for a task without a PPO reference.
    """
    row = score_table(list(runs.values()), late_evaluations=LATE_EVALUATIONS).iloc[0]
    if np.isnan(row["Jr_bar"]):
        return ""

    def pair(reward: float, cost: float) -> str:
        return "-" if np.isnan(reward) else f"({reward:.3f}, {cost:.3f})"

    return (
        f"Normalised (Jr, Jc) of thesis Eq. 5.1 (against the unconstrained PPO of As et al., 2022), mean over seeds: "
        f"{pair(row['Jr_bar_late'], row['Jc_bar_late'])} over the last {LATE_EVALUATIONS} evaluations, "
        f"{pair(row['Jr_bar'], row['Jc_bar'])} at the final one, at {int(row['sim_steps']):,} simulator steps; "
        f"the thesis's DS-SLAC {pair(row['thesis_Jr_bar'], row['thesis_Jc_bar'])} and LAMBDA "
        f"{pair(row['lambda_Jr_bar'], row['lambda_Jc_bar'])} at 1M (Table 5.1)."
    )


# A logged update's KL above this is a latent-model spike (normal runs sit at 40-70)
SPIKE_KL = 1_000.0


def health_table(runs_root: Path, multipliers: dict[int, tuple[np.ndarray, np.ndarray]]) -> str:
    """
    Markdown: each seed's latent-model health from its ``progress.csv``: the largest KL of an update (``train/kl_max``,
    the extreme over every update; ``train/kl``, a burst mean, in runs from before it was logged), how many logged
    rows passed ``SPIKE_KL``, the largest |z|, and the multiplier's final value (``multipliers``, from ``read_multiplier``).
    """
    import pandas as pd

    lines = [
        f"| seed | largest KL of an update | logged rows with KL > {SPIKE_KL:,.0f} | largest abs z | final multiplier |",
        "|---|---:|---:|---:|---:|",
    ]
    for seed, (_, multiplier) in multipliers.items():
        progress = pd.read_csv(runs_root / f"seed{seed}" / "progress.csv")
        kl = progress["train/kl_max" if "train/kl_max" in progress else "train/kl"].dropna()
        if kl.empty:
            continue
        z = progress["train/z_abs_max"].max() if "train/z_abs_max" in progress else float("nan")
        final = f"{multiplier[-1]:.3f}" if multiplier.size else "-"
        lines.append(f"| {seed} | {kl.max():.4g} | {int((kl > SPIKE_KL).sum())} | {z:.3g} | {final} |")
    return "" if len(lines) == 2 else "The latent model's health, from each seed's `progress.csv`:\n\n" + "\n".join(lines)


def time_account_table(runs_root: Path, seeds: list[int]) -> str:
    """Markdown: each seed's wall minutes by activity (its ``time_account.json``) and their share of its wall time."""
    columns = [*ACTIVITIES, "other"]
    lines = [
        "| seed | " + " | ".join(name.replace("_", " ") for name in columns) + " | wall | process CPU |",
        "|---|" + "---:|" * (len(columns) + 2),
    ]
    for seed in seeds:
        account = read_time_account(runs_root / f"seed{seed}")
        if account is None:
            continue
        wall = max(account["wall"], 1e-9)
        cells = [f"{account[name] / 60:.1f} ({account[name] / wall:.0%})" for name in columns]
        lines.append(f"| {seed} | " + " | ".join(cells) + f" | {wall / 60:.1f} | {account['cpu'] / 60:.1f} |")
    if len(lines) == 2:
        return ""
    return "Minutes (share of the wall time) by activity, from each seed's `time_account.json`:\n\n" + "\n".join(lines)


def write_pictures(out: Path, run_dir: Path, episode_seed: int) -> str:
    """
    ``beliefs.png`` and ``episode.mp4`` of the run's final model (a stopped run's last checkpoint) on one evaluation
    episode, with the policy its evaluations used (a car's mean action can stand still where its sampled actions drive);
    a line saying so.
    """
    config = load_config(run_dir)
    checkpoint = find_checkpoint(run_dir)
    final = run_dir / FINAL_MODEL
    model = DSSLAC.load(final if final.is_file() or checkpoint is None else checkpoint.model, device="cpu")
    deterministic = config.eval_deterministic
    beliefs = episode_beliefs(model, config.env, seed=episode_seed, deterministic=deterministic, env_kwargs=config.env_kwargs)
    plot_beliefs(beliefs, out / "beliefs.png")
    on_costly, on_free = mean_cost_probabilities(beliefs)
    results = evaluate(
        model, config.env, episodes=1, deterministic=deterministic, seed=episode_seed, video=out / "episode.mp4",
        obs_type="pixels", env_kwargs=config.env_kwargs,
    )  # fmt: skip
    policy = eval_policy_name(deterministic)
    return (
        f"{run_dir.name}, evaluation episode {episode_seed}, {policy} policy: beliefs.png's episode reward "
        f"{beliefs.rewards.sum():.2f}, cost {beliefs.costs.sum():g}, predicted p(cost) {on_costly:.3f} on its costly "
        f"steps and {on_free:.3f} on the others; episode.mp4's (its own draw of the actions) reward "
        f"{results.rewards[0]:.2f}, cost {results.costs[0]:g}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="SafetyGym/PointGoal1-v0")
    parser.add_argument("--obs-type", default="state", choices=["state", "pixels"])
    parser.add_argument("--preset", default="cpu_learning", help="a preset of sb3_dsslac.presets")
    parser.add_argument("--sim-steps", type=int, default=160_000, help="simulator steps per seed")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--parallel", type=int, default=2, help="seeds running at once, one process and thread each")
    parser.add_argument("--eval-every", type=int, default=20_000, help="simulator steps between evaluations")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--checkpoint-every", type=int, default=20_000, help="simulator steps between checkpoints")
    parser.add_argument("--hyperparams", nargs="*", default=[], metavar="KEY=VALUE", help="DSSLAC keywords (YAML)")
    parser.add_argument(
        "--env-kwargs", nargs="*", default=[], metavar="KEY=VALUE", help="env keywords (YAML) on top of the preset's"
    )
    parser.add_argument("--random-episodes", type=int, default=10)
    parser.add_argument(
        "--report-at", type=int, nargs="*", default=[], metavar="SIM_STEPS",
        help="also tabulate the seeds as they stood at these simulator steps (e.g. 300000 for runs of 600k)",
    )  # fmt: skip
    parser.add_argument(
        "--no-pictures", action="store_true", help="on pixels, skip beliefs.png and episode.mp4 of the first seed"
    )
    parser.add_argument(
        "--report-only", action="store_true",
        help="tabulate the seeds as they stand, stopped ones included (their evaluations so far), training nothing",
    )  # fmt: skip
    parser.add_argument("--poll", type=float, default=5.0, help="seconds between checks on the running seeds")
    parser.add_argument(
        "--out", type=Path, help="results folder (default benchmarks/results/learning_<task>_<obs>_<preset>[_<key>_<value>])"
    )
    args = parser.parse_args()
    # Overrides name the folder and the title too: a variant never overwrites its preset's results
    variant = "".join(f"_{setting.replace('=', '_')}" for setting in [*args.env_kwargs, *args.hyperparams])
    name = f"learning_{task_name(args.env)}_{args.obs_type}_{args.preset}{variant}"
    out = args.out or Path("benchmarks/results") / name
    runs_root = out / RUNS_DIR
    runs_root.mkdir(parents=True, exist_ok=True)

    if not args.report_only:
        run_seeds(args, runs_root)
    runs = {seed: load_run(runs_root / f"seed{seed}") for seed in args.seeds}
    random = random_level(args, out, load_config(runs_root / f"seed{args.seeds[0]}").env_kwargs)
    for seed, run in runs.items():
        write_seed_csv(out / f"seed{seed}.csv", run)
        keep_record(runs_root / f"seed{seed}", out / f"seed{seed}_run")
    overrides = f" with {' '.join([*args.env_kwargs, *args.hyperparams])}" if args.env_kwargs or args.hyperparams else ""
    title = f"{task_name(args.env)} ({args.obs_type}), preset {args.preset}{overrides}, {len(runs)} seeds"
    reached = sorted({int(run.sim_steps[-1]) for run in runs.values()})
    if reached[0] < args.sim_steps:
        title += f", stopped at {' and '.join(f'{steps:,}' for steps in reached)} of {args.sim_steps:,} simulator steps"
    multipliers = {seed: read_multiplier(runs_root / f"seed{seed}") for seed in args.seeds}
    plot_seeds(out / "curves.png", runs, random, multipliers, title)
    minutes = {seed: run_minutes(runs_root / f"seed{seed}") for seed in args.seeds}
    table = summary_table(runs, random, minutes) + "\n\n" + protocol_note(next(iter(runs.values())))
    for extra in (normalised_line(runs), health_table(runs_root, multipliers), time_account_table(runs_root, args.seeds)):
        table += f"\n\n{extra}" if extra else ""
    for sim_steps in args.report_at:
        earlier = {seed: truncated(run, sim_steps) for seed, run in runs.items()}
        table += f"\n\nThe same seeds at {sim_steps:,} simulator steps (their evaluations up to it):\n\n"
        table += summary_table(earlier, random, None) + f"\n\n{normalised_line(earlier)}".rstrip()
    (out / "table.md").write_text(f"{title}\n\n{table}\n")
    print(f"\n{title}\n\n{table}\n\nwrote {out}/seed<S>.csv, curves.png, table.md")
    if args.obs_type == "pixels" and not args.no_pictures:
        print(write_pictures(out, runs_root / f"seed{args.seeds[0]}", episode_seed=10_000))
        print(f"wrote {out}/beliefs.png, episode.mp4")


if __name__ == "__main__":
    main()
