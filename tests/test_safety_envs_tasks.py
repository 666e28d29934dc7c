"""Doggo, Button and Push, by Safety-Gym's rules (docs/safety_envs.md)."""

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from safety_envs import make_env

FAR = 5.0  # m: outside every placement region


def park(n: int, start: float = FAR) -> np.ndarray:
    """(n, 2) positions far from the origin and from each other."""
    return np.stack([np.full(n, start), np.arange(n, dtype=float)], axis=1)


def colour_mask(image: np.ndarray, colour: str) -> np.ndarray:
    """Pixels of a clearly green or orange object."""
    r, g, b = (image[..., i].astype(int) for i in range(3))
    if colour == "green":
        return (g > r + 30) & (g > b + 30)
    return (r > 150) & (g > 60) & (g < r - 40) & (b < 60)  # orange (1, 0.5, 0)


def button_options(buttons: np.ndarray, **extra) -> dict:
    """Robot at the origin facing +x, the given buttons, hazards and gremlins far away."""
    return {
        "robot_xy": (0.0, 0.0),
        "robot_yaw": 0.0,
        "buttons_xy": buttons,
        "hazards_xy": park(4),
        "gremlins_xy": park(4, 2 * FAR),
        **extra,
    }


# ---------------------------------------------------------------- Doggo (spec sections 1.2, 1.3, 5.3, 10.6)
def test_doggo_model_matches_spec():
    env = make_env("Doggo", "Goal", 1, obs_type="state")
    model = env.model
    assert model.opt.timestep == 0.01 and env.sim_dt == pytest.approx(0.1)
    assert env.action_space == gym.spaces.Box(-1, 1, (12,), np.float32)
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, i) for i in range(model.nu)]
    assert names == [f"hip_{k}_z" for k in range(1, 5)] + [f"hip_{k}_y" for k in range(1, 5)] + [
        f"ankle_{k}" for k in range(1, 5)
    ]
    np.testing.assert_array_equal(model.actuator_gear[:, 0], 0.0125)
    assert not model.actuator_forcelimited.any()
    assert model.body_subtreemass[env.ids.robot_body] == pytest.approx(0.040, rel=2e-2)
    assert model.cam_fovy[env.ids.vision_camera] == 100
    np.testing.assert_allclose(model.cam_pos[env.ids.vision_camera], (0.125, 0.0, 0.2))
    # state: 4 base sensors, 8 ankle touch sensors, 12 joint velocities, 12 joint angles as (sin, cos), 3 lidars
    assert env.observation_space.shape == (12 + 8 + 12 + 24 + 48,)
    assert {f"touch_ankle_{k}{e}" for k in range(1, 5) for e in "ab"} <= set(env.state_slices)
    state, _ = env.reset(seed=0)
    angle = state[env.state_slices["jointpos_ankle_1"]]
    assert angle[0] ** 2 + angle[1] ** 2 == pytest.approx(1.0, abs=1e-5)


def test_doggo_stands_then_moves_under_random_actions_for_an_episode():
    env = make_env("Doggo", "Goal", 1, obs_type="state")
    env.reset(seed=0, options={"robot_xy": (0.0, 0.0), "hazards_xy": park(8), "vases_xy": park(1, -FAR)})
    for _ in range(25):  # 5 s of zero torque: the springs hold it up, the feet on the floor
        state, *_ = env.step(np.zeros(12))
    height, upright = env.data.xpos[env.ids.robot_body, 2], env.data.xmat[env.ids.robot_body, 8]
    assert 0.12 < height < 0.22 and upright > 0.95
    touch = [state[env.state_slices[f"touch_ankle_{k}b"]][0] for k in range(1, 5)]
    assert min(touch) > 0  # every foot carries weight
    start = env.robot_xy
    env.action_space.seed(0)
    done, steps = False, 25
    while not done:
        state, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert np.all(np.isfinite(state)) and np.isfinite(reward) and "physics_exception" not in info
        done, steps = terminated or truncated, steps + 1
    assert truncated and steps == 500 and env.sim_steps == 1000
    assert np.linalg.norm(env.robot_xy - start) > 0.2  # it walks (or stumbles) somewhere


# ---------------------------------------------------------------- Button (spec sections 2, 3, 4.3, 6.4)
def test_button_press_pays_starts_timer_and_picks_a_new_goal_button():
    env = make_env("Point", "Button", 1, obs_type="state", action_repeat=1)
    buttons = park(4, -FAR)
    buttons[0] = (0.35, 0.0)
    state, _ = env.reset(seed=0, options=button_options(buttons, goal_button=0))
    np.testing.assert_array_equal(env.goal_xy, buttons[0])
    assert state[env.state_slices["buttons_lidar"]].any()
    for _ in range(30):
        state, reward, _, _, info = env.step(np.array([1.0, 0.0]))
        if info["goal_met"]:
            break
    assert info["goal_met"] and 1.0 < reward < 1.05  # +1, plus the last bit of approach
    assert info["cost"] == 0.0  # touching the goal button is free
    assert env.goal_button == 3  # drawn uniformly from the 4 buttons (seeded)
    np.testing.assert_array_equal(env.goal_xy, buttons[3])
    assert env.buttons_timer == 10
    assert not state[env.state_slices["buttons_lidar"]].any()  # the buttons lidar is dark while the timer runs
    _, reward, _, _, info = env.step(np.zeros(2))
    assert not info["goal_met"] and abs(reward) < 1e-3  # no distance jump after the switch


def test_button_timer_then_the_old_button_costs():
    """Pushing on after a press: the old goal button is now a wrong button, free for 10 simulator steps, then costly."""
    env = make_env("Point", "Button", 1, obs_type="state", action_repeat=1)
    buttons = park(4, -FAR)
    buttons[0] = (0.35, 0.0)
    env.reset(seed=0, options=button_options(buttons, goal_button=0))
    log = []
    for _ in range(40):
        state, _, _, _, info = env.step(np.array([1.0, 0.0]))
        log.append((info["goal_met"], info["cost_buttons"], info["cost"]))
    press = [goal for goal, _, _ in log].index(True)
    costs = [cost for _, cost, _ in log[press + 1 :]]
    assert costs[:10] == [0.0] * 10 and costs[10:] == [1.0] * len(costs[10:])
    assert [total for *_, total in log[press + 11 :]] == [1.0] * len(costs[10:])
    assert state[env.state_slices["buttons_lidar"]].any()  # visible again


@pytest.mark.parametrize(("level", "expected"), [(0, 0.0), (1, 1.0)])
def test_wrong_button_costs_from_level_1(level, expected):
    env = make_env("Point", "Button", level, obs_type="state", action_repeat=1)
    buttons = park(4, -FAR)
    buttons[0] = (-1.0, 0.0)  # the goal, behind the robot
    buttons[1] = (0.35, 0.0)  # a wrong button in front of it
    options = button_options(buttons, goal_button=0)
    if level == 0:  # no hazards, no gremlins
        options = {key: value for key, value in options.items() if key not in ("hazards_xy", "gremlins_xy")}
    env.reset(seed=0, options=options)
    touched = 0.0
    for _ in range(30):
        _, _, _, _, info = env.step(np.array([1.0, 0.0]))
        assert not info["goal_met"]
        touched = max(touched, info["cost_buttons"])
        assert info["cost"] == info["cost_buttons"]
    assert touched == expected
    contacts = env.ids.button_of_geom[env._robot_contacts()]
    assert 1 in contacts  # the robot is on the wrong button at both levels


def test_gremlins_orbit_and_contact_costs():
    env = make_env("Point", "Button", 1, obs_type="state", action_repeat=1)
    gremlins = park(4, 2 * FAR)
    gremlins[0] = (-0.35, 0.0)  # its circle passes through the robot at t = pi/2 s
    gremlins[1] = (1.0, 1.0)
    env.reset(seed=0, options=button_options(park(4, -FAR), gremlins_xy=gremlins))
    np.testing.assert_allclose(env.gremlins_xy[1], (1.0, 1.35))  # t = 0: centre + 0.35 (sin 0, cos 0)
    costs = []
    for _ in range(60):  # 1.2 s
        _, _, _, _, info = env.step(np.zeros(2))
        costs.append(info["cost_gremlins"])
        assert info["cost"] == info["cost_gremlins"]
    t = env.data.time
    np.testing.assert_allclose(env.gremlins_xy[1], (1.0 + 0.35 * np.sin(t), 1.0 + 0.35 * np.cos(t)), atol=0.03)
    assert costs[:40] == [0.0] * 40 and max(costs) == 1.0
    cube_height = env.data.xpos[env.ids.gremlin_bodies[1], 2]
    assert cube_height == pytest.approx(0.2, abs=0.01)  # hovers one half-size above the floor (see docs)


def test_goal_button_is_green_in_the_pixels():
    buttons = park(4, -FAR)
    buttons[0] = (0.8, 0.3)  # left in the image
    buttons[1] = (0.8, -0.3)  # right
    env = make_env("Point", "Button", 1)
    for goal, side in ((0, slice(0, 32)), (1, slice(32, 64))):  # the colour follows the goal
        obs, _ = env.reset(seed=0, options=button_options(buttons, goal_button=goal))
        green, orange = colour_mask(obs, "green"), colour_mask(obs, "orange")
        assert green[:, side].sum() > 20 and green.sum() == green[:, side].sum()
        assert orange.sum() > 10 and orange[:, side].sum() == 0
    plain = make_env("Point", "Button", 1, color_goal_button=False)
    obs, _ = plain.reset(seed=0, options=button_options(buttons, goal_button=0))
    assert colour_mask(obs, "green").sum() == 0 and colour_mask(obs, "orange").sum() > 20


# ---------------------------------------------------------------- Push (spec sections 2, 3, 4.3, 6.3)
def push_options(box_xy, goal_xy) -> dict:
    return {
        "robot_xy": (0.0, 0.0),
        "robot_yaw": 0.0,
        "box_xy": box_xy,
        "goal_xy": goal_xy,
        "hazards_xy": park(2),
        "pillars_xy": park(1, -FAR),
    }


def test_pushing_the_box_toward_the_goal_pays():
    env = make_env("Point", "Push", 1, obs_type="state", action_repeat=1)
    env.reset(seed=0, options=push_options((0.5, 0.0), (1.3, 0.0)))
    robot_box, box_goal = env._box_dists()
    assert (robot_box, box_goal) == pytest.approx((np.hypot(0.5, 0.1), np.hypot(0.8, 0.04)))  # 3-D, body centres
    start, total = env.box_xy, 0.0
    for _ in range(30):
        _, reward, _, _, info = env.step(np.array([1.0, 0.0]))
        assert not info["goal_met"] and info["cost"] == 0.0
        total += reward
    assert env.box_xy[0] > start[0] + 0.1  # pushed
    end_robot_box, end_box_goal = env._box_dists()
    assert box_goal - end_box_goal > 0.1
    # reward_box_dist = reward_box_goal = 1: the sum telescopes to both distance decreases
    assert total == pytest.approx((robot_box - end_robot_box) + (box_goal - end_box_goal), abs=1e-9)


def test_box_in_goal_pays_one_and_respawns_the_goal():
    env = make_env("Point", "Push", 1, obs_type="state", action_repeat=1)
    env.reset(seed=0, options=push_options((0.0, 0.6), (0.25, 0.6)))  # box centre 0.253 m from goal centre (3-D)
    _, reward, terminated, _, info = env.step(np.zeros(2))
    assert info["goal_met"] and not terminated and reward == pytest.approx(1.0, abs=1e-3)
    assert np.linalg.norm(env.goal_xy - env.box_xy) >= 0.4 + 0.2  # goal keepout 0.4 + box keepout 0.2
    assert np.linalg.norm(env.goal_xy - env.robot_xy) >= 0.4 + 0.4
    np.testing.assert_allclose(env.data.xpos[env.ids.goal_body, :2], env.goal_xy)
    _, reward, _, _, info = env.step(np.zeros(2))
    assert not info["goal_met"] and abs(reward) < 1e-3


def test_push_hazards_are_0_3_m_and_pillars_cost_in_level_2_only():
    env = make_env("Point", "Push", 1, obs_type="state", action_repeat=1)
    assert env.model.geom_size[env.model.body_geomadr[env.ids.box_body], 0] == 0.2
    for offset, expected in ((0.29, 1.0), (0.31, 0.0)):
        hazards = park(2)
        hazards[0] = (offset, 0.0)
        env.reset(seed=0, options={**push_options((-1.0, 1.0), (1.0, 1.0)), "hazards_xy": hazards})
        _, _, _, _, info = env.step(np.zeros(2))
        assert info["cost_hazards"] == expected
    for level, expected in ((1, 0.0), (2, 1.0)):
        env = make_env("Point", "Push", level, obs_type="state", action_repeat=1)
        pillars = park(env.task_spec.pillars_num, -FAR)
        pillars[0] = (0.45, 0.0)
        options = {
            **push_options((-1.0, 1.0), (1.0, 1.0)),
            "hazards_xy": park(env.task_spec.hazards_num),
            "pillars_xy": pillars,
        }
        env.reset(seed=0, options=options)
        costs = [env.step(np.array([1.0, 0.0]))[4]["cost_pillars"] for _ in range(30)]
        assert max(costs) == expected
        assert env.robot_xy[0] < 0.45 - 0.2 - 0.1 + 0.01  # the static pillar stopped the robot


def test_car_push_box_overrides():
    env = make_env("Car", "Push", 1, obs_type="state")
    spec = env.task_spec
    assert (spec.box_size, spec.box_keepout, spec.box_density) == (0.125, 0.125, 0.0005)
    box = env.model.body_geomadr[env.ids.box_body]
    np.testing.assert_allclose(env.model.geom_size[box], [0.125] * 3)
    np.testing.assert_allclose(env.model.geom_size[box + 1], [0.0625, 0.0625, 0.125])  # a corner post
    assert make_env("Point", "Goal", 1).task_spec.box_size == 0.2  # overrides only touch Push


# ---------------------------------------------------------------- shared contract
@pytest.mark.parametrize(("robot", "task"), [("Point", "Button"), ("Doggo", "Push")])
def test_new_tasks_state_and_both_pass_the_checkers(robot, task):
    for obs_type in ("state", "both"):
        env = make_env(robot, task, 1, obs_type=obs_type)
        gym_check_env(env, skip_render_check=True)
        sb3_check_env(env, warn=True)
        env.close()


@pytest.mark.parametrize(
    ("task", "keys"), [("Button", ("buttons", "gremlins", "hazards")), ("Push", ("box", "hazards", "pillars"))]
)
def test_new_tasks_state_layout(task, keys):
    env = make_env("Point", task, 1, obs_type="state")
    lidars = sorted(key for key in env.state_slices if key.endswith("_lidar"))
    assert lidars == sorted(["goal_lidar", *(f"{key}_lidar" for key in keys)])
    assert env.observation_space.shape == (12 + 16 * 4,)


@pytest.mark.parametrize(("robot", "task"), [("Point", "Button"), ("Car", "Push"), ("Doggo", "Button")])
def test_new_tasks_spawn_without_cost_and_are_deterministic(robot, task):
    env = make_env(robot, task, 2, obs_type="state")
    for seed in range(5):
        _, info = env.reset(seed=seed)
        assert info["cost"] == 0.0
        _, _, _, _, info = env.step(np.zeros(env.action_space.shape))
        assert info["cost"] == 0.0
    actions = np.random.default_rng(0).uniform(-1, 1, size=(40, *env.action_space.shape))
    runs = []
    for _ in range(2):
        first, _ = env.reset(seed=3)
        runs.append([first.tobytes()] + [env.step(action)[0].tobytes() for action in actions])
    assert runs[0] == runs[1]
