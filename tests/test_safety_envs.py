"""Safety-Gym rebuild: API contract, env checkers, and Safety-Gym's task rules (docs/safety_envs.md)."""

import warnings

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from gymnasium.utils.passive_env_checker import env_render_passive_checker
from stable_baselines3.common.env_checker import check_env as sb3_check_env
from stable_baselines3.common.monitor import Monitor

import safety_envs
from safety_envs import ActionRepeat, CostMonitor, SafetyGymEnv, make_env

ALL_IDS = safety_envs.env_ids()
FAR = 5.0  # m: a position outside every placement region, to park objects out of the way


def park(n: int, start: float = FAR) -> np.ndarray:
    """(n, 2) positions far from the origin and from each other."""
    return np.stack([np.full(n, start), np.arange(n, dtype=float)], axis=1)


def blue_pixels(image: np.ndarray) -> int:
    """Pixels whose blue channel clearly dominates (hazards are translucent blue)."""
    r, g, b = (image[..., i].astype(int) for i in range(3))
    return int(np.sum((b > r + 30) & (b > g + 30)))


def green_pixels(image: np.ndarray) -> int:
    r, g, b = (image[..., i].astype(int) for i in range(3))
    return int(np.sum((g > r + 30) & (g > b + 30)))


def cyan_pixels(image: np.ndarray) -> int:
    r, g, b = (image[..., i].astype(int) for i in range(3))
    return int(np.sum((g > r + 50) & (b > r + 50) & (np.abs(g - b) < 30)))


# ---------------------------------------------------------------- registration and API
def test_ids_registered():
    expected = [
        f"SafetyGym/{robot}{task}{level}-v0"
        for robot in ("Point", "Car", "Doggo")
        for task in ("Goal", "Button", "Push")
        for level in (0, 1, 2)
    ]
    assert ALL_IDS == expected
    for env_id in ALL_IDS:
        assert env_id in gym.registry
    env = gym.make("safety_envs:SafetyGym/PointGoal1-v0", obs_type="state")
    assert isinstance(env.unwrapped, SafetyGymEnv)
    assert (env.unwrapped.robot_spec.name, env.unwrapped.task_spec.id_name) == ("Point", "Goal1")
    env.close()


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_env_checkers_pixels(env_id):
    env = gym.make(env_id, render_mode="rgb_array", render_width=32, render_height=32).unwrapped
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any checker warning fails the test
        gym_check_env(env)
        sb3_check_env(env, warn=True)
    env.close()


@pytest.mark.parametrize("action_repeat", [1, 2, 4])
def test_render_fps_is_one_frame_per_agent_step(action_repeat):
    env = SafetyGymEnv(action_repeat=action_repeat, render_mode="rgb_array")
    agent_step_seconds = env.model.opt.timestep * env.task_spec.frameskip * action_repeat
    assert env.metadata["render_fps"] == pytest.approx(1.0 / agent_step_seconds)
    assert env.metadata["render_fps"] == {1: 50, 2: 25, 4: 12.5}[action_repeat]  # Safety-Gym's 0.002 s x 10 substeps
    assert SafetyGymEnv.metadata["render_fps"] == 25  # the class's, for the default repeat, is left alone
    wrapped = ActionRepeat(SafetyGymEnv(action_repeat=1, render_mode="rgb_array"), repeat=action_repeat)
    assert wrapped.metadata["render_fps"] == pytest.approx(env.metadata["render_fps"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium's "No render fps was declared" and its type checks
        for checked in (env, wrapped):
            checked.reset(seed=0)
            env_render_passive_checker(checked)
    env.close()
    wrapped.close()


def test_env_checkers_state_and_both():
    for obs_type in ("state", "both"):
        env = make_env("Car", "Goal", 2, obs_type=obs_type)
        gym_check_env(env, skip_render_check=True)
        sb3_check_env(env, warn=True)
        env.close()


def test_spaces_and_state_layout():
    env = make_env("Point", "Goal", 1, obs_type="both", width=48, height=32)
    assert env.observation_space["pixels"] == gym.spaces.Box(0, 255, (32, 48, 3), np.uint8)
    assert env.observation_space["state"].shape == (60,)  # 4 sensors x 3 + 3 lidars x 16, as PointGoal1
    assert env.observation_space["state"].dtype == np.float32
    assert env.action_space == gym.spaces.Box(-1, 1, (2,), np.float32)
    assert list(env.state_slices) == sorted(env.state_slices)
    obs, _ = env.reset(seed=0)
    assert obs["pixels"].shape == (32, 48, 3)
    env.close()
    assert make_env("Car", "Goal", 1, obs_type="state").observation_space.shape == (72,)  # + ball joint 9 + 3
    assert make_env("Point", "Goal", 0, obs_type="state").observation_space.shape == (28,)  # goal lidar only


def test_bad_names_list_valid_ones():
    with pytest.raises(ValueError, match=r"Unknown robot 'Ant'.*\['Car', 'Doggo', 'Point'\]"):
        make_env("Ant")
    with pytest.raises(ValueError, match=r"Unknown task 'Circle'.*\['Goal', 'Button', 'Push'\]"):
        make_env("Point", "Circle")
    with pytest.raises(ValueError, match=r"Unknown level 3.*\[0, 1, 2\]"):
        make_env("Point", "Goal", 3)
    with pytest.raises(ValueError, match=r"Unknown obs_type 'rgb'.*'pixels', 'state', 'both'"):
        make_env(obs_type="rgb")
    with pytest.raises(ValueError, match="render_mode"):
        make_env(render_mode="human")
    with pytest.raises(ValueError, match="action_repeat"):
        make_env(action_repeat=0)


def test_bad_actions_rejected():
    env = make_env("Point", "Goal", 1, obs_type="state")
    env.reset(seed=0)
    for action in ([np.nan, 0.0], [0.0, np.inf], [-np.inf, 0.0]):
        with pytest.raises(ValueError, match="NaN or inf"):
            env.step(np.array(action, dtype=np.float32))
    for action in (np.zeros(3), np.zeros((1, 2)), 0.0):
        with pytest.raises(ValueError, match="shape"):
            env.step(action)
    with pytest.raises(ValueError, match="Unknown reset options"):
        env.reset(options={"robot_pos": (0, 0)})
    env.step(np.array([5.0, -5.0]))  # out of range: clipped, not an error
    np.testing.assert_array_equal(env.data.ctrl, [1.0, -1.0])


# ---------------------------------------------------------------- model numbers (spec sections 1.3, 5, 10.6-10.7)
def test_model_matches_spec():
    point, car = make_env("Point", obs_type="state"), make_env("Car", obs_type="state")
    assert point.model.opt.timestep == 0.002 and car.model.opt.timestep == 0.004
    assert point.sim_dt == pytest.approx(0.02) and car.sim_dt == pytest.approx(0.04)
    assert point.model.body_subtreemass[point.ids.robot_body] == pytest.approx(5.19e-3, rel=1e-2)
    assert car.model.body_subtreemass[car.ids.robot_body] == pytest.approx(0.030, rel=2e-2)
    np.testing.assert_array_equal(point.model.actuator_forcerange, [[-0.05, 0.05]] * 2)
    np.testing.assert_array_equal(car.model.actuator_forcerange, [[-0.02, 0.02]] * 2)
    assert point.model.cam_fovy[point.ids.vision_camera] == 90 and car.model.cam_fovy[car.ids.vision_camera] == 45
    # robot geoms for contact costs: everything in the robot's body tree, never the floor
    names = {mujoco.mj_id2name(car.model, mujoco.mjtObj.mjOBJ_GEOM, g) for g in np.flatnonzero(car.ids.robot_geom_mask)}
    assert names == {"robot", "back_bumper", "back_connector", "front_bumper", "front_connector", "left", "right", "rear"}


@pytest.mark.parametrize(("robot", "saturation"), [("Point", 0.05), ("Car", 0.02)])
def test_force_saturation(robot, saturation):
    """Point forward motor saturates at |a| >= 0.05, Car wheel motors at |a| >= 0.02 (the Point's turning
    actuator is a velocity servo, so it is held at 0 here)."""
    mask = np.array([1.0, 0.0]) if robot == "Point" else np.ones(2)

    def final_pose(command: float) -> np.ndarray:
        env = make_env(robot, "Goal", 0, obs_type="state", action_repeat=1)
        env.reset(seed=0, options={"robot_xy": (0.0, 0.0), "robot_yaw": 0.0, "goal_xy": (FAR, 0.0)})
        for _ in range(25):
            env.step(command * mask)
        return env.data.qpos.copy()

    np.testing.assert_array_equal(final_pose(saturation), final_pose(1.0))
    assert not np.allclose(final_pose(saturation / 2), final_pose(1.0))


def test_car_drives_toward_minus_y():
    env = make_env("Car", "Goal", 0, obs_type="state")
    env.reset(seed=0, options={"robot_xy": (0.0, 0.0), "robot_yaw": 0.0, "goal_xy": (FAR, 0.0)})
    for _ in range(50):
        env.step(np.ones(2))
    x, y = env.robot_xy
    assert y < -0.05 and abs(x) < abs(y) / 3


# ---------------------------------------------------------------- layout (spec sections 1.4, 4.2, 10.5)
@pytest.mark.parametrize(("robot", "level"), [("Point", 1), ("Car", 2)])
def test_spawn_respects_keepouts_and_costs_nothing(robot, level):
    env = make_env(robot, "Goal", level, obs_type="state")
    spec = env.task_spec
    half = {1: 1.5, 2: 2.0}[level]
    for seed in range(10):
        _, info = env.reset(seed=seed)
        assert info["cost"] == 0.0
        robot_xy, goal_xy, hazards, vases = env.robot_xy, env.goal_xy, env.hazards_xy, env.vases_xy
        assert np.all(np.abs(robot_xy) <= half - 0.4 + 1e-9) and np.all(np.abs(goal_xy) <= half - 0.305 + 1e-9)
        assert np.all(np.abs(hazards) <= half - 0.18 + 1e-9) and np.all(np.abs(vases) <= half - 0.15 + 1e-9)
        assert np.linalg.norm(robot_xy - goal_xy) >= 0.705
        assert np.all(np.linalg.norm(hazards - robot_xy, axis=1) >= 0.58)
        assert np.all(np.linalg.norm(vases - robot_xy, axis=1) >= 0.55)
        assert np.all(np.linalg.norm(hazards - goal_xy, axis=1) >= 0.485)
        assert np.all(np.linalg.norm(vases - goal_xy, axis=1) >= 0.455)
        pairs = np.linalg.norm(hazards[:, None] - hazards[None], axis=-1) + np.eye(spec.hazards_num)
        assert np.all(pairs >= 0.36)
        assert np.all(np.linalg.norm(hazards[:, None] - vases[None], axis=-1) >= 0.33)
        _, _, _, _, info = env.step(np.zeros(2))
        assert info["cost"] == 0.0


# ---------------------------------------------------------------- costs (spec sections 3, 10.1-10.3)
@pytest.mark.parametrize("robot", ["Point", "Car"])
def test_hazard_cost_from_robot_origin(robot):
    env = make_env(robot, "Goal", 1, obs_type="state", action_repeat=1)
    hazards = park(env.task_spec.hazards_num)
    hazards[0] = (0.0, 0.0)
    for offset, expected in ((0.0, 1.0), (0.19, 1.0), (0.21, 0.0), (0.5, 0.0)):
        # at 0.21 m the robot's body (radius >= 0.1) overlaps the 0.2 m disc, but only the origin counts
        env.reset(
            seed=0,
            options={"robot_xy": (offset, 0.0), "robot_yaw": 0.0, "goal_xy": (-FAR, 0.0), "hazards_xy": hazards},
        )
        _, _, _, _, info = env.step(np.zeros(2))
        assert info["cost_hazards"] == expected and info["cost"] == expected, offset


def test_costs_are_binary_per_sim_step_and_summed_over_repeat():
    """Robot parked inside two overlapping hazards: cost 1 per simulator step, not 2; 2 per agent step."""
    env = make_env("Point", "Goal", 1, obs_type="state")  # action_repeat=2
    hazards = park(env.task_spec.hazards_num)
    hazards[:2] = [(0.05, 0.0), (-0.05, 0.0)]
    env.reset(seed=0, options={"robot_xy": (0.0, 0.0), "goal_xy": (-FAR, 0.0), "hazards_xy": hazards})
    total = 0.0
    for _ in range(10):
        _, _, _, _, info = env.step(np.zeros(2))
        assert info["cost"] == 2.0 and info["cost_hazards"] == 2.0 and info["cost_vases"] == 0.0
        total += info["cost"]
    assert total == 20.0


def push_vase(level: int) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Drive the Point straight into a vase; return (cost, vase cost, vase start xy, vase end xy)."""
    env = make_env("Point", "Goal", level, obs_type="state")
    spec = env.task_spec
    vases = park(spec.vases_num, start=-FAR)
    vases[0] = (0.4, 0.0)
    env.reset(
        seed=0,
        options={
            "robot_xy": (0.0, 0.0),
            "robot_yaw": 0.0,
            "goal_xy": (0.0, FAR),
            "hazards_xy": park(spec.hazards_num),
            "vases_xy": vases,
        },
    )
    cost = vase_cost = 0.0
    for _ in range(60):
        _, _, _, _, info = env.step(np.array([1.0, 0.0]))
        cost += info["cost"]
        vase_cost += info["cost_vases"]
        assert info["cost_hazards"] == 0.0
    return cost, vase_cost, vases[0], env.vases_xy[0]


def test_vase_push_costs_in_goal2_only():
    cost, vase_cost, start, end = push_vase(level=2)
    assert end[0] > start[0] + 0.05  # the vase was pushed
    assert cost > 0 and vase_cost == cost
    cost, vase_cost, start, end = push_vase(level=1)
    assert end[0] > start[0] + 0.05  # physical in Goal1 too ...
    assert cost == 0 and vase_cost == 0  # ... but not constrained


# ---------------------------------------------------------------- reward and goal (spec sections 2, 10.4)
@pytest.mark.parametrize("robot", ["Point", "Car"])
def test_goal_reached_pays_one_and_respawns(robot):
    env = make_env(robot, "Goal", 1, obs_type="state", action_repeat=1)
    env.reset(
        seed=0, options={"robot_xy": (0.0, 0.0), "goal_xy": (0.25, 0.0), "hazards_xy": park(8), "vases_xy": park(1, -FAR)}
    )
    _, reward, terminated, truncated, info = env.step(np.zeros(2))
    assert info["goal_met"] and not terminated and not truncated
    assert reward == pytest.approx(1.0, abs=1e-3)  # +1, plus a negligible dense term
    assert np.linalg.norm(env.goal_xy - env.robot_xy) >= 0.705  # robot keepout 0.4 + goal keepout 0.305
    assert np.all(np.abs(env.goal_xy) <= 1.5 - 0.305)
    goal_body = env.data.xpos[env.ids.goal_body, :2]
    np.testing.assert_allclose(goal_body, env.goal_xy)  # the goal geom moved too (it is rendered there)
    _, reward, _, _, info = env.step(np.zeros(2))
    assert not info["goal_met"] and abs(reward) < 1e-3  # no distance jump after the respawn


def test_dense_reward_telescopes():
    env = make_env("Point", "Goal", 0, obs_type="state")
    env.reset(seed=0, options={"robot_xy": (0.0, 0.0), "robot_yaw": 0.0, "goal_xy": (3.0, 0.0)})
    total = 0.0
    for _ in range(40):
        _, reward, _, _, info = env.step(np.array([1.0, 0.0]))
        assert not info["goal_met"]
        total += reward
    assert total > 0.05  # driving toward the goal pays
    assert total == pytest.approx(3.0 - np.linalg.norm(env.goal_xy - env.robot_xy), abs=1e-9)


# ---------------------------------------------------------------- episode and action repeat (spec sections 1.2, 1.6, 6.5)
def test_episode_is_500_agent_steps_of_1000_sim_steps():
    env = gym.make("SafetyGym/PointGoal1-v0")
    _, info = env.reset(seed=0)
    assert info["sim_steps"] == 0
    for step in range(1, 501):
        obs, _, terminated, truncated, info = env.step(env.action_space.sample())
        assert not terminated
        assert truncated == (step == 500)
        assert info["sim_steps"] == 2 * step
    assert obs.shape == (64, 64, 3)
    assert env.unwrapped.max_episode_steps == 500
    env.close()
    raw = make_env("Car", "Goal", 2, obs_type="state", action_repeat=1)
    assert raw.max_episode_steps == 1000
    raw.reset(seed=0)
    ends = [raw.step(np.zeros(2))[3] for _ in range(1000)]
    assert ends[-1] and not any(ends[:-1]) and raw.sim_steps == 1000


def rollout(env: gym.Env, actions: np.ndarray, options: dict) -> tuple[list, list, list]:
    obs, _ = env.reset(seed=7, options=options)
    frames, rewards, costs = [obs], [], []
    for action in actions:
        obs, reward, _, _, info = env.step(action)
        frames.append(obs)
        rewards.append(reward)
        costs.append(info["cost"])
    return frames, rewards, costs


def hazard_run_options() -> dict:
    """Robot starting just outside a hazard in front of it, so a run toward it collects costs."""
    hazards = park(8)
    hazards[0] = (0.3, 0.0)
    return {"robot_xy": (0.0, 0.0), "robot_yaw": 0.0, "goal_xy": (1.0, 0.0), "hazards_xy": hazards}


def test_action_repeat_sums_reward_and_cost():
    actions = np.random.default_rng(0).uniform(-0.2, 1.0, size=(40, 2)).astype(np.float32)
    options = hazard_run_options()
    frames1, rewards1, costs1 = rollout(make_env("Point", "Goal", 1, action_repeat=1), np.repeat(actions, 2, axis=0), options)
    frames2, rewards2, costs2 = rollout(make_env("Point", "Goal", 1, action_repeat=2), actions, options)
    assert sum(costs1) > 0 and set(costs1) <= {0.0, 1.0} and set(costs2) <= {0.0, 1.0, 2.0}
    np.testing.assert_allclose(rewards2, np.add(rewards1[0::2], rewards1[1::2]), atol=1e-12)
    np.testing.assert_array_equal(costs2, np.add(costs1[0::2], costs1[1::2]))
    for k in range(len(actions)):  # one render per agent step, after its last simulator step
        np.testing.assert_array_equal(frames2[k + 1], frames1[2 * k + 2])
    # the wrapper on the raw task gives the same numbers
    frames3, rewards3, costs3 = rollout(ActionRepeat(make_env("Point", "Goal", 1, action_repeat=1), 2), actions, options)
    np.testing.assert_allclose(rewards3, rewards2, atol=1e-12)
    np.testing.assert_array_equal(costs3, costs2)
    np.testing.assert_array_equal(frames3[-1], frames2[-1])


def test_determinism_byte_exact():
    actions = np.random.default_rng(1).uniform(-1, 1, size=(60, 2)).astype(np.float32)
    runs = [rollout(gym.make("SafetyGym/PointGoal2-v0", obs_type="both"), actions, {}) for _ in range(2)]
    for a, b in zip(runs[0][0], runs[1][0], strict=True):
        assert a["pixels"].tobytes() == b["pixels"].tobytes() and a["state"].tobytes() == b["state"].tobytes()
    assert runs[0][1] == runs[1][1] and runs[0][2] == runs[1][2]
    env = make_env("Point", "Goal", 2)
    first, _ = env.reset(seed=3)
    env.reset(seed=4)
    for _ in range(100):  # let resting vases fall asleep: reset must still place and show them anew
        env.step(np.zeros(2))
    again, _ = env.reset(seed=3)
    assert first.tobytes() == again.tobytes()
    assert not np.array_equal(env.reset(seed=4)[0], first)


def test_physics_sleep_keeps_robot_dynamics_and_vase_costs():
    """Sleeping resting vases changes nothing for the robot away from them, and a pushed vase still costs."""
    actions = np.random.default_rng(2).uniform(-1, 1, size=(200, 2))
    runs = []
    for sleep in (True, False):
        env = make_env("Point", "Goal", 2, obs_type="state", physics_sleep=sleep)
        env.reset(seed=0)
        runs.append([env.step(action)[1] for action in actions])
        assert env.data.ntree_awake == (1 if sleep else env.model.ntree)  # only the robot is simulated
    assert runs[0] == runs[1]


def test_physics_sleep_is_off_with_a_warning_on_a_mujoco_without_it(monkeypatch):
    assert safety_envs.engine.SLEEP_FLAG is not None  # setup.cfg asks for MuJoCo >= 3.4, which has sleeping
    monkeypatch.setattr(safety_envs.engine, "SLEEP_FLAG", None)
    with pytest.warns(UserWarning, match="MuJoCo 3.4"):
        env = make_env("Point", "Goal", 2, obs_type="state")
    assert not env.model.opt.enableflags & mujoco.mjtEnableBit.mjENBL_SLEEP
    env.reset(seed=0)
    env.step(np.zeros(2))
    assert env.data.ntree_awake == env.model.ntree


def test_physics_exception_ends_episode():
    env = make_env("Point", "Goal", 1, obs_type="state")
    env.reset(seed=0)
    env.data.qvel[:] = np.nan
    _, reward, terminated, truncated, info = env.step(np.zeros(2))
    assert truncated and not terminated and info["physics_exception"]
    assert reward == pytest.approx(-10.0) and info["cost"] == 1.0


# ---------------------------------------------------------------- pixels (spec sections 6, 10.8)
def test_image_upright_with_robot_at_bottom():
    env = make_env("Point", "Goal", 0)
    obs, _ = env.reset(seed=0)
    top, middle, bottom = obs[:8].astype(int), obs[28:36].astype(int), obs[-6:].astype(int)
    assert top.max() < 10  # background above the horizon (no skybox)
    assert middle.mean() > 100 and np.ptp(middle.mean(axis=2)) < 80  # grey checker floor
    assert np.mean((bottom[..., 0] > 150) & (bottom[..., 1] < 50)) > 0.5  # the robot's own red body


@pytest.mark.parametrize("robot", ["Point", "Car"])
def test_first_frame_shows_hazards_vase_and_goal(robot):
    env = make_env(robot, "Goal", 1)
    heading = 0.0 if robot == "Point" else np.pi / 2  # the Car looks toward its body -y
    hazards = park(8)
    empty, _ = env.reset(
        seed=0,
        options={
            "robot_xy": (0, 0),
            "robot_yaw": heading,
            "goal_xy": (-FAR, 0),
            "hazards_xy": hazards,
            "vases_xy": park(1, -FAR),
        },
    )
    hazards[0] = (0.8, 0.0)
    with_hazard, _ = env.reset(seed=0, options={"robot_xy": (0, 0), "robot_yaw": heading, "hazards_xy": hazards})
    assert blue_pixels(empty) == 0 and blue_pixels(with_hazard) > 20  # visible in the reset frame
    with_vase, _ = env.reset(
        seed=0, options={"robot_xy": (0, 0), "robot_yaw": heading, "hazards_xy": park(8), "vases_xy": [(0.9, 0.2)]}
    )
    assert cyan_pixels(empty) == 0 and cyan_pixels(with_vase) > 20
    with_goal, _ = env.reset(
        seed=0, options={"robot_xy": (0, 0), "robot_yaw": heading, "goal_xy": (1.2, 0.0), "vases_xy": park(1, -FAR)}
    )
    assert green_pixels(empty) == 0 and green_pixels(with_goal) > 20
    # stepping keeps them in view
    obs, *_ = env.step(np.zeros(2))
    assert green_pixels(obs) > 20


@pytest.mark.parametrize("robot", ["Point", "Car", "Doggo"])
def test_back_camera_sees_behind_the_robot(robot):
    heading = {"Point": 0.0, "Car": np.pi / 2, "Doggo": 0.0}[robot]  # the camera looks along +x in each case
    parked = {"hazards_xy": park(8), "vases_xy": park(1, -FAR)}
    front = make_env(robot, "Goal", 1)
    both = make_env(robot, "Goal", 1, back_camera=True)
    assert both.observation_space.shape == (64, 128, 3)
    for goal_x, seen_in in ((1.2, "front"), (-1.2, "back")):
        options = {"robot_xy": (0, 0), "robot_yaw": heading, "goal_xy": (goal_x, 0.0), **parked}
        plain, _ = front.reset(seed=0, options=options)
        pair, _ = both.reset(seed=0, options=options)
        assert pair.shape == (64, 128, 3) and pair.dtype == np.uint8
        np.testing.assert_array_equal(pair[:, :64], plain)  # the front half is the usual frame
        halves = {"front": green_pixels(pair[:, :64]), "back": green_pixels(pair[:, 64:])}
        assert halves[seen_in] > 20 and min(halves.values()) == 0, halves
    with pytest.raises(ValueError, match="back_camera"):
        make_env(robot, "Goal", 1, back_camera="yes")


def test_render_modes():
    env = gym.make("SafetyGym/CarGoal1-v0", render_mode="rgb_array", render_width=96, render_height=80)
    obs, _ = env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (80, 96, 3) and frame.dtype == np.uint8 and frame.std() > 10
    assert obs.shape == (64, 64, 3)  # the observation keeps its own size
    env.close()
    env.close()  # idempotent
    silent = make_env("Point", obs_type="state", render_mode=None)
    silent.reset(seed=0)
    assert silent.render() is None


# ---------------------------------------------------------------- episode-cost wrapper
def test_cost_monitor_with_sb3_monitor():
    env = CostMonitor(Monitor(make_env("Point", "Goal", 1, obs_type="state")))
    hazards = park(8)
    hazards[0] = (0.0, 0.0)
    env.reset(seed=0, options={"robot_xy": (0.0, 0.0), "goal_xy": (-FAR, 0.0), "hazards_xy": hazards})
    total, done, info = 0.0, False, {}
    while not done:
        _, _, terminated, truncated, info = env.step(np.zeros(2))
        total += info["cost"]
        done = terminated or truncated
    assert total == 1000.0  # parked in a hazard for 1000 simulator steps
    assert info["episode"]["c"] == total and info["episode_cost"] == total
    assert info["episode"]["l"] == 500 and {"r", "t"} <= set(info["episode"])
    env.reset(seed=1)
    assert env.episode_cost == 0.0


def test_cost_monitor_requires_cost():
    env = CostMonitor(gym.make("CartPole-v1"))
    env.reset(seed=0)
    with pytest.raises(KeyError, match="cost"):
        env.step(0)
