"""
A ceiling for the pixel learners: a scripted controller that reads only the agent's frames (RGB uint8, action repeat 4)
and has no memory. ``seek``: turn in place until the goal shows (``goal_view``'s in-view rule), then steer toward the
bearing of its green pixels, forward speed falling with the bearing. ``avoid``: the same, steering around the hazards
(and vases) it sees: each blue pixel is put on the floor by the camera's pinhole geometry, each vase by the lowest cyan
pixel of its columns; the robot heads along the visible direction nearest the goal whose straight path stays
``clearance`` m from them for ``stop_distance`` m (with none, the one with the longest free path), its speed falling
with that free path too (hazard points nearer than ``ignore_within`` m are not looked at: it cannot steer around them
any more, and they would keep it in a hazard it stands in). ``careful``: ``avoid`` that also backs away from a vase seen
within ``back_off`` m. The camera's pose on the robot is read from the simulator once at reset (its calibration); each
action is computed from the frame alone.

Per task and frame size, N seeded episodes (reset seeds 0..N-1): reward mean ± sample std, cost mean, the share of the
steps whose frame shows the goal (``goal_view.IN_VIEW_SHARE`` of the frame) and the share with the goal's centre inside
the camera's horizontal field of view (from the simulator state).

    python benchmarks/ceiling.py          # PointGoal1, PointGoal2, CarGoal1 at 32x32 and 64x64, 10 episodes each
    python benchmarks/ceiling.py --controllers avoid --tasks PointGoal1 --sizes 32 --episodes 3 --clearance 0.1

Tuning ``avoid`` (PointGoal1 at 32x32, 5 episodes, reset seeds 100-104, apart from the table's; reward / cost; the
``seek`` script there: 16.0 / 37.4). The Point coasts: its speed falls about 15% per agent step once its thrust stops
(about 0.6 m from full speed), so turning in place to search or to dodge slid it into hazards. A straight 0.8 m path
checked, turning in place when none is free: 14.0 / 39.2; creeping ahead while searching 13.7 / 49.2; thrusting back
while an obstacle is ahead 14.9 / 45-48; slowing toward the goal 10.5-14.9 / 23-53. Speed from the free path instead
(``stop_distance`` 0.5, 0.8, 1.2 m): 14.8 / 47.2, 14.2 / 26.0, 12.3 / 181 (one episode trapped in a hazard, the goal at
the frame's edge and the free heading at the other, speed 0 at both); speed 0 only at 90 degrees of bearing: 15.0 / 35.4
(0.8 m), 14.2 / 24.2 (1.2 m); with ``max_speed`` 0.6 or 0.75: 12.8 / 18.6 or 13.8 / 36.2 (0.8 m), 12.5 / 27.0 (0.6, 1.2
m). Kept: ``max_speed`` 0.6, ``stop_distance`` 0.8 m, ``slow_bearing`` 90 degrees, ``clearance`` 0.1 m. On PointGoal2
(4 episodes, seeds 100-103) that gave 12.8 / 107.5, 89 of it vases sliding after a touch (each touch, mostly slow, near a
vase hidden under the Point's own nose, costs about 25 simulator steps): a vase clearance of 0.2, 0.25, 0.3 m: 12.0 / 74.0,
8.7 / 72.8, 6.7 / 117; backing away from a vase seen within 0.25, 0.3 or 0.35 m (clearance 0.2): 6.2 / 30.3, 3.1 / 11.3,
2.4 / 11.3, with no vase cost from 0.3 m on. Kept: 0.2 m for ``avoid`` and ``careful``, backing away at 0.3 m for
``careful`` only (on the Goal1 tasks it lost reward, see ``benchmarks/results/ceiling.md``).
"""

import argparse
import shlex
import sys
from dataclasses import dataclass, replace
from pathlib import Path

# Run from a checkout without installing: the repository (safety_envs) and the benchmarks' shared modules
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import gymnasium as gym
import numpy as np
from goal_view import IN_VIEW_SHARE, goal_in_fov, goal_mask, hazard_mask, in_view, min_pixels, vase_mask
from machine import cpu_model

import safety_envs  # noqa: F401  (registers the ids)

ACTION_REPEAT = 4
# The action at which the drive saturates (safety_envs/robots/*.xml): the Point's forward motor at its force range 0.05
# (1.28 m/s), the Car's wheel motors at their torque range 0.02; the Point's turn is a velocity actuator, 1 = 3 rad/s
FULL_FORWARD = {"Point": 0.05, "Car": 0.02}
HAZARD_TOP = 0.03  # m: height of the hazard discs' top (safety_envs.world: centre 0.02, half-height 0.01)


@dataclass(frozen=True)
class CameraGeometry:
    """
    Where each pixel of the robot's frame looks, in the robot's level frame (x forward, y left, m from its centre).

    :param bearing: (H, W) horizontal bearing of each pixel's ray, rad, positive to the left
    :param hazard_floor: (H, W, 2) where each ray meets the hazards' top plane, NaN at and above the horizon
    :param floor: (H, W, 2) where each ray meets the floor, NaN at and above the horizon
    :param half_fov: half the horizontal field of view, rad
    """

    bearing: np.ndarray
    hazard_floor: np.ndarray
    floor: np.ndarray
    half_fov: float

    @classmethod
    def of(cls, env: gym.Env) -> "CameraGeometry":
        """The ``vision`` camera's geometry, from the pose of the camera on the robot after ``env.reset()``."""
        sim = env.unwrapped
        camera, data = sim.ids.vision_camera, sim.data
        rotation = data.cam_xmat[camera].reshape(3, 3)  # columns: the camera's x, y, z axes in the world
        forward = -rotation[:, 2] * np.array([1.0, 1.0, 0.0])  # the view direction, made level
        forward /= np.linalg.norm(forward)
        level = np.stack([forward, [-forward[1], forward[0], 0.0], [0.0, 0.0, 1.0]])  # rows: forward, left, up
        offset = level @ (data.cam_xpos[camera] - data.xpos[sim.ids.robot_body])
        height = float(data.cam_xpos[camera, 2])
        tan_half = np.tan(np.radians(sim.model.cam_fovy[camera]) / 2)
        u = ((np.arange(sim.width) + 0.5) / sim.width * 2 - 1) * tan_half * sim.width / sim.height
        v = (1 - (np.arange(sim.height) + 0.5) / sim.height * 2) * tan_half  # row 0 is the top of the frame
        rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], -1.0), axis=-1)  # (H, W, 3) in the camera's frame
        rays = rays @ (level @ rotation).T  # in the level frame

        def plane(z: float) -> np.ndarray:
            with np.errstate(divide="ignore", invalid="ignore"):
                scale = np.where(rays[..., 2] < 0, (z - height) / rays[..., 2], np.nan)
            return offset[:2] + scale[..., None] * rays[..., :2]

        half_fov = float(np.arctan(tan_half * sim.width / sim.height))
        return cls(np.arctan2(rays[..., 1], rays[..., 0]), plane(HAZARD_TOP), plane(0.0), half_fov)


@dataclass(frozen=True)
class Gains:
    """
    The controller's knobs.

    :param turn: turn command (1 = the robot's fastest turn) per rad of bearing
    :param slow_bearing: rad of bearing at which the forward speed has fallen to 0 (linearly from full at 0)
    :param max_speed: forward speed on a straight free path to the goal (1 = the robot's full speed)
    :param clearance: m a path keeps from every hazard point seen (``avoid``): the robot's centre must stay out
    :param vase_clearance: m a path keeps from every vase point seen (``avoid``): the robot's body (the Point's radius
        0.1 m, its nose 0.15 m) must not touch, and a vase that moves costs as long as it slides
    :param back_off: m from a vase point seen within which the robot backs away at full speed (``avoid``; 0: never)
    :param stop_distance: m of free path ahead below which the speed falls in proportion (``avoid``): the robots
        coast on (the Point about 0.6 m from full speed), so they must slow before an obstacle, not at it
    :param ignore_within: m around the robot's centre where hazard points are not looked at (``avoid``)
    :param headings: candidate headings across the field of view (``avoid``)
    """

    turn: float = 2.0
    slow_bearing: float = np.pi / 4
    max_speed: float = 1.0
    clearance: float = 0.1
    vase_clearance: float = 0.2
    back_off: float = 0.0
    stop_distance: float = 0.8
    ignore_within: float = 0.2
    headings: int = 21


CONTROLLERS = {
    "seek": Gains(),  # the script: full speed ahead, none at 45 degrees of bearing; hazards and vases ignored
    # Tuned on PointGoal1 at 32x32 (module docstring): the Point coasts about 0.6 m from full speed, so it goes slower
    "avoid": Gains(slow_bearing=np.pi / 2, max_speed=0.6),
    # For PointGoal2's ten vases: a touched vase slides on and costs for about 25 simulator steps, so this one backs away
    # from a vase at its nose (on the Goal1 tasks it can then dither by a vase beside the goal)
    "careful": Gains(slow_bearing=np.pi / 2, max_speed=0.6, back_off=0.3),
}


class PixelController:
    """
    A memoryless scripted controller on the robot's frames (see the module's docstring).

    :param robot: ``"Point"`` or ``"Car"``
    :param geometry: the camera's geometry at the frame size the controller sees
    :param avoid: steer around the hazards and vases seen (False: ignore them)
    :param gains: the controller's knobs
    """

    def __init__(self, robot: str, geometry: CameraGeometry, avoid: bool = False, gains: Gains = Gains()) -> None:
        if robot not in FULL_FORWARD:
            raise ValueError(f"PixelController drives {sorted(FULL_FORWARD)}, not {robot!r}")
        self.robot, self.geometry, self.avoid, self.gains = robot, geometry, avoid, gains

    def obstacles(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        (H, W, 3) uint8 frame -> (N, 2) floor points (m, robot frame) of the hazard pixels (those within
        ``ignore_within`` of the robot left out) and of the vases' bottoms, and (N,) the clearance (m) each asks for.
        """
        hazards = self.geometry.hazard_floor[hazard_mask(frame)]
        hazards = hazards[np.hypot(hazards[:, 0], hazards[:, 1]) >= self.gains.ignore_within]
        vases = vase_mask(frame)
        columns = np.flatnonzero(vases.any(axis=0))
        bottom_rows = vases.shape[0] - 1 - np.argmax(vases[::-1, columns], axis=0)
        vases = self.geometry.floor[bottom_rows, columns]
        points = np.concatenate([hazards, vases])
        clearances = np.repeat([self.gains.clearance, self.gains.vase_clearance], [len(hazards), len(vases)])
        seen = ~np.isnan(points[:, 0])
        return points[seen], clearances[seen]

    def free_distances(self, headings: np.ndarray, obstacles: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """
        (K,) headings (rad, positive left) -> (K,) m of straight path along each before it comes within an obstacle
        point's clearance (inf if it never does); ``obstacles`` as ``obstacles`` gives them.
        """
        points, clearances = obstacles
        directions = np.stack([np.cos(headings), np.sin(headings)], axis=1)
        along = points @ directions.T  # (N, K)
        across = np.abs(points @ np.stack([-directions[:, 1], directions[:, 0]], axis=1).T)
        reach = along - np.sqrt(np.maximum(clearances[:, None] ** 2 - across**2, 0.0))
        blocking = (across < clearances[:, None]) & (along > 0)
        return np.where(blocking, np.maximum(reach, 0.0), np.inf).min(axis=0, initial=np.inf)

    def steer(self, goal_bearing: float, obstacles: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
        """
        The heading in view nearest ``goal_bearing`` with ``stop_distance`` of free path, or the one with the most free
        path if none has that much, and that free path (rad, m).
        """
        half_fov = self.geometry.half_fov
        headings = np.append(goal_bearing, np.linspace(-half_fov, half_fov, self.gains.headings))
        free = self.free_distances(headings, obstacles)
        open_enough = free >= self.gains.stop_distance
        if open_enough.any():
            best = np.flatnonzero(open_enough)[np.argmin(np.abs(headings[open_enough] - goal_bearing))]
        else:
            best = int(np.argmax(free))
        return float(headings[best]), float(free[best])

    def command(self, frame: np.ndarray) -> tuple[float, float]:
        """(H, W, 3) uint8 frame -> (forward speed in [0, 1], turn in [-1, 1], positive to the left)."""
        goal = goal_mask(frame)
        if not in_view(goal):
            return 0.0, 1.0  # search: turn left in place
        heading = float(self.geometry.bearing[goal].mean())
        speed = self.gains.max_speed
        if self.avoid:
            obstacles = self.obstacles(frame)
            heading, free = self.steer(heading, obstacles)
            speed *= min(1.0, free / self.gains.stop_distance)
            points, clearances = obstacles
            vases = points[clearances == self.gains.vase_clearance]
            if len(vases) and np.hypot(vases[:, 0], vases[:, 1]).min() < self.gains.back_off:
                speed = -1.0  # a vase at its nose: back away (the way it came) rather than turn into it
        speed *= max(0.0, 1.0 - abs(heading) / self.gains.slow_bearing)
        return speed, float(np.clip(self.gains.turn * heading, -1.0, 1.0))

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 frame -> the env's action, float32 (2,)."""
        speed, turn = self.command(frame)
        if self.robot == "Point":  # forward force, turn rate
            action = [speed * FULL_FORWARD["Point"], turn]
        else:  # left and right wheels: the left wheel forward and the right one back turns the Car left
            action = np.clip([speed + turn, speed - turn], -1.0, 1.0) * FULL_FORWARD["Car"]
        return np.asarray(action, dtype=np.float32)


@dataclass(frozen=True)
class Episode:
    """One episode of ``T`` agent steps."""

    rewards: np.ndarray  # (T,) reward of each step
    costs: np.ndarray  # (T,) cost of each step
    goal_pixels: np.ndarray  # (T,) goal pixels in the frame acted on
    in_fov: np.ndarray  # (T,) bool: the goal's centre in the camera's field of view as the frame was taken


def run_episode(env: gym.Env, act, seed: int) -> Episode:
    """
    One episode from ``env.reset(seed=seed)`` with ``act``, a callable from the frame (H, W, 3) uint8 to the action
    (and with a ``reset()`` method if it has a state to clear).
    """
    if hasattr(act, "reset"):
        act.reset()
    frame, _ = env.reset(seed=seed)
    rewards, costs, goal_pixels, in_fov = [], [], [], []
    done = False
    while not done:
        goal_pixels.append(int(goal_mask(frame).sum()))
        in_fov.append(goal_in_fov(env))
        frame, reward, terminated, truncated, info = env.step(act(frame))
        rewards.append(float(reward))
        costs.append(float(info["cost"]))
        done = terminated or truncated
    return Episode(np.array(rewards), np.array(costs), np.array(goal_pixels), np.array(in_fov))


def make_ceiling_env(task: str, size: int) -> gym.Env:
    """``SafetyGym/<task>-v0`` with ``size`` x ``size`` frames and action repeat 4."""
    return gym.make(f"SafetyGym/{task}-v0", width=size, height=size, action_repeat=ACTION_REPEAT)


def controller_for(env: gym.Env, name: str = "seek", gains: Gains | None = None) -> PixelController:
    """
    The controller ``name`` of ``CONTROLLERS`` (its gains unless ``gains`` are given) for ``env``'s robot at its frame
    size; the env must have been reset.
    """
    avoid = name != "seek"
    return PixelController(env.unwrapped.robot_spec.name, CameraGeometry.of(env), avoid, gains or CONTROLLERS[name])


def evaluate(task: str, size: int, name: str, episodes: int, gains: Gains, first_seed: int = 0) -> list[Episode]:
    """``episodes`` episodes of controller ``name`` on ``task`` at ``size`` x ``size`` (reset seeds from ``first_seed``)."""
    env = make_ceiling_env(task, size)
    try:
        env.reset(seed=first_seed)
        controller = controller_for(env, name, gains)
        return [run_episode(env, controller, seed) for seed in range(first_seed, first_seed + episodes)]
    finally:
        env.close()


def table_row(task: str, size: int, name: str, episodes: list[Episode]) -> str:
    """A markdown row: reward mean ± sample std, cost mean, goals reached, goal in view and in the field of view."""
    rewards = np.array([episode.rewards.sum() for episode in episodes])
    costs = np.array([episode.costs.sum() for episode in episodes])
    goals = np.mean([(episode.rewards > 0.5).sum() for episode in episodes])
    pixels = np.concatenate([episode.goal_pixels for episode in episodes])
    in_view = float(np.mean(pixels >= min_pixels(size, size)))
    in_fov = float(np.concatenate([episode.in_fov for episode in episodes]).mean())
    std = rewards.std(ddof=1) if len(rewards) > 1 else float("nan")
    return (
        f"| {task} | {size}x{size} | {name} | {len(episodes)} | {rewards.mean():.2f} ± {std:.2f} | {costs.mean():.1f} | "
        f"{goals:.1f} | {in_view:.0%} | {in_fov:.0%} |"
    )


TABLE_HEADER = (
    "| task | frame | controller | episodes | reward (mean ± std) | cost (mean) | goals per episode | goal in view, share of "
    "steps | goal in the field of view |\n|---|---|---|---:|---:|---:|---:|---:|---:|"
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=["PointGoal1", "PointGoal2", "CarGoal1"])
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64], help="frame widths and heights in pixels")
    parser.add_argument("--controllers", nargs="+", choices=list(CONTROLLERS), default=list(CONTROLLERS))
    parser.add_argument("--episodes", type=int, default=10, help="episodes per task, size and controller")
    parser.add_argument("--first-seed", type=int, default=0, help="reset seed of the first episode (+1 each)")
    for name in Gains.__dataclass_fields__:
        kind = type(getattr(Gains(), name))
        parser.add_argument(f"--{name.replace('_', '-')}", type=kind, help=f"{name} of every controller (Gains)")
    parser.add_argument("--out", type=Path, help="write the table to this markdown file too")
    args = parser.parse_args()
    if args.episodes < 1 or min(args.sizes) < 1:
        parser.error("--episodes and --sizes must be positive")
    overrides = {name: value for name, value in vars(args).items() if name in Gains.__dataclass_fields__ and value is not None}
    gains = {name: replace(CONTROLLERS[name], **overrides) for name in args.controllers}
    command = "python benchmarks/ceiling.py " + shlex.join(sys.argv[1:])
    knobs = "; ".join(f"{name}: {value}" for name, value in gains.items())
    title = f"{cpu_model()}; action repeat {ACTION_REPEAT}, in view at {IN_VIEW_SHARE * 4096:g}/4096 of the frame\n\n{knobs}"
    print(f"{title}\n\n{TABLE_HEADER}", flush=True)
    rows = []
    for task in args.tasks:
        for size in args.sizes:
            for name in args.controllers:
                episodes = evaluate(task, size, name, args.episodes, gains[name], args.first_seed)
                rows.append(table_row(task, size, name, episodes))
                print(rows[-1], flush=True)
    if args.out:
        args.out.write_text(f"`{command}`\n\n{title}\n\n{TABLE_HEADER}\n" + "\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
