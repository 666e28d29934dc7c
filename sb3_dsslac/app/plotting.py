"""Learning curves and the thesis's normalised score table (Eq. 5.1, Table 5.1) from run folders."""

import re
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from sb3_dsslac.common.evaluation import (
    PPO_REFERENCE,
    THESIS_DSSLAC_SCORES,
    THESIS_LAMBDA_SCORES,
    eval_policy_name,
    normalised_scores,
)
from sb3_dsslac.app.runs import CONFIG_FILE, load_config


@dataclass
class RunResults:
    """
    The evaluations of one run.

    :param path: the run folder
    :param env: env id
    :param cost_limit: the episode cost budget
    :param sim_steps: (n_evals,) simulator steps of each evaluation
    :param rewards: (n_evals, n_episodes) episode rewards
    :param costs: (n_evals, n_episodes) episode costs
    :param eval_policy: "stochastic" (the thesis's protocol) or "deterministic", from the run's config
    """

    path: Path
    env: str
    cost_limit: float
    sim_steps: np.ndarray
    rewards: np.ndarray
    costs: np.ndarray
    eval_policy: str


def load_run(run_dir: str | Path) -> RunResults:
    """Read ``evaluations.npz`` and ``config.yaml`` of a run folder."""
    run_dir = Path(run_dir)
    config = load_config(run_dir)
    path = run_dir / "evaluations.npz"
    if not path.is_file():
        raise FileNotFoundError(f"{run_dir} has no evaluations.npz yet (no evaluation finished)")
    resolved = yaml.safe_load((run_dir / CONFIG_FILE).read_text())["resolved"]
    with np.load(path) as data:
        return RunResults(
            path=run_dir,
            env=config.env,
            cost_limit=float(resolved["dsslac"].get("cost_limit", 25.0)),
            sim_steps=data["timesteps"] * int(resolved["action_repeat"]),
            rewards=np.asarray(data["results"], dtype=float),
            costs=np.asarray(data["costs"], dtype=float),
            eval_policy=eval_policy_name(config.eval_deterministic),
        )


def task_name(env_id: str) -> str:
    """``SafetyGym/PointGoal1-v0`` -> ``PointGoal1`` (the env id itself when it is no Safety-Gym task)."""
    match = re.search(r"(Point|Car|Doggo)(Goal|Button|Push)\d", env_id)
    return match.group(0) if match else env_id


def _by_env(runs: list[RunResults]) -> dict[str, list[RunResults]]:
    groups: dict[str, list[RunResults]] = defaultdict(list)
    for run in runs:
        groups[run.env].append(run)
    return dict(groups)


def _curves(runs: list[RunResults], values: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """Mean and spread over the runs of the per-evaluation means, on the evaluations all runs have."""
    steps = runs[0].sim_steps
    for run in runs[1:]:
        steps = np.intersect1d(steps, run.sim_steps)
    means = np.stack([getattr(run, values)[np.isin(run.sim_steps, steps)].mean(axis=1) for run in runs])
    if len(runs) > 1:
        return steps, means.mean(axis=0), means.std(axis=0), f"mean ± std over {len(runs)} runs"
    per_episode = getattr(runs[0], values)[np.isin(runs[0].sim_steps, steps)]
    return steps, means[0], per_episode.std(axis=1), "mean ± std over evaluation episodes"


def plot_learning_curves(runs: list[RunResults], path: str | Path) -> Path:
    """
    Eval reward and cost against simulator steps, one row per env, the cost budget drawn as a dashed line.

    :param runs: the runs (runs of one env are averaged)
    :param path: the PNG file
    :return: the PNG file
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = _by_env(runs)
    figure, axes = plt.subplots(len(groups), 2, figsize=(10, 3.5 * len(groups)), squeeze=False)
    for row, (env, env_runs) in enumerate(groups.items()):
        for col, (values, label) in enumerate((("rewards", "episode reward"), ("costs", "episode cost"))):
            steps, mean, spread, how = _curves(env_runs, values)
            axis = axes[row, col]
            axis.plot(steps, mean, marker="o", markersize=3, label=f"DS-SLAC ({how})")
            axis.fill_between(steps, mean - spread, mean + spread, alpha=0.25)
            if values == "costs":
                axis.axhline(env_runs[0].cost_limit, color="red", linestyle="--", label=f"budget {env_runs[0].cost_limit:g}")
            axis.set_title(f"{task_name(env)}: {label}")
            axis.set_xlabel("simulator steps")
            axis.set_ylabel(label)
            axis.grid(alpha=0.3)
            axis.legend(fontsize=8)
    figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return path


def score_table(runs: list[RunResults], late_evaluations: int = 3) -> pd.DataFrame:
    """
    Each env's runs at the final evaluation and over their last ``late_evaluations`` evaluations pooled (``*_late``:
    less of one evaluation's noise): mean episode reward Jr and cost Jc (over episodes, then runs), their normalised
    scores (Eq. 5.1, against the unconstrained PPO of ``PPO_REFERENCE``), and the thesis's Table 5.1 scores of DS-SLAC
    and LAMBDA. Envs without a PPO reference get NaN scores. ``eval`` is the runs' evaluation policy ("stochastic", the
    thesis's protocol, or "deterministic"; "mixed" when the runs of an env differ).
    """
    rows = []
    for env, env_runs in _by_env(runs).items():
        task = task_name(env)
        budget = env_runs[0].cost_limit
        levels = {}
        for suffix, last in (("", 1), ("_late", late_evaluations)):
            reward = float(np.mean([run.rewards[-last:].mean() for run in env_runs]))
            cost = float(np.mean([run.costs[-last:].mean() for run in env_runs]))
            normalised = (np.nan, np.nan)
            if task in PPO_REFERENCE:
                normalised = normalised_scores(reward, cost, *PPO_REFERENCE[task], budget)
            levels[suffix] = (reward, cost, *normalised)
        thesis = THESIS_DSSLAC_SCORES.get(task, (np.nan, np.nan))
        lambda_scores = THESIS_LAMBDA_SCORES.get(task, (np.nan, np.nan))
        policies = {run.eval_policy for run in env_runs}
        final, late = levels[""], levels["_late"]
        rows.append(
            {
                "task": task,
                "runs": len(env_runs),
                "sim_steps": int(min(run.sim_steps[-1] for run in env_runs)),
                "Jr": final[0],
                "Jc": final[1],
                "budget": budget,
                "Jr_bar": final[2],
                "Jc_bar": final[3],
                "Jr_late": late[0],
                "Jc_late": late[1],
                "Jr_bar_late": late[2],
                "Jc_bar_late": late[3],
                "thesis_Jr_bar": thesis[0],
                "thesis_Jc_bar": thesis[1],
                "lambda_Jr_bar": lambda_scores[0],
                "lambda_Jc_bar": lambda_scores[1],
                "eval": policies.pop() if len(policies) == 1 else "mixed",
            }
        )
    return pd.DataFrame(rows)


def to_markdown(table: pd.DataFrame) -> str:
    """A GitHub markdown table, numbers with three decimals."""

    def cell(value: object) -> str:
        if isinstance(value, float):
            return "-" if np.isnan(value) else f"{value:.3f}"
        return str(value)

    lines = ["| " + " | ".join(table.columns) + " |", "|" + "---|" * len(table.columns)]
    lines += ["| " + " | ".join(cell(value) for value in row) + " |" for row in table.itertuples(index=False)]
    return "\n".join(lines)


def report(run_dirs: list[str | Path], out: str | Path) -> str:
    """
    Write ``curves.png``, ``scores.csv`` and ``scores.md`` for the runs into ``out``.

    :return: the score table as markdown, with the files written
    """
    runs = [load_run(run_dir) for run_dir in run_dirs]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    curves = plot_learning_curves(runs, out / "curves.png")
    table = score_table(runs)
    table.to_csv(out / "scores.csv", index=False)
    markdown = to_markdown(table)
    note = (
        "Jr_bar = Jr / Jr_PPO, Jc_bar = max(0, Jc - d) / max(1e-6, Jc_PPO - d) (thesis Eq. 5.1); "
        "*_late: the last 3 evaluations' episodes pooled; "
        "thesis_* and lambda_* are DS-SLAC's and LAMBDA's Table 5.1 numbers (1M simulator steps, stochastic evaluation); "
        f"eval: the evaluation policy of these runs ({', '.join(sorted({run.eval_policy for run in runs}))})."
    )
    (out / "scores.md").write_text(f"{markdown}\n\n{note}\n")
    return f"{markdown}\n\n{note}\n\nwrote {curves}, {out / 'scores.csv'}, {out / 'scores.md'}"
