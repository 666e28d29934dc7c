"""Normalised scores (Eq. 5.1), the score table and the learning curves, on hand-made run folders."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from sb3_dsslac.app.plotting import _curves, load_run, plot_learning_curves, report, score_table, task_name
from sb3_dsslac.common.evaluation import PPO_REFERENCE, normalised_scores


def fake_run(
    folder: Path, env: str, rewards: np.ndarray, costs: np.ndarray, action_repeat: int = 2, **settings: object
) -> Path:
    """
    A run folder with ``evaluations.npz`` of (n_evals, n_episodes) rewards and costs, every 25k simulator steps;
    ``settings`` go into its config.yaml (without ``eval_deterministic`` it is a run from before the field existed).
    """
    folder.mkdir(parents=True)
    config = {"env": env, "seed": 0, **settings, "resolved": {"action_repeat": action_repeat, "dsslac": {"cost_limit": 25.0}}}
    (folder / "config.yaml").write_text(yaml.safe_dump(config))
    timesteps = 12_500 * np.arange(1, len(rewards) + 1)
    np.savez(
        folder / "evaluations.npz", timesteps=timesteps, results=rewards, ep_lengths=np.full(rewards.shape, 500), costs=costs
    )
    return folder


def test_normalised_scores_by_hand() -> None:
    # PointGoal1's PPO: Jr 17.476, Jc 76.439; d = 25
    jr_bar, jc_bar = normalised_scores(20.0, 30.0, 17.476, 76.439, 25.0)
    assert jr_bar == pytest.approx(20.0 / 17.476) and jr_bar == pytest.approx(1.14443, abs=1e-5)
    assert jc_bar == pytest.approx(5.0 / 51.439) and jc_bar == pytest.approx(0.09720, abs=1e-5)
    assert normalised_scores(20.0, 24.0, 17.476, 76.439) == (pytest.approx(1.14443, abs=1e-5), 0.0)  # within budget
    assert normalised_scores(1.0, 26.0, 2.0, 20.0) == (0.5, pytest.approx(1e6))  # PPO under the budget: 1e-6 floor


def test_task_names() -> None:
    assert task_name("SafetyGym/PointGoal1-v0") == "PointGoal1"
    assert task_name("SafetyGym/CarGoal2-v0") == "CarGoal2"
    assert task_name("MyEnv-v0") == "MyEnv-v0"


def test_score_table_averages_seeds_at_the_final_evaluation(tmp_path: Path) -> None:
    env = "SafetyGym/PointGoal1-v0"
    runs = [
        fake_run(tmp_path / "seed0", env, np.array([[0.0, 0.0], [18.0, 22.0]]), np.array([[90.0, 90.0], [30.0, 40.0]])),
        fake_run(tmp_path / "seed1", env, np.array([[0.0, 0.0], [16.0, 24.0]]), np.array([[90.0, 90.0], [20.0, 10.0]])),
        fake_run(tmp_path / "custom", "MyEnv-v0", np.array([[1.0]]), np.array([[0.0]])),
    ]
    table = score_table([load_run(run) for run in runs]).set_index("task")
    row = table.loc["PointGoal1"]
    assert row["runs"] == 2 and row["sim_steps"] == 50_000  # agent steps 25k x action repeat 2
    assert row["Jr"] == pytest.approx(20.0) and row["Jc"] == pytest.approx(25.0)
    assert row["Jr_bar"] == pytest.approx(20.0 / PPO_REFERENCE["PointGoal1"][0]) and row["Jc_bar"] == 0.0
    assert (row["thesis_Jr_bar"], row["thesis_Jc_bar"]) == (1.237, 0.0)
    assert (row["lambda_Jr_bar"], row["lambda_Jc_bar"]) == (1.077, 0.0)
    assert np.isnan(table.loc["MyEnv-v0", "Jr_bar"]) and np.isnan(table.loc["MyEnv-v0", "thesis_Jr_bar"])


def test_score_table_pools_the_last_evaluations(tmp_path: Path) -> None:
    env = "SafetyGym/PointGoal1-v0"
    rewards, costs = (
        np.array([[0.0, 0.0], [4.0, 6.0], [8.0, 10.0], [12.0, 14.0]]),
        np.array([[90.0] * 2, [60.0] * 2, [30.0] * 2, [0.0] * 2]),
    )
    table = score_table([load_run(fake_run(tmp_path / "seed0", env, rewards, costs))], late_evaluations=3)
    row = table.set_index("task").loc["PointGoal1"]
    assert (row["Jr"], row["Jc"]) == (13.0, 0.0)
    assert (row["Jr_late"], row["Jc_late"]) == (9.0, 30.0)  # the last 3 evaluations' 6 episodes
    assert row["Jc_bar_late"] == pytest.approx((30.0 - 25.0) / (PPO_REFERENCE["PointGoal1"][1] - 25.0))


def test_report_writes_the_files(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    runs = [
        fake_run(tmp_path / f"seed{seed}", "SafetyGym/PointGoal1-v0", rng.normal(10, 2, (4, 3)), rng.uniform(0, 50, (4, 3)))
        for seed in range(2)
    ]
    text = report(runs, tmp_path / "out")
    assert text.splitlines()[0].startswith("| task | runs | sim_steps | Jr | Jc | budget | Jr_bar | Jc_bar |")
    assert "| PointGoal1 | 2 | 100000 |" in text
    for name in ("curves.png", "scores.csv", "scores.md"):
        assert (tmp_path / "out" / name).stat().st_size > 0


def test_curves_of_runs_with_different_lengths_use_the_common_evaluations(tmp_path: Path) -> None:
    env = "SafetyGym/PointGoal1-v0"
    short = fake_run(tmp_path / "short", env, np.ones((2, 2)), np.zeros((2, 2)))
    long = fake_run(tmp_path / "long", env, np.ones((3, 2)), np.zeros((3, 2)))
    runs = [load_run(short), load_run(long)]
    steps, mean, spread, how = _curves(runs, "rewards")
    assert steps.tolist() == [25_000, 50_000] and mean.tolist() == [1.0, 1.0] and spread.tolist() == [0.0, 0.0]
    assert how == "mean ± std over 2 runs"
    assert plot_learning_curves(runs, tmp_path / "curves.png").stat().st_size > 10_000


def test_missing_evaluations_is_a_clear_error(tmp_path: Path) -> None:
    folder = fake_run(tmp_path / "run", "MyEnv-v0", np.ones((1, 1)), np.zeros((1, 1)))
    (folder / "evaluations.npz").unlink()
    with pytest.raises(FileNotFoundError, match=r"no evaluations\.npz"):
        load_run(folder)


def test_the_score_table_says_which_policy_was_evaluated(tmp_path: Path) -> None:
    env, ones, zeros = "SafetyGym/PointGoal1-v0", np.ones((1, 2)), np.zeros((1, 2))
    stochastic = fake_run(tmp_path / "stochastic", env, ones, zeros, eval_deterministic=False)
    deterministic = fake_run(tmp_path / "deterministic", env, ones, zeros, eval_deterministic=True)
    old = fake_run(tmp_path / "old", "SafetyGym/CarGoal1-v0", ones, zeros)
    policies = [load_run(run).eval_policy for run in (stochastic, deterministic, old)]
    assert policies == ["stochastic", "deterministic", "deterministic"]
    assert score_table([load_run(stochastic)])["eval"].tolist() == ["stochastic"]
    table = score_table([load_run(run) for run in (stochastic, deterministic, old)]).set_index("task")
    assert table["eval"].to_dict() == {"PointGoal1": "mixed", "CarGoal1": "deterministic"}
    report([stochastic], tmp_path / "out")
    markdown = (tmp_path / "out" / "scores.md").read_text()
    assert markdown.splitlines()[0].endswith("| eval |") and "| stochastic |" in markdown
    assert "evaluation policy of these runs (stochastic)" in markdown
    assert pd.read_csv(tmp_path / "out" / "scores.csv")["eval"].tolist() == ["stochastic"]
