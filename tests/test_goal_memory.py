"""benchmarks/goal_memory.py: the goal's bearing, the steps since it was in view, the probe and its split, a short run."""

import sys
from pathlib import Path

import numpy as np
import pytest

from sb3_dsslac import DSSLAC
from sb3_dsslac.common.envs import make_env
from sb3_dsslac.presets import preset_hyperparams

REPO = Path(__file__).resolve().parents[1]
FAR = {"hazards_xy": np.full((8, 2), 3.3), "vases_xy": np.array([[3.3, -3.3]])}  # PointGoal1's hazards and vase
PIXELS32 = {"width": 32, "height": 32, "action_repeat": 4}


@pytest.fixture
def benchmarks(monkeypatch):
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))


def test_the_bearing_is_counter_clockwise_from_the_heading(benchmarks) -> None:
    from goal_memory import bearing

    offsets = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 0.0], [0.0, 2.0], [1.0, 0.0]])
    along_x = bearing(offsets, np.array([2.0, 0.0]))  # a heading of any length
    np.testing.assert_allclose(np.degrees(along_x), [45.0, -45.0, 180.0, 90.0, 0.0], atol=1e-9)
    along_y = bearing(offsets, np.array([0.0, 1.0]))
    np.testing.assert_allclose(np.degrees(along_y), [-45.0, -135.0, 90.0, 0.0, -90.0], atol=1e-9)


@pytest.mark.parametrize(("robot", "yaw"), [("Point", 0.0), ("Car", np.pi / 2)])  # both facing +x
@pytest.mark.parametrize("back_camera", [False, True])
def test_the_goal_bearing_is_from_where_the_camera_looks(benchmarks, robot: str, yaw: float, back_camera: bool) -> None:
    from goal_memory import goal_bearing
    from goal_view import goal_in_fov

    env = make_env(f"SafetyGym/{robot}Goal1-v0", "pixels", env_kwargs={**PIXELS32, "back_camera": back_camera})
    seen = (0.0, 180.0) if back_camera else (0.0,)
    try:
        # Ahead, to the left, to the right, behind; the Car's camera sits 0.1 m behind its centre
        for goal_xy, degrees in (([1.5, 0.0], 0.0), ([0.0, 1.5], 90.0), ([0.0, -1.5], -90.0), ([-1.5, 0.0], 180.0)):
            env.reset(seed=0, options={"robot_xy": [0.0, 0.0], "robot_yaw": yaw, "goal_xy": goal_xy, **FAR})
            error = (np.degrees(goal_bearing(env)) - degrees + 180.0) % 360.0 - 180.0
            assert abs(error) < 5.0, (goal_xy, np.degrees(goal_bearing(env)))
            assert goal_in_fov(env) is (degrees in seen)
    finally:
        env.close()


def test_steps_since_in_view_count_from_the_last_frame_in_view_and_restart_with_each_goal(benchmarks) -> None:
    from goal_memory import NOT_SEEN, steps_since_in_view

    in_fov = np.array([0, 1, 1, 0, 0, 0, 1, 0, 0, 0, 0], dtype=bool)
    new_goal = np.array([1, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0], dtype=bool)  # a goal reached before step 8
    expected = [NOT_SEEN, 0, 0, 1, 2, 3, 0, 1, NOT_SEEN, NOT_SEEN, NOT_SEEN]
    assert steps_since_in_view(in_fov, new_goal).tolist() == expected
    in_fov[8] = True  # the new goal in view at once
    assert steps_since_in_view(in_fov, new_goal)[8:].tolist() == [0, 1, 2]


def test_the_halves_and_the_folds_keep_episodes_whole(benchmarks) -> None:
    from goal_memory import CV_FOLDS, cv_folds, episode_halves

    for n_episodes in (2, 5, 20):
        first, second = episode_halves(n_episodes)
        assert not set(first) & set(second)
        assert sorted([*first, *second]) == list(range(n_episodes))
        assert abs(len(first) - len(second)) <= 1
    episode_ids = np.repeat([0, 2, 4, 6, 8, 10, 12], 9)
    folds = cv_folds(episode_ids)
    assert len(folds) == CV_FOLDS
    assert sorted(np.concatenate(folds).tolist()) == list(range(len(episode_ids)))
    held_out = [set(episode_ids[fold]) for fold in folds]
    assert all(not a & b for i, a in enumerate(held_out) for b in held_out[i + 1 :])
    single = cv_folds(np.zeros(23, dtype=int))  # one episode: contiguous blocks of its steps
    assert [fold.tolist() for fold in single] == [list(block) for block in np.array_split(np.arange(23), CV_FOLDS)]


def test_the_results_are_named_after_the_run(benchmarks) -> None:
    from goal_memory import model_name

    assert model_name(Path("runs/pid_seed20/model.zip")) == "pid_seed20"
    assert model_name(Path("runs/pid_seed20/checkpoints/dsslac_75000_steps.zip")) == "pid_seed20_dsslac_75000_steps"
    assert model_name(Path("elsewhere/agent.zip")) == "agent"


def synthetic_steps(n_episodes: int, steps: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Random bearings (rad) of ``n_episodes`` x ``steps`` steps and the episode of each."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-np.pi, np.pi, n_episodes * steps), np.repeat(np.arange(n_episodes), steps)


def test_the_probe_reads_a_linear_code_and_not_noise(benchmarks) -> None:
    from goal_memory import probe_score

    rng = np.random.default_rng(1)
    bearings, episode_ids = synthetic_steps(10, 60)
    rows = np.ones(len(bearings), dtype=bool)
    code = np.stack([np.cos(bearings), np.sin(bearings), *rng.normal(size=(6, len(bearings)))], axis=1)
    mixed = code @ rng.normal(size=(8, 8)) + 3.0  # a full-rank linear code, off centre
    linear = probe_score(mixed + 0.01 * rng.normal(size=mixed.shape), bearings, episode_ids, rows)
    assert linear is not None and linear.r2 > 0.99 and linear.median_error < 1.0
    assert linear.steps == len(bearings)
    noise = probe_score(rng.normal(size=(len(bearings), 8)), bearings, episode_ids, rows)
    assert noise is not None and abs(noise.r2) < 0.05 and 70.0 < noise.median_error < 110.0
    half_rows = episode_ids < 6
    assert probe_score(mixed, bearings, episode_ids, half_rows).steps == half_rows.sum()
    assert probe_score(mixed, bearings, episode_ids, episode_ids == 0) is None  # one half has none of the rows


def test_the_probe_never_scores_an_episode_it_was_fitted_on(benchmarks) -> None:
    from goal_memory import probe_score

    # Each episode's goal keeps one bearing, and the input names the episode: a probe that saw an episode's steps
    # would read its bearing off the name; across episodes the name says nothing
    bearings_per_episode, _ = synthetic_steps(12, 1, seed=2)
    episode_ids = np.repeat(np.arange(12), 40)
    names = np.eye(12)[episode_ids]
    score = probe_score(names, bearings_per_episode[episode_ids], episode_ids, np.ones(len(episode_ids), dtype=bool))
    assert score is not None and score.r2 < 0.05


def test_the_pooled_r2_and_the_angle_error(benchmarks) -> None:
    from goal_memory import angle_errors, r2_score

    targets = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    assert r2_score(targets, targets) == pytest.approx(1.0)
    assert r2_score(np.zeros_like(targets), targets) == pytest.approx(0.0)
    # Pooled: the squared errors of both columns over both columns' spread (2 + 2)
    assert r2_score(targets + np.array([0.5, 0.0]), targets) == pytest.approx(1 - 1.0 / 4.0)
    predicted = np.array([[np.cos(np.radians(179)), np.sin(np.radians(179))], [2.0, 0.0]])  # any length
    np.testing.assert_allclose(angle_errors(predicted, np.radians([-179.0, 30.0])), [2.0, 30.0], atol=1e-9)


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> Path:
    """An untrained agent of the ``cpu`` preset on PointGoal1's 32x32 frames at action repeat 4, saved."""
    env = make_env("SafetyGym/PointGoal1-v0", "pixels", env_kwargs=PIXELS32)
    path = tmp_path_factory.mktemp("goal_memory") / "tiny.zip"
    DSSLAC("LatentPolicy", env, seed=0, **preset_hyperparams("cpu")).save(path)
    env.close()
    return path


def test_two_episodes_end_to_end(benchmarks, tiny_model: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    import goal_memory

    out = tmp_path / "goal_memory_tiny.md"
    monkeypatch.setattr(sys, "argv", ["goal_memory.py", str(tiny_model), "--episodes", "2", "--seed", "7", "--out", str(out)])
    goal_memory.main()
    text, printed = out.read_text(), capsys.readouterr().out
    assert text.startswith(f"# Goal memory: tiny\n\n`python benchmarks/goal_memory.py {tiny_model} --episodes 2 --seed 7")
    assert printed[printed.index("| agent steps |") : printed.index("\n\nwritten to")] in text  # the table printed is written
    assert "2 episodes (500 agent steps)" in text and "reset seeds 7-8" in text and "'action_repeat': 4" in text
    assert goal_memory.cpu_model() in text
    for name in goal_memory.STEP_KINDS:
        assert f"| {name} |" in text or f"| **{name}** |" in text
    assert not list(tmp_path.glob(".*.tmp"))  # the temporary file was renamed over the results


def test_bearings_of_an_episode_agree_with_the_field_of_view(benchmarks, tiny_model: Path) -> None:
    from goal_memory import goal_episode

    model = DSSLAC.load(tiny_model, device="cpu")
    env = make_env("SafetyGym/PointGoal1-v0", "pixels", env_kwargs=PIXELS32)
    try:
        episode = goal_episode(model, env, seed=3)
    finally:
        env.close()
    steps = len(episode.bearings)
    assert steps == 250 and episode.beliefs.shape == (steps, 16 + 64) and episode.previous_actions.shape == (steps, 2)
    assert episode.new_goal[0] and not episode.previous_actions[0].any()
    assert episode.in_fov.any() and (~episode.in_fov).any()
    # The Point's horizontal field of view is 90 degrees; the camera's pitch widens it a little near the frame's edge
    assert (np.abs(np.degrees(episode.bearings[episode.in_fov])) <= 47.0).all()
    assert (np.abs(np.degrees(episode.bearings[~episode.in_fov])) >= 43.0).all()


def test_a_non_goal_task_and_a_state_agent_are_refused(benchmarks, tiny_model: Path, tmp_path: Path, monkeypatch) -> None:
    import goal_memory

    monkeypatch.setattr(sys, "argv", ["goal_memory.py", str(tiny_model), "--env", "SafetyGym/PointButton1-v0"])
    with pytest.raises(SystemExit, match="not a Safety-Gym Goal task"):
        goal_memory.main()
    env = make_env("SafetyGym/PointGoal1-v0", "state")
    state_model = tmp_path / "state.zip"
    DSSLAC("LatentPolicy", env, seed=0, **preset_hyperparams("cpu")).save(state_model)
    env.close()
    monkeypatch.setattr(sys, "argv", ["goal_memory.py", str(state_model)])
    with pytest.raises(SystemExit, match="not a pixel agent"):
        goal_memory.main()
