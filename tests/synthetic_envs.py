"""Tiny Gymnasium envs with ``info["cost"]`` for fast algorithm tests."""

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces


class HazardPointEnv(gym.Env):
    """
    A point on a plane that is rewarded for approaching the origin and pays cost 1 per step inside a hazard disc.

    :param obs_type: "state" gives (4,) float32 (position, hazard centre); "pixels" gives (size, size, 3) uint8
        with the point drawn white and the hazard blue
    :param size: image side in pixels
    :param max_episode_steps: agent steps per episode (then ``truncated=True``)
    :param report_cost: put the cost into ``info["cost"]`` (False imitates an env without costs)
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 30}  # noqa: RUF012

    def __init__(
        self,
        obs_type: str = "state",
        size: int = 32,
        max_episode_steps: int = 30,
        report_cost: bool = True,
        render_mode: str | None = None,
    ):
        self.obs_type = obs_type
        self.size = size
        self.max_episode_steps = max_episode_steps
        self.report_cost = report_cost
        self.render_mode = render_mode
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        if obs_type == "pixels":
            self.observation_space = spaces.Box(0, 255, (size, size, 3), np.uint8)
        else:
            self.observation_space = spaces.Box(-np.inf, np.inf, (4,), np.float32)
        self.hazard = np.array([0.5, 0.0])
        self.hazard_radius = 0.4

    def _obs(self) -> np.ndarray:
        if self.obs_type == "state":
            return np.concatenate([self.position, self.hazard]).astype(np.float32)
        image = np.zeros((self.size, self.size, 3), np.uint8)
        scale = self.size / 4.0

        def pixel(point: np.ndarray) -> tuple[int, int]:
            col, row = np.clip(((point + 2.0) * scale).astype(int), 0, self.size - 1)
            return int(row), int(col)

        row, col = pixel(self.hazard)
        radius = max(1, int(self.hazard_radius * scale))
        image[max(row - radius, 0) : row + radius, max(col - radius, 0) : col + radius, 2] = 255
        row, col = pixel(self.position)
        image[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2] = 255
        return image

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.position = self.np_random.uniform(-1.5, 1.5, size=2)
        self.steps = 0
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        before = np.linalg.norm(self.position)
        self.position = np.clip(self.position + 0.2 * action, -2.0, 2.0)
        self.steps += 1
        reward = float(before - np.linalg.norm(self.position))
        cost = float(np.linalg.norm(self.position - self.hazard) < self.hazard_radius)
        info: dict[str, Any] = {"cost": cost} if self.report_cost else {}
        return self._obs(), reward, False, self.steps >= self.max_episode_steps, info

    def render(self) -> np.ndarray:
        return self._obs() if self.obs_type == "pixels" else np.zeros((self.size, self.size, 3), np.uint8)
