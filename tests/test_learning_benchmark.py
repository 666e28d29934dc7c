"""benchmarks/learning.py: several seeds in their own processes, resumable after a stop, with its CSVs, plot and table."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch as th

from sb3_dsslac.app.plotting import RunResults, load_run

REPO = Path(__file__).resolve().parents[1]
TINY = [
    "--env", "tests.registered_envs:HazardPoint-v0", "--preset", "cpu", "--obs-type", "state", "--sim-steps", "200",
    "--eval-every", "100", "--eval-episodes", "2", "--checkpoint-every", "100", "--random-episodes", "2", "--poll", "0.2",
    "--hyperparams", "learning_starts=40", "latent_pretrain_steps=3", "train_freq=20", "gradient_steps=2",
]  # fmt: skip


def run_benchmark(out: Path, *seeds: str, sim_steps: int = 200, extra: tuple[str, ...] = ()) -> str:
    env = {**os.environ, "PYTHONPATH": str(REPO), "MUJOCO_GL": "egl"}
    command = [sys.executable, "benchmarks/learning.py", *TINY, "--seeds", *seeds, "--out", str(out)]
    command += ["--sim-steps", str(sim_steps), *extra]
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout


def test_seeds_run_in_parallel_and_a_stopped_run_resumes(tmp_path) -> None:
    # About 30 s: two seeds' train processes (each importing torch and MuJoCo), a stop and a resume
    output = run_benchmark(tmp_path, "0", "1")
    assert "seed 0: starting" in output and "seed 1: starting" in output
    for name in ("seed0.csv", "seed1.csv", "curves.png", "table.md", "random_policy.json"):
        assert (tmp_path / name).is_file(), name
    table = (tmp_path / "table.md").read_text()
    assert "DS-SLAC, seed 1 | 200 |" in table and "mean ± sample std of 2 seeds" in table and "stochastic policy" in table
    # The late level pools the last 3 evaluations' episodes (here both: at 100 and 200 simulator steps)
    evaluations = np.load(tmp_path / "runs" / "seed0" / "evaluations.npz")
    row = next(line for line in table.splitlines() if "seed 0" in line).strip("|").split("|")
    assert [float(cell) for cell in row[2:6]] == [
        round(float(evaluations["results"][-1].mean()), 2), round(float(evaluations["costs"][-1].mean()), 1),
        round(float(evaluations["results"].mean()), 2), round(float(evaluations["costs"].mean()), 1),
    ]  # fmt: skip
    # The latent model's health: the largest KL of an update, read from progress.csv
    health = next(line for line in table.splitlines() if line.startswith("| 0 | ") and line.count("|") == 6)
    largest_kl = float(health.split("|")[2])
    kl_max = pd.read_csv(tmp_path / "runs" / "seed0" / "progress.csv")["train/kl_max"].max()
    assert largest_kl == pytest.approx(kl_max, rel=1e-3)
    # Where each seed's minutes went, from its time_account.json: every activity and the rest add up to its wall time
    assert "by activity" in table and table.count("\n| 0 | ") == 2 and table.count("\n| 1 | ") == 2  # health, time
    account = json.loads((tmp_path / "runs" / "seed0" / "time_account.json").read_text())
    assert account["updates"] > 0 and account["acting"] > 0 and account["evaluation"] > 0 and account["checkpoints"] > 0
    parts = sum(value for name, value in account.items() if name not in ("wall", "cpu"))
    assert abs(parts - account["wall"]) < 0.3
    # The table's minutes are the time account's, which the checkpoints carry across a stop that kills every process
    assert [float(cell) for cell in row[-2:]] == [round(account["wall"] / 60, 1), round(account["cpu"] / 60, 1)]
    assert len((tmp_path / "seed0.csv").read_text().splitlines()) == 3  # header and evaluations at 100 and 200
    # Each seed's record (no weights) is kept beside the table, and `plot` reads it as it reads the run folder
    record = tmp_path / "seed0_run"
    files = {"config.yaml", "progress.csv", "evaluations.npz", "time_account.json", "wall_minutes.json"}
    assert {path.name for path in record.iterdir()} == files
    assert np.array_equal(load_run(record).rewards, evaluations["results"])

    # A stop after the last checkpoint but before the final save: seed 1 resumes, seed 0 is reused untouched
    runs = tmp_path / "runs"
    finished = (runs / "seed0" / "model.zip").stat().st_mtime_ns
    (runs / "seed1" / "model.zip").unlink()
    # A stop before the first checkpoint: seed 2 has a config but nothing to continue from, so it starts afresh
    (runs / "seed2").mkdir()
    (runs / "seed2" / "config.yaml").write_text("env: x\n")
    output = run_benchmark(tmp_path, "0", "1", "2")
    assert "seed 0: finished earlier, reused" in output
    assert "seed 1: resuming" in output and "seed 2: starting" in output
    assert (runs / "seed0" / "model.zip").stat().st_mtime_ns == finished
    assert (runs / "seed1" / "model.zip").is_file() and (runs / "seed2" / "model.zip").is_file()
    assert "mean ± sample std of 3 seeds" in (tmp_path / "table.md").read_text()

    # A finished seed asked for more simulator steps continues from its last checkpoint, its evaluations kept
    output = run_benchmark(tmp_path, "0", sim_steps=300, extra=("--report-at", "200"))
    assert "seed 0: resuming" in output and "--sim-steps 300" in output
    assert [line.split(",")[0] for line in (tmp_path / "seed0.csv").read_text().splitlines()[1:]] == ["100", "200", "300"]
    # --report-at: the seed as it stood at 200 simulator steps, below its table at 300
    table = (tmp_path / "table.md").read_text()
    at_300, at_200 = (line for line in table.splitlines() if line.startswith("| DS-SLAC, seed 0 |"))
    assert "The same seeds at 200 simulator steps" in table and at_300.split("|")[2:3] == [" 300 "]
    with np.load(runs / "seed0" / "evaluations.npz") as extended:
        rewards, costs = extended["results"][:2], extended["costs"][:2]  # the evaluations at 100 and 200
    assert [float(cell) for cell in at_200.strip("|").split("|")[1:6]] == [
        200, round(float(rewards[-1].mean()), 2), round(float(costs[-1].mean()), 1),
        round(float(rewards.mean()), 2), round(float(costs.mean()), 1),
    ]  # fmt: skip

    # --report-only: the seeds as they stand, none trained, the title saying where they stopped
    output = run_benchmark(tmp_path, "0", "1", sim_steps=400, extra=("--report-only",))
    assert "starting" not in output and "resuming" not in output
    assert "stopped at 200 and 300 of 400 simulator steps" in (tmp_path / "table.md").read_text().splitlines()[0]


def test_the_table_gives_the_normalised_scores_beside_the_thesis(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    import learning

    def run(rewards: list[float], costs: list[float]) -> RunResults:
        return RunResults(
            Path("."), "SafetyGym/PointGoal1-v0", 25.0, np.array([100_000, 200_000, 300_000, 400_000]),
            np.array(rewards)[:, None], np.array(costs)[:, None], "stochastic",
        )  # fmt: skip

    runs = {0: run([0.0, 8.0, 10.0, 12.0], [60.0, 30.0, 20.0, 10.0]), 1: run([0.0, 2.0, 4.0, 6.0], [60.0, 40.0, 30.0, 35.0])}
    line = learning.normalised_line(runs)
    # Last 3 evaluations: reward (10 + 4) / 2 = 7, cost (20 + 35) / 2 = 27.5, over the budget of 25 by a 51.439th of
    # (PPO's cost on PointGoal1 - 25); final: reward 9, cost 22.5, under the budget
    late, final = f"({7 / 17.476:.3f}, {2.5 / 51.439:.3f})", f"({9 / 17.476:.3f}, 0.000)"
    assert f"{late} over the last 3 evaluations, {final} at the final one, at 400,000 simulator steps" in line
    assert "DS-SLAC (1.237, 0.000) and LAMBDA (1.077, 0.000) at 1M" in line
    runs[0] = run([0.0, 8.0, 10.0, 12.0], [60.0, 30.0, 45.0, 45.0])
    assert f"({9 / 17.476:.3f}, {15 / 51.439:.3f}) at the final one" in learning.normalised_line(runs)
    assert learning.normalised_line({0: RunResults(**{**vars(runs[1]), "env": "tests.registered_envs:HazardPoint-v0"})}) == ""


def test_a_failed_seed_does_not_stop_the_others(monkeypatch, tmp_path, capsys) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    import learning

    # Seed 1 fails at once; seed 0 and seed 2 (started after the failure) still run to their end
    def seed_command(run_dir: Path, seed: int, args) -> list[str]:
        run_dir.mkdir(parents=True, exist_ok=True)
        code = f"import pathlib, sys, time; time.sleep(0.5); pathlib.Path({str(run_dir / 'done')!r}).touch()"
        return [sys.executable, "-c", "import sys; sys.exit(3)" if seed == 1 else code]

    monkeypatch.setattr(learning, "seed_command", seed_command)
    args = learning.argparse.Namespace(seeds=[0, 1, 2], parallel=2, poll=0.1, sim_steps=200)
    with pytest.raises(SystemExit, match=r"failed: seed 1 \(exit 3\): .*seed1.log; run the benchmark again"):
        learning.run_seeds(args, tmp_path)
    assert (tmp_path / "seed0" / "done").is_file() and (tmp_path / "seed2" / "done").is_file()
    assert "seed 1: failed (exit 3), the others go on" in capsys.readouterr().out


def test_pixel_runs_show_what_the_first_seed_sees_and_believes(tmp_path) -> None:
    # About 25 s: a pixel train process, then the beliefs figure and an episode video rendered from its model
    pixels = [flag if flag != "state" else "pixels" for flag in TINY] + ["--env-kwargs", "max_episode_steps=25"]
    env = {**os.environ, "PYTHONPATH": str(REPO), "MUJOCO_GL": "egl"}
    command = [sys.executable, "benchmarks/learning.py", *pixels, "--seeds", "3", "--out", str(tmp_path)]
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "seed3, evaluation episode 10000, stochastic policy" in result.stdout  # the policy the evaluations used
    assert (tmp_path / "beliefs.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "episode.mp4").stat().st_size > 1000
    assert "env_kwargs:\n  max_episode_steps: 25\n" in (tmp_path / "runs" / "seed3" / "config.yaml").read_text()
    # The random baseline runs in the runs' env settings: 25-step episodes, so at most 25 cost each
    random = json.loads((tmp_path / "random_policy.json").read_text())
    assert random["env_kwargs"] == {"max_episode_steps": 25} and max(random["costs"]) <= 25
    account = json.loads((tmp_path / "runs" / "seed3" / "time_account.json").read_text())
    # One torch thread: at most the process's own core plus its render and data threads
    assert 0 < account["cpu"] <= 2 * account["wall"]

    command = [
        sys.executable,
        "benchmarks/tools/diagnostics/belief_probe.py",
        str(tmp_path / "runs" / "seed3"),
        "--windows",
        "100",
    ]
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    rows = {line.split("|")[1].strip(): line for line in result.stdout.splitlines() if line.startswith("| ")}
    assert {"goal in view", "goal column", "hazard pixels"} <= set(rows)
    assert "of the frames" in result.stdout
    assert "cost decoder on the windows' last transitions: costly share" in result.stdout
    assert "cost decoder on 5 fresh episodes (125 steps), online filter: costly share" in result.stdout
    assert "by the goal in view: goal in view " in result.stdout

    command = [
        sys.executable,
        "benchmarks/tools/diagnostics/filter_memory.py",
        str(tmp_path / "runs" / "seed3"),
        "--env",
        TINY[1],
    ]
    command += ["--episodes", "2", "--windows", "1", "2"]
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ") and "window" not in line]
    windows = [row.split("|")[1].strip() for row in rows]
    assert windows == ["1", "2", "4"]  # the two asked for and the preset's training window

    command = [
        sys.executable,
        "benchmarks/tools/diagnostics/latent_scale.py",
        str(tmp_path / "runs" / "seed3"),
        "--windows",
        "20",
    ]
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    z1_rows = [line for line in result.stdout.splitlines() if line.count("|") == 4 and line.split("|")[0].strip().isdigit()]
    assert len(z1_rows) == 16  # the cpu preset's z1_dim
    assert "z2 recurrence stretch (Jacobian spectral norm): median" in result.stdout


def test_reconstruction_speed_probes_the_latent_model_at_each_checkpoint(tmp_path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "MUJOCO_GL": "egl"}
    command = [sys.executable, "benchmarks/tools/diagnostics/reconstruction_speed.py", "--random-steps", "120"]
    command += ["--checkpoints", "2", "5", "--episode-steps", "6", "--held-out-steps", "30", "--probe-windows", "100"]
    command += ["--preset", "cpu_pixels32_bounded", "--hyperparams", "sequence_length=3", "compile_updates=false"]
    result = subprocess.run([*command, "--out", str(tmp_path)], cwd=REPO, env=env, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "{'width': 32, 'height': 32, 'action_repeat': 4}" in result.stdout.splitlines()[0]  # the preset's env keywords
    rows = [json.loads(line) for line in result.stdout.splitlines() if line.startswith("{")]
    assert [row["latent_updates"] for row in rows] == [2, 5]
    assert all(0.0 <= row["mean_abs_error"]["all"] <= 1.0 for row in rows)
    assert all(row["reward_r2"]["all"] <= 1.0 and 0.0 <= row["reward_r2"]["share_in_view"] <= 1.0 for row in rows)
    assert all(set(row["readout_r2"]) == {"goal column", "hazard column"} for row in rows)
    assert (tmp_path / "beliefs_2.png").is_file() and (tmp_path / "beliefs_5.png").is_file()


def test_object_sizes_gives_each_object_its_shares_and_size() -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "MUJOCO_GL": "egl"}
    command = [sys.executable, "benchmarks/tools/diagnostics/object_sizes.py", "--envs", "SafetyGym/PointGoal1-v0"]
    command += ["--sizes", "16", "--episodes", "1"]
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    rows = [line.split("|")[1:-1] for line in result.stdout.splitlines() if line.startswith("| PointGoal1")]
    assert [row[2].strip() for row in rows] == ["goal", "hazard"]
    for row in rows:
        frames, shown, in_view, median, per_mille = (float(cell.replace(",", "")) for cell in row[3:])
        assert frames == 250 and 0.0 <= in_view <= shown <= 1.0
        assert 0.0 <= median <= 256 and per_mille == pytest.approx(1000 * median / 256, abs=0.05)
    assert float(rows[1][4]) > 0.0  # PointGoal1's eight hazards are in some random-policy frame


def test_belief_probe_scores_a_linear_readout_near_one_and_noise_near_zero(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools" / "diagnostics"))
    from belief_probe import frame_targets, ridge_r2

    rng = np.random.default_rng(0)
    inputs = rng.normal(size=(600, 5))
    assert ridge_r2(inputs, inputs @ np.arange(1.0, 6.0) + 3.0) > 0.999
    assert ridge_r2(inputs, rng.normal(size=600)) < 0.05

    frames = np.full((2, 64, 64, 3), 180, dtype=np.uint8)
    frames[0, 30:40, 10:14] = (100, 230, 100)  # 40 green pixels, columns 10-13
    targets = frame_targets(frames)
    assert targets["goal in view"].tolist() == [1.0, 0.0] and targets["goal pixels"].tolist() == [40.0, 0.0]
    assert targets["goal column"][0] == 11.5 and np.isnan(targets["goal column"][1])
    assert targets["hazard in view"].tolist() == [0.0, 0.0]


def test_belief_probe_cost_head_auc_ranks_costly_transitions_against_free_ones(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools" / "diagnostics"))
    from belief_probe import cost_head_scores, roc_auc

    costly = np.array([False, False, True, True])
    assert roc_auc(np.array([0.1, 0.2, 0.8, 0.9]), costly) == 1.0
    assert roc_auc(np.array([0.9, 0.8, 0.2, 0.1]), costly) == 0.0
    assert roc_auc(np.full(4, 0.3), costly) == 0.5  # a constant cannot tell them apart
    assert roc_auc(np.array([0.1, 0.5, 0.5, 0.9]), costly) == 0.875  # the tie at 0.5 counts half
    assert roc_auc(np.array([0.1, 0.2]), np.array([False, False])) is None

    scores = cost_head_scores(np.array([0.1, 0.3, 0.6, 0.8]), np.array([0.0, 0.0, 2.0, 1.0]))
    assert scores["costly share"] == 0.5 and scores["ROC AUC"] == 1.0
    assert scores["p(cost) on costly"] == 0.7 and scores["p(cost) on free"] == 0.2


def test_belief_probe_splits_the_reward_by_the_goal_in_the_frame_acted_on(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools" / "diagnostics"))
    from belief_probe import goal_in_view, reward_by_goal_view

    # Two episodes of 2 steps (3 frames each); frames 0 and 1 of the first show the goal, no frame of the second does
    frames = [np.zeros((3, 8, 8, 3), dtype=np.uint8) for _ in range(2)]
    frames[0][:2, :, :2, 1] = 255
    frames[1][:, :, :, 1] = 255
    frames[1][:, :, :, 0] = 255  # yellow, not green
    rewards = [np.array([1.0, 0.5]), np.array([0.25, -0.25])]
    split = reward_by_goal_view([goal_in_view(episode) for episode in frames], rewards)
    assert split["goal in view"] == 0.5
    assert split["reward per step in view"] == 0.75 and split["reward per step out of view"] == 0.0
    assert split["share of the reward in view"] == 1.0
    assert split["episode reward at the in-view rate"] == 1.5  # 0.75 per step over 2 steps per episode
    # The last frame of an episode is never acted on: a goal seen only there counts for no step
    frames[1][-1] = 0
    frames[1][-1, :, :, 1] = 255
    assert reward_by_goal_view([goal_in_view(episode) for episode in frames], rewards)["goal in view"] == 0.5


def test_belief_probe_times_the_search_from_a_goal_reached_to_the_next_goal_in_view(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools" / "diagnostics"))
    from belief_probe import goal_in_view, search_lengths

    # One episode of 6 steps (7 frames): goals reached at steps 0 and 4; the goal shows in frames 3 and 4 only
    frames = np.zeros((7, 8, 8, 3), dtype=np.uint8)
    frames[3:5, :, :, 1] = 255
    rewards = np.array([1.05, 0.0, 0.1, 0.1, 1.1, -0.02])
    assert search_lengths([goal_in_view(frames)], [rewards]) == (
        [3],
        1,
    )  # frame 3 three steps after step 0; after step 4 never
    # No goal reached, no search
    assert search_lengths([goal_in_view(frames)], [np.full(6, 0.1)]) == ([], 0)


def test_hazard_visibility_counts_sightings_in_the_window_and_the_bottom_rows(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools" / "diagnostics"))
    from hazard_visibility import hazard_in_view, seen_within

    assert seen_within(np.array([1, 0, 0, 0, 1, 0], dtype=bool), 1).tolist() == [1, 0, 0, 0, 1, 0]
    assert seen_within(np.array([1, 0, 0, 0, 1, 0], dtype=bool), 3).tolist() == [1, 1, 1, 0, 1, 1]
    frames = np.full((3, 32, 32, 3), 180, dtype=np.uint8)
    frames[0, 2:4, 10:12] = (60, 60, 230)  # 4 blue pixels at the top: over 10/4096 of 1,024 pixels (2.5)
    frames[1, 30:32, 10:12] = (60, 60, 230)  # 4 at the bottom
    frames[2, 31, 10:12] = (60, 60, 230)  # 2: under the threshold
    assert hazard_in_view(frames).tolist() == [True, True, False]
    assert hazard_in_view(frames, rows=0.25).tolist() == [False, True, False]


def test_filter_memory_windows_as_long_as_the_episode_give_the_online_belief(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools" / "diagnostics"))
    from filter_memory import filtered_episode, mismatch_share, window_beliefs

    from tests.synthetic_envs import HazardPointEnv
    from tests.test_cli import TINY_ENV
    from tests.test_dsslac import SMALL_POLICY, small_model

    policy_kwargs = {**SMALL_POLICY, "image_channels": (4, 8, 8, 16)}
    model = small_model(HazardPointEnv(obs_type="pixels"), seed=3, policy_kwargs=policy_kwargs)
    episode = filtered_episode(model, TINY_ENV, seed=5)
    frames = len(episode.features)
    assert frames == 30 and episode.actions.shape == (29, 2) and episode.beliefs.shape[0] == 30
    # The window over the whole episode is the online filter; a window of the first two frames is its second belief
    assert th.allclose(window_beliefs(model, episode, frames)[0], episode.beliefs[-1], atol=1e-5)
    pairs = window_beliefs(model, episode, 2)
    assert pairs.shape == (29, episode.beliefs.shape[1]) and th.allclose(pairs[0], episode.beliefs[1], atol=1e-5)
    assert 0.0 <= mismatch_share(model, [episode], 20) < mismatch_share(model, [episode], 1)
