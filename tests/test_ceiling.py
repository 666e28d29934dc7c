"""benchmarks/ceiling.py and benchmarks/goal_view.py: the goal's pixels, the in-view rule, the scripted controller."""

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
FAR = {"hazards_xy": np.full((8, 2), 3.3), "vases_xy": np.array([[3.3, -3.3]])}  # PointGoal1's hazards and vase


@pytest.fixture
def benchmarks(monkeypatch):
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools" / "diagnostics"))


@pytest.fixture
def point_env(benchmarks):
    from ceiling import make_ceiling_env

    env = make_ceiling_env("PointGoal1", 32)
    yield env
    env.close()


def frame_with(patches: dict[tuple[int, int, int], tuple[slice, slice]], size: int = 32) -> np.ndarray:
    """A grey (floor-coloured) frame with each colour painted over its (rows, columns)."""
    frame = np.full((size, size, 3), 180, dtype=np.uint8)
    for colour, (rows, columns) in patches.items():
        frame[rows, columns] = colour
    return frame


@pytest.mark.parametrize(("robot", "yaw"), [("Point", 0.0), ("Car", np.pi / 2)])  # both facing +x
def test_the_goal_mask_finds_the_goal_in_the_field_of_view_and_not_behind(benchmarks, robot: str, yaw: float) -> None:
    from ceiling import make_ceiling_env
    from goal_view import goal_in_fov, goal_in_view, goal_mask

    env = make_ceiling_env(f"{robot}Goal1", 32)
    try:
        for goal_x, seen in ((1.5, True), (-1.5, False), (0.0, False)):  # ahead, behind, beside (at y = 1.5)
            goal_xy = [goal_x, 0.0] if goal_x else [0.0, 1.5]
            frame, _ = env.reset(seed=0, options={"robot_xy": [0.0, 0.0], "robot_yaw": yaw, "goal_xy": goal_xy, **FAR})
            assert goal_in_fov(env) is seen
            assert bool(goal_in_view(frame)) is seen and bool(goal_mask(frame).any()) is seen
    finally:
        env.close()


def test_the_in_view_rule_is_a_share_of_the_frame(benchmarks) -> None:
    from goal_view import IN_VIEW_SHARE, in_view, min_pixels

    assert min_pixels(64, 64) == pytest.approx(10.0) and min_pixels(32, 32) == pytest.approx(2.5)
    for size in (16, 32, 64):
        mask = np.zeros((size, size), dtype=bool)
        mask.flat[: int(np.ceil(IN_VIEW_SHARE * size * size))] = True
        assert in_view(mask)
        mask.flat[int(np.ceil(IN_VIEW_SHARE * size * size)) - 1] = False
        assert not in_view(mask)
    three = np.zeros((2, 64, 64), dtype=bool)
    three[:, 0, :3] = True
    assert in_view(three[0, :32, :32]) and not in_view(three[0])  # 3 pixels: in view at 32x32, not at 64x64
    assert in_view(three).shape == (2,)


def test_the_masks_tell_the_objects_apart(benchmarks) -> None:
    from goal_view import goal_mask, hazard_mask, vase_mask

    # Colours as rendered: the goal's faint side over the floor, the goal against the dark sky, a hazard, a vase's side
    frame = np.array([[[112, 124, 112], [0, 30, 0], [96, 96, 208], [0, 112, 112], [180, 180, 180], [240, 0, 0]]], np.uint8)
    assert goal_mask(frame).tolist() == [[True, True, False, False, False, False]]
    assert hazard_mask(frame).tolist() == [[False, False, True, False, False, False]]
    assert vase_mask(frame).tolist() == [[False, False, False, True, False, False]]


def test_the_controller_turns_in_place_without_the_goal_and_toward_its_side(point_env) -> None:
    from ceiling import CameraGeometry, PixelController

    point_env.reset(seed=0)
    controller = PixelController("Point", CameraGeometry.of(point_env))
    green = (100, 230, 100)
    assert controller.command(frame_with({})) == (0.0, 1.0)  # no goal: turn left in place
    assert controller.command(frame_with({green: (slice(14, 16), slice(0, 1))})) == (0.0, 1.0)  # 2 pixels: not in view
    speed, turn = controller.command(frame_with({green: (slice(12, 18), slice(15, 17))}))  # ahead
    assert speed == pytest.approx(1.0) and turn == pytest.approx(0.0)
    right_speed, right_turn = controller.command(frame_with({green: (slice(12, 18), slice(24, 28))}))
    left_speed, left_turn = controller.command(frame_with({green: (slice(12, 18), slice(4, 8))}))
    assert right_turn < 0 < left_turn and right_turn == pytest.approx(-left_turn)
    assert 0 < right_speed < 1 and right_speed == pytest.approx(left_speed)
    action = controller(frame_with({green: (slice(12, 18), slice(24, 28))}))
    assert action.dtype == np.float32 and action[0] == pytest.approx(0.05 * right_speed) and action[1] < 0


def test_the_car_turns_with_its_wheels(benchmarks) -> None:
    from ceiling import CameraGeometry, PixelController, make_ceiling_env

    env = make_ceiling_env("CarGoal1", 32)
    try:
        env.reset(seed=0)
        controller = PixelController("Car", CameraGeometry.of(env))
    finally:
        env.close()
    left_wheel, right_wheel = controller(frame_with({}))
    assert left_wheel > 0 > right_wheel  # searching turns it left (counter-clockwise) in place
    left_wheel, right_wheel = controller(frame_with({(100, 230, 100): (slice(12, 18), slice(24, 28))}))
    assert right_wheel > left_wheel  # the goal on the right


def test_the_camera_geometry_puts_a_hazard_where_it_lies(point_env) -> None:
    from ceiling import CameraGeometry, PixelController
    from goal_view import goal_mask, hazard_mask

    hazards = FAR["hazards_xy"].copy()
    hazards[0] = (0.8, 0.2)  # 0.8 m ahead, 0.2 m to the left; radius 0.2 m
    options = {"robot_xy": [0.0, 0.0], "robot_yaw": 0.0, "goal_xy": [2.0, 0.3], **FAR, "hazards_xy": hazards}
    frame, _ = point_env.reset(seed=0, options=options)
    geometry = CameraGeometry.of(point_env)
    points = geometry.hazard_floor[hazard_mask(frame)]
    assert len(points) > 5 and np.all(np.hypot(points[:, 0] - 0.8, points[:, 1] - 0.2) < 0.25)
    # The goal lies behind the hazard: ignoring it the script heads for the goal; avoiding it, it steers right of it
    seek, avoid = PixelController("Point", geometry), PixelController("Point", geometry, avoid=True)
    assert seek.command(frame)[1] > 0  # toward the goal, 8.5 degrees to the left
    assert avoid.command(frame)[1] < 0
    heading, free = avoid.steer(float(geometry.bearing[goal_mask(frame)].mean()), avoid.obstacles(frame))
    assert heading < 0 and free >= avoid.gains.stop_distance


def test_the_script_earns_more_than_a_random_policy(point_env) -> None:
    from ceiling import controller_for, run_episode

    class Truncated:
        """The first 100 agent steps of an episode: ``run_episode`` of a shorter env."""

        def __init__(self, env) -> None:
            self.env, self.unwrapped = env, env.unwrapped

        def reset(self, **kwargs):
            self.steps = 0
            return self.env.reset(**kwargs)

        def step(self, action):
            observation, reward, terminated, truncated, info = self.env.step(action)
            self.steps += 1
            return observation, reward, terminated, truncated or self.steps == 100, info

    point_env.reset(seed=0)
    script = controller_for(point_env, "seek")
    rng = np.random.default_rng(0)
    scripted = run_episode(Truncated(point_env), script, seed=1)
    random = run_episode(Truncated(point_env), lambda frame: rng.uniform(-1, 1, 2).astype(np.float32), seed=1)
    assert len(scripted.rewards) == len(random.rewards) == 100
    assert scripted.rewards.sum() > random.rewards.sum() + 2.0  # at least two goals more
    assert scripted.goal_pixels.shape == scripted.in_fov.shape == (100,)


def test_the_reward_split_counts_the_steps_of_each_condition(benchmarks) -> None:
    from ceiling import Episode
    from reward_by_view import reward_split

    episode = Episode(
        rewards=np.array([1.0, 0.5, 0.0, -0.5]),
        costs=np.zeros(4),
        goal_pixels=np.array([12, 3, 1, 0]),
        in_fov=np.array([True, True, False, True]),
    )
    split = reward_split([episode, episode], (32, 32))
    assert split["goal pixels >= 1"]["share of steps"] == 0.75
    assert split["goal pixels >= 10"]["reward per step"] == 1.0 and split["goal pixels >= 10"]["otherwise"] == 0.0
    assert split["goal in view (goal_view's rule)"]["share of steps"] == 0.5  # 2.5 pixels at 32x32
    assert split["goal pixels >= 3"]["share of the reward"] == 1.5  # 1.5 of a total of 1.0
    assert split["goal in the field of view"]["reward per step"] == pytest.approx(1.0 / 3)
    assert split["in the field of view, no goal pixel"]["share of steps"] == 0.25
    assert reward_split([episode], (64, 64))["goal in view (goal_view's rule)"]["share of steps"] == 0.25


def test_the_searching_agent_searches_after_n_frames_without_the_goal_and_tells_its_filter(benchmarks) -> None:
    from reward_by_view import SearchingAgent

    class Policy:
        def scale_action(self, action: np.ndarray) -> np.ndarray:
            return action * 10.0

    class Model:
        policy = Policy()

        def predict(self, frame, state, episode_start, deterministic):
            steps = 0 if state is None else state[0] + 1
            return np.array([0.5, 0.5], dtype=np.float32), (steps, np.array([[0.5, 0.5]]))

    goal = frame_with({(0, 200, 0): (slice(10, 14), slice(10, 14))})
    empty = frame_with({})
    agent = SearchingAgent(Model(), lambda frame: np.array([0.0, 0.1], dtype=np.float32), after=2)
    assert agent(empty).tolist() == [0.5, 0.5]  # one frame without the goal: still the agent's
    searched = agent(empty)
    assert searched.tolist() == pytest.approx([0.0, 0.1])
    assert agent.state[0] == 1 and agent.state[1][0].tolist() == pytest.approx([0.0, 1.0])  # the action taken, scaled
    assert agent(goal).tolist() == [0.5, 0.5]
    agent(empty)
    agent.reset()
    assert agent.state is None and agent(empty).tolist() == [0.5, 0.5]


def test_the_turn_keeping_agent_holds_its_first_turns_direction_until_the_goal_shows(benchmarks) -> None:
    from reward_by_view import TurnKeepingAgent

    turns = iter([0.3, -0.6, 0.8, -0.2, -0.4, 0.7, 0.5])

    class Policy:
        def scale_action(self, action: np.ndarray) -> np.ndarray:
            return action

    class Model:
        policy = Policy()

        def predict(self, frame, state, episode_start, deterministic):
            action = np.array([0.2, next(turns)], dtype=np.float32)
            return action, (None, action[None])

    goal = frame_with({(0, 200, 0): (slice(10, 14), slice(10, 14))})
    empty = frame_with({})
    agent = TurnKeepingAgent(Model(), after=2)
    taken = [agent(frame)[1] for frame in (empty, empty, empty, empty, goal, empty, empty)]
    # the agent's own turn, then the sign of -0.6 kept at each turn's magnitude; in view again: its own; gone again: 0.5's
    assert taken == pytest.approx([0.3, -0.6, -0.8, -0.2, -0.4, 0.7, 0.5])
    assert agent.state[1][0].tolist() == pytest.approx([0.2, 0.5])  # the filter is told the action taken


def test_same_way_as_before_compares_each_turns_sign_with_the_previous_steps(benchmarks) -> None:
    from search_values import same_way_as_before

    assert same_way_as_before(np.array([0.5, 0.9, -0.1, -0.7, 0.2])).tolist() == [False, True, False, True, False]


def test_search_values_scores_the_agents_action_and_each_alternative_with_the_critics_minimum(benchmarks) -> None:
    import gymnasium as gym
    import torch as th
    from search_values import ALTERNATIVES, episode_values

    from sb3_dsslac import DSSLAC, preset_hyperparams

    env = gym.make("SafetyGym/PointGoal1-v0", width=32, height=32, action_repeat=4, max_episode_steps=12)
    hyperparams = preset_hyperparams("cpu", {"policy_kwargs": {"image_channels": (4, 8, 8, 16)}})
    model = DSSLAC("LatentPolicy", env, seed=0, **hyperparams)

    def critic(z: th.Tensor, actions: th.Tensor) -> th.Tensor:  # Q1 = the turn command, Q2 = Q1 - 1: the minimum is Q2
        turn = actions[:, 1:]
        return th.stack([turn, turn - 1.0])

    model.policy.critic.forward = critic
    episode = episode_values(model, env, seed=3)
    env.close()
    gone, values, actions = episode.gone, episode.values, episode.actions
    assert gone.shape == (12,) and values.shape == (12, 1 + len(ALTERNATIVES)) and episode.mean_actions.shape == (12, 2)
    assert (np.abs(actions) <= 1.0).all() and (np.abs(episode.mean_actions) <= 1.0).all()  # Point units, in [-1, 1]
    assert (gone[1:] == 0).sum() + (np.diff(gone) == 1).sum() == 11  # each step: back in view, or one frame longer gone
    assert values[:, 1:] == pytest.approx(np.tile([0.0, -2.0, -1.0], (12, 1)))  # left, right, straight (scaled turn 1, -1, 0)
    assert values[:, 0] == pytest.approx(actions[:, 1] - 1.0, abs=1e-5)  # the agent's own turn (Point units = scaled) minus 1


@pytest.mark.parametrize("robot", ["Point", "Car"])
def test_the_point_only_diagnostics_stop_on_another_robot(benchmarks, robot: str) -> None:
    from ceiling import make_ceiling_env
    from reward_by_view import require_point

    env = make_ceiling_env(f"{robot}Goal1", 32)
    try:
        if robot == "Point":
            assert require_point(env, "SafetyGym/PointGoal1-v0", "--keep-turn-after") is None
        else:
            with pytest.raises(SystemExit, match=r"--keep-turn-after: the Point's actions .* not the Car's"):
                require_point(env, "SafetyGym/CarGoal1-v0", "--keep-turn-after")
    finally:
        env.close()
