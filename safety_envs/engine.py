"""The Safety-Gym Goal, Button and Push tasks as a Gymnasium env: dynamics, reward, cost and observations.

The rules follow Safety-Gym's; ``docs/safety_envs.md`` lists each of them.
"""

import warnings
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from safety_envs.layout import ResamplingError, sample_layout, sample_position
from safety_envs.tasks import OBS_TYPES, TaskSpec, get_robot, get_task
from safety_envs.world import BUTTON_RGBA, GOAL_BUTTON_RGBA, build_world
from safety_envs.wrappers import COST_KEYS

LIDAR_NUM_BINS = 16
LIDAR_MAX_DIST = 3.0  # m
SENSOR_KEYS = ("accelerometer", "velocimeter", "gyro", "magnetometer")
REWARD_EXCEPTION = -10.0
# Resting free bodies (vases) sleep below this velocity, far under the 1e-4 m/s vase-velocity cost threshold.
SLEEP_TOLERANCE = 1e-6
# MuJoCo's sleeping islands arrived in MuJoCo 3.4.0; without them every body is simulated at every substep.
SLEEP_FLAG = getattr(mujoco.mjtEnableBit, "mjENBL_SLEEP", None)
# Vision tessellation: 16 slices and 8 stacks instead of MuJoCo's 28 and 16 halve the CPU render time.
RENDER_NUM_SLICES = 16
RENDER_NUM_STACKS = 8
_PHYSICS_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL, mujoco.mjtWarning.mjWARN_BADQACC)
_RESET_OPTIONS = (
    "robot_xy",
    "robot_yaw",
    "goal_xy",
    "goal_button",
    "box_xy",
    "buttons_xy",
    "hazards_xy",
    "vases_xy",
    "pillars_xy",
    "gremlins_xy",
)


def _yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    """Quaternion (w, x, y, z) of a rotation by ``yaw`` rad about z."""
    return (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))


class SafetyGymEnv(gym.Env):
    """Safety-Gym ``{robot}{task}{level}`` rebuilt on current MuJoCo, with first-person pixel observations.

    One agent step runs ``action_repeat`` simulator steps of ``frameskip`` (10) physics substeps each, with the
    action held; rewards and costs are summed over the repeat and the image is rendered once, after the last
    simulator step. An episode is 1000 simulator steps (500 agent steps with the default repeat of 2) and ends
    with ``truncated=True``; the tasks never terminate (``terminated`` is only set if no new goal position can
    be found, which the keepouts make practically impossible).

    Tasks: ``Goal`` (reach the green disc), ``Button`` (touch the goal button; a new one is drawn after each
    press) and ``Push`` (push the yellow box into the green disc); each goal pays +1 and is then replaced.

    Actions: Box(-1, 1, (nu,)) float32, nu = 2 (Point, Car) or 12 (Doggo). Out-of-range values are clipped to
    the actuators' ``ctrlrange`` [-1, 1] as in the original; the actuators' ``forcerange`` then saturates them
    further (Point forward force at |a| >= 0.05, Car wheel torque at |a| >= 0.02). NaN/inf or a wrong shape
    raises ``ValueError``.

    ``info`` on every step: ``cost`` (float: binary per simulator step, summed over the repeat) and its parts
    ``cost_hazards``, ``cost_vases`` (contact or velocity), ``cost_vases_contact``, ``cost_vases_velocity``,
    ``cost_pillars``, ``cost_buttons`` (wrong button), ``cost_gremlins`` (same convention; 0 where the task does
    not constrain them), ``goal_met`` (bool: a goal was reached during the repeat) and ``sim_steps`` (simulator
    steps so far).

    :param robot: ``"Point"``, ``"Car"`` or ``"Doggo"``
    :param task: ``"Goal"``, ``"Button"`` or ``"Push"``
    :param level: 0, 1 or 2
    :param obs_type: ``"pixels"`` (uint8 (height, width, 3) image from the robot's ``vision`` camera, upright;
        (height, 2 * width, 3) with ``back_camera``),
        ``"state"`` (float32 Safety-Gym vector: sensors and 16-bin lidars) or ``"both"`` (Dict of the two)
    :param action_repeat: simulator steps per agent step
    :param width: image width in pixels
    :param height: image height in pixels
    :param render_mode: ``None`` or ``"rgb_array"`` (third-person tracking view for videos)
    :param render_width: width of the ``render()`` image in pixels
    :param render_height: height of the ``render()`` image in pixels
    :param physics_sleep: let MuJoCo put resting vases to sleep (velocity tolerance 1e-6, below the 1e-4 m/s
        cost threshold) until something touches them: 3-4x faster physics in Goal2, same costs; the robot never
        sleeps. ``False`` simulates every body at every substep, as does a MuJoCo older than 3.4 (with a warning).
    :param color_goal_button: in Button tasks, colour the goal button green (the others stay orange), as the
        LAMBDA and Safe SLAC pixel pipelines did; ``False`` keeps Safety-Gym's all-orange buttons
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 25}  # noqa: RUF012

    def __init__(
        self,
        robot: str = "Point",
        task: str = "Goal",
        level: int = 1,
        obs_type: str = "pixels",
        action_repeat: int = 2,
        width: int = 64,
        height: int = 64,
        render_mode: str | None = None,
        render_width: int = 256,
        render_height: int = 256,
        physics_sleep: bool = True,
        color_goal_button: bool = True,
        back_camera: bool = False,
    ) -> None:
        self.robot_spec = get_robot(robot)
        self.task_spec: TaskSpec = get_task(task, level, self.robot_spec)
        if obs_type not in OBS_TYPES:
            raise ValueError(f"Unknown obs_type {obs_type!r}; valid obs_types: {list(OBS_TYPES)}")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"Unknown render_mode {render_mode!r}; valid render modes: [None, 'rgb_array']")
        for name, value in (("action_repeat", action_repeat), ("width", width), ("height", height)):
            if int(value) != value or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        self.obs_type = obs_type
        self.action_repeat = int(action_repeat)
        self.width, self.height = int(width), int(height)
        self.render_mode = render_mode
        self.render_width, self.render_height = int(render_width), int(render_height)
        self.color_goal_button = bool(color_goal_button)
        if not isinstance(back_camera, (bool, np.bool_)):
            raise ValueError(f"back_camera must be True or False, got {back_camera!r}")
        self.back_camera = bool(back_camera)

        self.model, self.ids = build_world(self.robot_spec, self.task_spec, (self.width, self.height))
        self.model.vis.quality.offsamples = 0
        self.model.vis.quality.numslices = RENDER_NUM_SLICES
        self.model.vis.quality.numstacks = RENDER_NUM_STACKS
        if physics_sleep and SLEEP_FLAG is None:
            warnings.warn(
                f"MuJoCo {mujoco.__version__} cannot put bodies to sleep (MuJoCo 3.4 added it): physics_sleep is off, "
                "the same dynamics and costs, slower in Goal2 tasks. pip install 'mujoco>=3.4' to have it",
                stacklevel=2,
            )
        elif physics_sleep:
            self.model.opt.enableflags |= SLEEP_FLAG
            self.model.opt.sleep_tolerance = SLEEP_TOLERANCE
        self.data = mujoco.MjData(self.model)
        self.sim_dt = self.model.opt.timestep * self.task_spec.frameskip  # s per simulator step
        # One frame per agent step: 25 at Safety-Gym's 0.002 s timestep, frameskip 10 and action repeat 2; 12.5 at 4
        self.metadata = {**self.metadata, "render_fps": round(1.0 / (self.sim_dt * self.action_repeat), 6)}

        ctrlrange = self.model.actuator_ctrlrange
        self._ctrl_low, self._ctrl_high = ctrlrange[:, 0].copy(), ctrlrange[:, 1].copy()
        self.action_space = spaces.Box(-1.0, 1.0, shape=(self.model.nu,), dtype=np.float32)
        self._build_state_layout()
        frame_width = 2 * self.width if self.back_camera else self.width
        pixels = spaces.Box(0, 255, shape=(self.height, frame_width, 3), dtype=np.uint8)
        state = spaces.Box(-np.inf, np.inf, shape=(self._state_size,), dtype=np.float32)
        self.observation_space = {"pixels": pixels, "state": state, "both": spaces.Dict(pixels=pixels, state=state)}[obs_type]

        self._scene_option = mujoco.MjvOption()
        self._scene_option.geomgroup[:] = 0
        self._scene_option.geomgroup[:6] = 1  # goal 0, box/buttons 1, pillars 2, hazards 3, vases 4, gremlins 5
        self._scene_option.sitegroup[:] = 0
        self._vision = self._make_renderer(self.height, self.width) if obs_type != "state" else None
        self._tracker: mujoco.Renderer | None = None
        self._frame = np.zeros((self.height, self.width, 3), dtype=np.uint8)
        self._back_frame = np.zeros((self.height, self.width, 3), dtype=np.uint8)

        spec = self.task_spec
        self._hazards_xy = np.zeros((spec.hazards_num, 2))
        self._buttons_xy = np.zeros((spec.buttons_num, 2))
        self._pillars_xy = np.zeros((spec.pillars_num, 2))
        self._gremlins_centre = np.zeros((spec.gremlins_num, 2))  # centres of the gremlins' circles
        self._goal_xy = np.zeros(2)
        self._goal_button = 0
        self._buttons_timer = 0  # simulator steps left without wrong-button cost and buttons lidar
        self._last_dist = 0.0  # robot to goal (planar), or robot to box (3-D) in Push
        self._last_box_goal = 0.0  # box to goal (3-D), Push only
        self.sim_steps = 0
        self._vase_dofs = self.ids.vase_dof[:, None] + np.arange(3)
        mocaps = self.ids.gremlin_mocaps  # consecutive ids: a slice assigns faster than an index array
        contiguous = len(mocaps) > 0 and np.array_equal(mocaps, np.arange(mocaps[0], mocaps[0] + len(mocaps)))
        self._gremlin_mocaps = slice(int(mocaps[0]), int(mocaps[-1]) + 1) if contiguous else mocaps

    # ------------------------------------------------------------------ rendering
    def _make_renderer(self, height: int, width: int) -> mujoco.Renderer:
        """A renderer tuned for speed: buffer the size of the image, no shadows, reflections or multisampling."""
        vis = self.model.vis.global_
        vis.offwidth, vis.offheight = max(vis.offwidth, width), max(vis.offheight, height)
        try:
            renderer = mujoco.Renderer(self.model, height=height, width=width)
        except Exception as error:
            raise RuntimeError(
                "Could not create a MuJoCo rendering context. On a headless machine set MUJOCO_GL=egl (GPU or Mesa's "
                "llvmpipe) or MUJOCO_GL=osmesa before importing mujoco/safety_envs; or use obs_type='state'."
            ) from error
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0
        return renderer

    def _render_vision(self) -> np.ndarray:
        """The first-person image (height, width, 3) uint8, upright; (height, 2 * width, 3) with the back camera's."""
        if self._vision is None:  # closed, then used again
            self._vision = self._make_renderer(self.height, self.width)
        self._vision.update_scene(self.data, camera=self.ids.vision_camera, scene_option=self._scene_option)
        front = self._vision.render(out=self._frame)
        if not self.back_camera:
            return front.copy()
        self._vision.update_scene(self.data, camera=self.ids.vision_back_camera, scene_option=self._scene_option)
        return np.concatenate((front, self._vision.render(out=self._back_frame)), axis=1)

    def render(self) -> np.ndarray | None:
        """Third-person tracking view (render_height, render_width, 3) uint8 when ``render_mode="rgb_array"``."""
        if self.render_mode is None:
            return None
        if self._tracker is None:
            self._tracker = self._make_renderer(self.render_height, self.render_width)
        self._tracker.update_scene(self.data, camera=self.ids.track_camera, scene_option=self._scene_option)
        return self._tracker.render()

    def close(self) -> None:
        """Release the rendering contexts (safe to call twice)."""
        for renderer in (self._vision, self._tracker):
            if renderer is not None:
                renderer.close()
        self._vision = self._tracker = None

    # ------------------------------------------------------------------ observations
    def _build_state_layout(self) -> None:
        """Slices of the flat state vector, in sorted key order as Safety-Gym flattens its observation dict.

        Sensors: the four base sensors and the robot's touch sensors (read as is), hinge-joint velocities (1 each),
        hinge-joint positions as (sin, cos), ball-joint angular velocities (3) and ball-joint quaternions as 3x3
        rotation matrices (Safety-Gym's ``sensors_angle_components``). Then one 16-bin lidar per observed object kind.
        """
        model, spec = self.model, self.task_spec
        sizes: dict[str, int] = {}
        self._direct_sensors: dict[str, tuple[int, int]] = {}  # name: (sensordata address, dim)
        self._hinge_pos: dict[str, int] = {}
        self._ball_quat: dict[str, int] = {}
        for sensor in range(model.nsensor):
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SENSOR, sensor)
            adr, dim, kind = int(model.sensor_adr[sensor]), int(model.sensor_dim[sensor]), model.sensor_type[sensor]
            on_hinge = model.sensor_objtype[sensor] == mujoco.mjtObj.mjOBJ_JOINT and (
                model.jnt_type[model.sensor_objid[sensor]] == mujoco.mjtJoint.mjJNT_HINGE
            )
            if name in SENSOR_KEYS or name in self.robot_spec.touch_sensors or kind == mujoco.mjtSensor.mjSENS_BALLANGVEL:
                self._direct_sensors[name] = (adr, dim)
                sizes[name] = dim
            elif kind == mujoco.mjtSensor.mjSENS_JOINTVEL and on_hinge:
                self._direct_sensors[name] = (adr, 1)
                sizes[name] = 1
            elif kind == mujoco.mjtSensor.mjSENS_JOINTPOS and on_hinge:
                self._hinge_pos[name] = adr
                sizes[name] = 2
            elif kind == mujoco.mjtSensor.mjSENS_BALLQUAT:
                self._ball_quat[name] = adr
                sizes[name] = 9
        lidars = {"goal_lidar": True, "box_lidar": spec.name == "Push", "hazards_lidar": spec.observe_hazards}
        lidars["vases_lidar"] = spec.observe_vases
        lidars["pillars_lidar"] = spec.pillars_num > 0 and spec.observe_pillars
        lidars["gremlins_lidar"] = spec.gremlins_num > 0 and spec.observe_gremlins
        lidars["buttons_lidar"] = spec.buttons_num > 0 and spec.observe_buttons
        self._lidar_keys = [key for key, on in lidars.items() if on]
        sizes.update(dict.fromkeys(self._lidar_keys, LIDAR_NUM_BINS))
        self.state_slices: dict[str, slice] = {}
        offset = 0
        for key in sorted(sizes):
            self.state_slices[key] = slice(offset, offset + sizes[key])
            offset += sizes[key]
        self._state_size = offset

    def _lidar(self, positions: np.ndarray) -> np.ndarray:
        """Safety-Gym pseudo-lidar (16,): per bin, max over objects of (3 - distance) / 3, aliased to neighbours.

        :param positions: (k, 2) world xy of the objects, m
        """
        out = np.zeros(LIDAR_NUM_BINS)
        if len(positions) == 0:
            return out
        robot_pos = self.data.xpos[self.ids.robot_body]
        rel = np.empty((len(positions), 3))
        rel[:, :2] = positions - robot_pos[:2]
        rel[:, 2] = -robot_pos[2]
        ego = rel @ self.data.xmat[self.ids.robot_body].reshape(3, 3)  # robot frame
        angle = np.arctan2(ego[:, 1], ego[:, 0]) % (2 * np.pi)
        bin_size = 2 * np.pi / LIDAR_NUM_BINS
        scaled = angle / bin_size
        bins = np.minimum(scaled.astype(np.int64), LIDAR_NUM_BINS - 1)
        alias = scaled - bins
        sensor = np.maximum(0.0, LIDAR_MAX_DIST - np.hypot(ego[:, 0], ego[:, 1])) / LIDAR_MAX_DIST
        np.maximum.at(out, bins, sensor)
        np.maximum.at(out, (bins + 1) % LIDAR_NUM_BINS, alias * sensor)
        np.maximum.at(out, (bins - 1) % LIDAR_NUM_BINS, (1 - alias) * sensor)
        return out

    def _state(self) -> np.ndarray:
        """The flat Safety-Gym state vector, float32; ``state_slices`` names its parts."""
        state = np.empty(self._state_size, dtype=np.float32)
        sensordata, slices = self.data.sensordata, self.state_slices
        for key, (adr, dim) in self._direct_sensors.items():
            state[slices[key]] = sensordata[adr : adr + dim]
        for key, adr in self._hinge_pos.items():
            state[slices[key]] = (np.sin(sensordata[adr]), np.cos(sensordata[adr]))
        for key, adr in self._ball_quat.items():
            matrix = np.empty(9)
            mujoco.mju_quat2Mat(matrix, sensordata[adr : adr + 4])
            state[slices[key]] = matrix
        for key in self._lidar_keys:
            state[slices[key]] = self._lidar(self._lidar_positions(key))
        return state

    def _lidar_positions(self, key: str) -> np.ndarray:
        """World xy (k, 2) of the objects seen by lidar ``key``; none for the buttons while their timer runs."""
        if key == "goal_lidar":
            return self._goal_xy[None]
        if key == "box_lidar":
            return self.data.xpos[[self.ids.box_body], :2]
        if key == "hazards_lidar":
            return self._hazards_xy
        if key == "vases_lidar":
            return self.data.xpos[self.ids.vase_bodies, :2]
        if key == "pillars_lidar":
            return self._pillars_xy
        if key == "gremlins_lidar":
            return self.data.xpos[self.ids.gremlin_bodies, :2]
        return self._buttons_xy if self._buttons_timer == 0 else np.zeros((0, 2))

    def _observe(self) -> np.ndarray | dict[str, np.ndarray]:
        if self.obs_type == "pixels":
            return self._render_vision()
        if self.obs_type == "state":
            return self._state()
        return {"pixels": self._render_vision(), "state": self._state()}

    # ------------------------------------------------------------------ layout
    def _place_robot(self, xy: np.ndarray, yaw: float) -> None:
        """Set the robot's root joints: planar slide/slide/hinge (Point) or a free joint (Car, Doggo)."""
        adr = self.ids.robot_qpos
        if len(adr) == 1:  # free joint: keep the spawn height, rotate about z
            start = adr[0]
            self.data.qpos[start : start + 2] = xy
            self.data.qpos[start + 3 : start + 7] = _yaw_quat(yaw)
        else:  # slide x, slide y, hinge z
            self.data.qpos[adr] = (xy[0], xy[1], yaw)

    def _place_free_body(self, qpos_adr: int, xy: np.ndarray, yaw: float | None = None) -> None:
        """Move a free body (vase, box) to ``xy``, keeping its height; rotate it to ``yaw`` if given."""
        self.data.qpos[qpos_adr : qpos_adr + 2] = xy
        if yaw is not None:
            self.data.qpos[qpos_adr + 3 : qpos_adr + 7] = _yaw_quat(yaw)

    def _move_goal(self, xy: np.ndarray) -> None:
        self._goal_xy = np.array(xy, dtype=np.float64)
        self.data.mocap_pos[self.ids.goal_mocap, :2] = xy

    def _set_goal_button(self, index: int) -> None:
        """Make button ``index`` the goal (and, with ``color_goal_button``, the only green one)."""
        self._goal_button = int(index)
        self._goal_xy = self._buttons_xy[index].copy()
        if self.color_goal_button:
            self.model.geom_rgba[self.ids.button_geoms] = BUTTON_RGBA
            self.model.geom_rgba[self.ids.button_geoms[index]] = GOAL_BUTTON_RGBA

    def _gremlin_targets(self, time: float | np.ndarray) -> np.ndarray:
        """Positions (..., n_gremlins, 3) of the gremlins' mocap bodies at sim ``time`` (s), a scalar or (..., 1).

        Each orbits its centre at radius ``gremlins_travel``, 1 rad/s, all in phase: centre + travel (sin t, cos t).
        The height is twice the cube's half-size: Safety-Gym sets the mocap height to the half-size and its weld keeps
        the cube's spawn height (the half-size again) above it, so the cubes hover one half-size above the floor.
        """
        spec = self.task_spec
        time = np.asarray(time, dtype=np.float64)
        targets = np.empty((*time.shape[:-1], spec.gremlins_num, 3)) if time.ndim else np.empty((spec.gremlins_num, 3))
        offset = spec.gremlins_travel * np.stack([np.sin(time), np.cos(time)], axis=-1)  # (..., 1, 2) or (2,)
        targets[..., :2] = self._gremlins_centre + offset
        targets[..., 2] = 2 * spec.gremlins_size
        return targets

    def _place_gremlins(self, yaws: np.ndarray | None = None) -> None:
        """Put the gremlin mocap bodies and cubes at their targets for the current sim time, at rest."""
        targets = self._gremlin_targets(self.data.time)
        self.data.mocap_pos[self.ids.gremlin_mocaps] = targets
        for i, adr in enumerate(self.ids.gremlin_qpos):
            if yaws is not None:
                self.data.mocap_quat[self.ids.gremlin_mocaps[i]] = _yaw_quat(yaws[i])
            self.data.qpos[adr : adr + 3] = targets[i]
            self.data.qpos[adr + 3 : adr + 7] = self.data.mocap_quat[self.ids.gremlin_mocaps[i]]

    def _layout_objects(self) -> list[tuple[str, float]]:
        """(name, keepout) of every placed object, in Safety-Gym's placement order."""
        spec = self.task_spec
        objects = [("robot", self.robot_spec.keepout)]
        if spec.has_goal_body:
            objects.append(("goal", spec.goal_keepout))
        if spec.name == "Push":
            objects.append(("box", spec.box_keepout))
        for kind, num, keepout in (
            ("button", spec.buttons_num, spec.buttons_keepout),
            ("hazard", spec.hazards_num, spec.hazards_keepout),
            ("vase", spec.vases_num, spec.vases_keepout),
            ("pillar", spec.pillars_num, spec.pillars_keepout),
            ("gremlin", spec.gremlins_num, spec.gremlins_keepout),
        ):
            objects += [(f"{kind}{i}", keepout) for i in range(num)]
        return objects

    def _reset_layout(self) -> None:
        """Sample and apply a fresh layout, then draw the goal once more (Goal, Push) or pick a goal button (Button)."""
        spec, rng = self.task_spec, self.np_random
        objects = self._layout_objects()
        layout = sample_layout(rng, objects, spec.placements_extents, spec.placements_margin)
        yaws = dict(zip(layout, rng.uniform(0.0, 2 * np.pi, size=len(objects)), strict=True))

        if spec.has_goal_body:
            others = [(name, keepout) for name, keepout in objects if name != "goal"]
            goal_xy = sample_position(
                rng,
                spec.goal_keepout,
                spec.placements_extents,
                np.array([layout[name] for name, _ in others]),
                np.array([keepout for _, keepout in others]),
                spec.placements_margin,
            )
            if goal_xy is None:
                raise ResamplingError("Failed to draw a goal position at reset")
            self._move_goal(goal_xy)

        self._place_robot(layout["robot"], yaws["robot"])
        if spec.name == "Push":
            self._place_free_body(self.ids.box_qpos, layout["box"], yaws["box"])
        for kind, positions, mocaps in (
            ("button", self._buttons_xy, self.ids.button_mocaps),
            ("hazard", self._hazards_xy, self.ids.hazard_mocaps),
            ("pillar", self._pillars_xy, self.ids.pillar_mocaps),
        ):
            for i in range(len(positions)):
                positions[i] = layout[f"{kind}{i}"]
            self.data.mocap_pos[mocaps, :2] = positions
        for i, adr in enumerate(self.ids.vase_qpos):
            self._place_free_body(adr, layout[f"vase{i}"], yaws[f"vase{i}"])
        for i in range(spec.gremlins_num):
            self._gremlins_centre[i] = layout[f"gremlin{i}"]
        self._place_gremlins(np.array([yaws[f"gremlin{i}"] for i in range(spec.gremlins_num)]))
        if spec.name == "Button":
            self._set_goal_button(rng.integers(spec.buttons_num))

    def _respawn_goal(self) -> bool:
        """Draw a new goal against the current robot, box and vase positions and the fixed objects (gremlins: their
        circles' centres); False if none is found."""
        spec = self.task_spec
        xpos = self.data.xpos
        box_xy = xpos[[self.ids.box_body], :2] if spec.name == "Push" else np.zeros((0, 2))
        parts = [
            (xpos[[self.ids.robot_body], :2], self.robot_spec.keepout),
            (box_xy, spec.box_keepout),
            (self._buttons_xy, spec.buttons_keepout),
            (self._hazards_xy, spec.hazards_keepout),
            (xpos[self.ids.vase_bodies, :2], spec.vases_keepout),
            (self._pillars_xy, spec.pillars_keepout),
            (self._gremlins_centre, spec.gremlins_keepout),
        ]
        xy = np.concatenate([positions for positions, _ in parts])
        keepout = np.concatenate([np.full(len(positions), keepout) for positions, keepout in parts])
        goal_xy = sample_position(
            self.np_random, spec.goal_keepout, spec.placements_extents, xy, keepout, spec.placements_margin
        )
        if goal_xy is None:
            return False
        self._move_goal(goal_xy)
        mujoco.mj_kinematics(self.model, self.data)  # the goal's world pose, for rendering and the box-goal distance
        return True

    def _next_goal(self) -> bool:
        """After a goal is met: start the button timer and pick the next goal button, or respawn the goal disc.
        Then re-initialise the distances, so the respawn gives no reward jump. False if no goal could be placed."""
        spec = self.task_spec
        self._buttons_timer = spec.buttons_resampling_delay
        if spec.name == "Button":
            self._set_goal_button(self.np_random.integers(spec.buttons_num))
        elif not self._respawn_goal():
            return False
        self._init_distances()
        return True

    # ------------------------------------------------------------------ rules
    def _goal_dist(self) -> float:
        """Planar distance (m) from the robot body origin to the goal centre (the goal button in Button tasks)."""
        robot_xy = self.data.xpos[self.ids.robot_body, :2]
        return float(np.hypot(robot_xy[0] - self._goal_xy[0], robot_xy[1] - self._goal_xy[1]))

    def _box_dists(self) -> tuple[float, float]:
        """3-D distances (m) robot origin to box centre and box centre to goal centre (Push)."""
        box = self.data.xpos[self.ids.box_body]
        return (
            float(np.linalg.norm(box - self.data.xpos[self.ids.robot_body])),
            float(np.linalg.norm(box - self.data.xpos[self.ids.goal_body])),
        )

    def _init_distances(self) -> None:
        if self.task_spec.name == "Push":
            self._last_dist, self._last_box_goal = self._box_dists()
        else:
            self._last_dist = self._goal_dist()

    def _dense_reward(self) -> float:
        """Distance progress of this simulator step, clipped to +-``reward_clip``; updates the last distances.

        Goal, Button: (d_{t-1} - d_t) * reward_distance, d the planar robot-goal distance. Push: the robot-box term
        (gated off within ``box_null_dist * box_size`` of the box; the gate is 0 in every task) plus the box-goal term.
        """
        spec = self.task_spec
        if spec.name == "Push":
            box_dist, box_goal = self._box_dists()
            gate = self._last_dist > spec.box_null_dist * spec.box_size
            reward = (self._last_dist - box_dist) * spec.reward_box_dist * gate
            reward += (self._last_box_goal - box_goal) * spec.reward_box_goal
            self._last_dist, self._last_box_goal = box_dist, box_goal
        else:
            dist = self._goal_dist()
            reward = (self._last_dist - dist) * spec.reward_distance
            self._last_dist = dist
        return float(np.clip(reward, -spec.reward_clip, spec.reward_clip))

    def _robot_contacts(self) -> np.ndarray:
        """Ids of the geoms in contact with a robot geom (robot-robot contacts give robot geoms)."""
        pairs = self.data.contact.geom[: self.data.ncon]
        robot = self.ids.robot_geom_mask[pairs]
        return np.concatenate([pairs[robot[:, 0], 1], pairs[robot[:, 1], 0]])

    def _costs(self, touched: np.ndarray) -> dict[str, float]:
        """Binary (0/1) cost components of the current (post-step) state, the total ``cost`` included.

        :param touched: ids of the geoms touching the robot (from ``_robot_contacts``)
        """
        spec, ids = self.task_spec, self.ids
        costs = dict.fromkeys(COST_KEYS, 0.0)
        if spec.constrain_hazards and spec.hazards_num:
            delta = self._hazards_xy - self.data.xpos[ids.robot_body, :2]
            # cost (size - dist) > 0 only strictly inside a disc, measured from the robot body origin
            costs["cost_hazards"] = float(np.any(np.einsum("ij,ij->i", delta, delta) < spec.hazards_size**2))
        if spec.constrain_vases and spec.vases_num:
            costs["cost_vases_contact"] = float(spec.vases_contact_cost > 0 and bool(np.any(ids.vase_geom_mask[touched])))
            if spec.vases_velocity_cost > 0:
                speed = np.linalg.norm(self.data.qvel[self._vase_dofs], axis=1)
                costs["cost_vases_velocity"] = float(np.any(speed >= spec.vases_velocity_threshold))
            costs["cost_vases"] = max(costs["cost_vases_contact"], costs["cost_vases_velocity"])
        if spec.constrain_pillars and spec.pillars_num:
            costs["cost_pillars"] = float(spec.pillars_cost > 0 and bool(np.any(ids.pillar_geom_mask[touched])))
        if spec.constrain_buttons and spec.buttons_num and self._buttons_timer == 0:
            button = ids.button_of_geom[touched]
            wrong = bool(np.any((button >= 0) & (button != self._goal_button)))
            costs["cost_buttons"] = float(spec.buttons_cost > 0 and wrong)
        if spec.constrain_gremlins and spec.gremlins_num:
            costs["cost_gremlins"] = float(spec.gremlins_contact_cost > 0 and bool(np.any(ids.gremlin_geom_mask[touched])))
        costs["cost"] = max(costs.values())
        return costs

    def _goal_met(self, touched: np.ndarray) -> bool:
        """Goal: robot origin within ``goal_size`` of the goal; Push: box centre within ``goal_size`` (3-D) of it;
        Button: a robot geom touches the goal button."""
        spec = self.task_spec
        if spec.name == "Button":
            return bool(np.any(self.ids.button_of_geom[touched] == self._goal_button))
        distance = self._last_box_goal if spec.name == "Push" else self._last_dist
        return distance <= spec.goal_size

    def _check_action(self, action: np.ndarray) -> np.ndarray:
        """Validate the action and clip it to the actuators' ctrlrange."""
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise ValueError(f"Action has shape {action.shape}, expected {self.action_space.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"Action contains NaN or inf: {action}")
        return np.clip(action, self._ctrl_low, self._ctrl_high)

    def _physics_step(self) -> bool:
        """One simulator step: ``frameskip`` physics substeps (gremlin mocaps moved before each) then ``mj_forward``.
        False on a physics exception."""
        for warning in _PHYSICS_WARNINGS:
            self.data.warning[warning].number = 0
        if self.task_spec.gremlins_num:
            frameskip, dt = self.task_spec.frameskip, self.model.opt.timestep
            targets = self._gremlin_targets(self.data.time + dt * np.arange(frameskip)[:, None])
            mocap_pos = self.data.mocap_pos
            for substep in range(frameskip):
                mocap_pos[self._gremlin_mocaps] = targets[substep]
                mujoco.mj_step(self.model, self.data)
        else:
            mujoco.mj_step(self.model, self.data, nstep=self.task_spec.frameskip)
        mujoco.mj_forward(self.model, self.data)
        return not any(self.data.warning[warning].number for warning in _PHYSICS_WARNINGS)

    # ------------------------------------------------------------------ gymnasium API
    def _zero_info(self) -> dict[str, Any]:
        info: dict[str, Any] = dict.fromkeys(COST_KEYS, 0.0)
        info["goal_met"] = False
        info["sim_steps"] = self.sim_steps
        return info

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode with a fresh layout; returns (observation, info with zero costs).

        :param options: optional fixed placements overriding the sampled ones (for tests and demos; keepouts are
            then not enforced), all in m: ``robot_xy`` (2,), ``robot_yaw`` (rad), ``goal_xy`` (2,) (Goal, Push),
            ``goal_button`` (int, Button), ``box_xy`` (2,) (Push), ``buttons_xy`` (n_buttons, 2), ``hazards_xy``
            (n_hazards, 2), ``vases_xy`` (n_vases, 2), ``pillars_xy`` (n_pillars, 2), ``gremlins_xy`` (n_gremlins, 2):
            the centres of the gremlins' circles.
        """
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        self._buttons_timer = 0
        self._reset_layout()
        if options:
            self._apply_options(options)
        mujoco.mj_forward(self.model, self.data)
        self._init_distances()
        self.sim_steps = 0
        return self._observe(), self._zero_info()

    def _check_option_names(self, options: dict[str, Any]) -> None:
        spec = self.task_spec
        unknown = set(options) - set(_RESET_OPTIONS)
        if unknown:
            raise ValueError(f"Unknown reset options {sorted(unknown)}; valid options: {list(_RESET_OPTIONS)}")
        applies = {"goal_xy": spec.has_goal_body, "goal_button": spec.name == "Button", "box_xy": spec.name == "Push"}
        for key, ok in applies.items():
            if key in options and not ok:
                raise ValueError(f"reset option {key!r} does not apply to {spec.name} tasks")

    def _apply_options(self, options: dict[str, Any]) -> None:
        spec = self.task_spec
        self._check_option_names(options)

        def array(key: str, shape: tuple[int, ...]) -> np.ndarray:
            value = np.asarray(options[key], dtype=np.float64)
            if value.shape != shape:
                raise ValueError(f"reset option {key!r} has shape {value.shape}, expected {shape}")
            return value

        if "robot_xy" in options or "robot_yaw" in options:
            xy = array("robot_xy", (2,)) if "robot_xy" in options else self.robot_xy
            self._place_robot(xy, float(options.get("robot_yaw", self.robot_yaw)))
        if "goal_xy" in options:
            self._move_goal(array("goal_xy", (2,)))
        if "box_xy" in options:
            self._place_free_body(self.ids.box_qpos, array("box_xy", (2,)))
        for key, positions, mocaps in (
            ("buttons_xy", self._buttons_xy, self.ids.button_mocaps),
            ("hazards_xy", self._hazards_xy, self.ids.hazard_mocaps),
            ("pillars_xy", self._pillars_xy, self.ids.pillar_mocaps),
        ):
            if key in options:
                positions[:] = array(key, positions.shape)
                self.data.mocap_pos[mocaps, :2] = positions
        if "vases_xy" in options:
            vases_xy = array("vases_xy", (spec.vases_num, 2))
            for adr, xy in zip(self.ids.vase_qpos, vases_xy, strict=True):
                self._place_free_body(adr, xy)
        if "gremlins_xy" in options:
            self._gremlins_centre[:] = array("gremlins_xy", self._gremlins_centre.shape)
            self._place_gremlins()
        if spec.name == "Button":
            goal_button = options.get("goal_button", self._goal_button)
            if int(goal_button) != goal_button or not 0 <= goal_button < spec.buttons_num:
                raise ValueError(f"reset option 'goal_button' must be an int in [0, {spec.buttons_num}), got {goal_button!r}")
            self._set_goal_button(int(goal_button))

    @property
    def max_episode_steps(self) -> int:
        """Agent steps per episode: the task's simulator steps divided by the action repeat (500 for the thesis setting)."""
        return -(-self.task_spec.num_steps // self.action_repeat)

    # ------------------------------------------------------------------ positions (world frame, m)
    def _xy(self, bodies: np.ndarray) -> np.ndarray:
        mujoco.mj_kinematics(self.model, self.data)
        return self.data.xpos[bodies, :2].copy()

    @property
    def robot_xy(self) -> np.ndarray:
        """Planar position (2,) of the robot body origin."""
        return self._xy(self.ids.robot_body)

    @property
    def robot_yaw(self) -> float:
        """Heading (rad) of the robot body's x axis."""
        mujoco.mj_kinematics(self.model, self.data)
        xmat = self.data.xmat[self.ids.robot_body]
        return float(np.arctan2(xmat[3], xmat[0]))

    @property
    def goal_xy(self) -> np.ndarray:
        """Planar position (2,) of the goal centre (of the goal button in Button tasks)."""
        return self._goal_xy.copy()

    @property
    def goal_button(self) -> int:
        """Index of the goal button (Button tasks)."""
        return self._goal_button

    @property
    def buttons_timer(self) -> int:
        """Simulator steps left during which wrong buttons cost nothing and the buttons lidar reads zeros."""
        return self._buttons_timer

    @property
    def box_xy(self) -> np.ndarray:
        """Planar position (2,) of the push box centre (Push tasks)."""
        return self._xy(self.ids.box_body)

    @property
    def buttons_xy(self) -> np.ndarray:
        """Planar positions (n_buttons, 2) of the buttons."""
        return self._buttons_xy.copy()

    @property
    def hazards_xy(self) -> np.ndarray:
        """Planar positions (n_hazards, 2) of the hazard centres."""
        return self._hazards_xy.copy()

    @property
    def vases_xy(self) -> np.ndarray:
        """Planar positions (n_vases, 2) of the vase centres."""
        return self._xy(self.ids.vase_bodies)

    @property
    def pillars_xy(self) -> np.ndarray:
        """Planar positions (n_pillars, 2) of the pillar centres."""
        return self._pillars_xy.copy()

    @property
    def gremlins_xy(self) -> np.ndarray:
        """Planar positions (n_gremlins, 2) of the gremlin cubes now (not their circles' centres)."""
        return self._xy(self.ids.gremlin_bodies)

    def step(self, action: np.ndarray):
        """Run ``action_repeat`` simulator steps with ``action``; returns (obs, reward, terminated, truncated, info)."""
        spec = self.task_spec
        self.data.ctrl[:] = self._check_action(action)
        info = self._zero_info()
        reward = 0.0
        terminated = truncated = False
        for _ in range(self.action_repeat):
            if not self._physics_step():
                # Physics exception: end the episode (truncated) with Safety-Gym's reward -10 and cost 1.
                reward += REWARD_EXCEPTION
                info["cost"] += 1.0
                info["physics_exception"] = True
                self.sim_steps += 1
                truncated = True
                break
            step_reward = self._dense_reward()
            touched = self._robot_contacts()
            for key, value in self._costs(touched).items():
                info[key] += value
            self._buttons_timer = max(0, self._buttons_timer - 1)
            if self._goal_met(touched):
                step_reward += spec.reward_goal
                info["goal_met"] = True
                terminated = not self._next_goal()
            reward += step_reward
            self.sim_steps += 1
            if terminated or self.sim_steps >= spec.num_steps:
                truncated = not terminated
                break
        info["sim_steps"] = self.sim_steps
        return self._observe(), reward, terminated, truncated, info
