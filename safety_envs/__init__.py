"""Safety-Gym Goal, Button and Push tasks (Point, Car, Doggo; levels 0-2) rebuilt on current MuJoCo and Gymnasium.

Importing the package registers ``SafetyGym/{Robot}{Task}{level}-v0`` with Gymnasium, so
``gym.make("SafetyGym/PointGoal1-v0")`` gives 64x64x3 uint8 first-person pixels and ``info["cost"]``.

Headless rendering: on Linux without a ``DISPLAY``, ``MUJOCO_GL`` defaults to ``egl`` (set before mujoco is
imported; an explicit ``MUJOCO_GL`` is kept) and ``LP_NUM_THREADS`` to ``0``, which makes Mesa's CPU rasteriser
(llvmpipe) draw small images in the calling thread, ~20% faster than its default thread pool at 64x64. Import
``safety_envs`` before anything that imports mujoco, or set ``MUJOCO_GL=egl`` (or ``osmesa``) yourself.
"""

import os
import sys

if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("LP_NUM_THREADS", "0")

import gymnasium

from safety_envs.engine import SafetyGymEnv
from safety_envs.tasks import ROBOTS, TASKS, env_ids
from safety_envs.wrappers import ActionRepeat, CostMonitor

__all__ = ["ROBOTS", "TASKS", "ActionRepeat", "CostMonitor", "SafetyGymEnv", "env_ids", "make_env"]


def make_env(robot: str = "Point", task: str = "Goal", level: int = 1, **kwargs) -> SafetyGymEnv:
    """Build ``SafetyGymEnv(robot, task, level, **kwargs)`` directly, without Gymnasium's wrappers."""
    return SafetyGymEnv(robot=robot, task=task, level=level, **kwargs)


for _robot in ROBOTS:
    for _task in TASKS.values():
        _id = f"SafetyGym/{_robot}{_task.id_name}-v0"
        if _id not in gymnasium.registry:
            gymnasium.register(
                id=_id,
                entry_point="safety_envs.engine:SafetyGymEnv",
                kwargs={"robot": _robot, "task": _task.name, "level": _task.level},
            )
