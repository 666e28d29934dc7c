"""
Any Gymnasium env with a Box action space works, as long as every step reports its cost in ``info["cost"]``.

Here Gymnasium's Pendulum pays a cost of 1 for every step spun faster than 4 rad/s; the budget is 25 per episode
(200 steps). Register the env, then use its id with the library (or ``python -m sb3_dsslac train --env
my_module:PendulumWithCost-v0`` from a module that registers it).

    python examples/custom_env_with_cost.py
"""

from typing import Any

import gymnasium as gym
import numpy as np

from sb3_dsslac.app.plotting import report
from sb3_dsslac.app.runs import TrainConfig, train


class SpinCost(gym.Wrapper):
    """Adds ``info["cost"]``: 1.0 when the pendulum spins faster than ``max_speed`` rad/s, else 0.0."""

    def __init__(self, env: gym.Env, max_speed: float = 4.0):
        super().__init__(env)
        self.max_speed = max_speed

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        observation, reward, terminated, truncated, info = self.env.step(action)
        info["cost"] = float(abs(observation[2]) > self.max_speed)  # observation: cos, sin, angular velocity
        return observation, float(reward), terminated, truncated, info


gym.register("PendulumWithCost-v0", entry_point=lambda **kwargs: SpinCost(gym.make("Pendulum-v1", **kwargs)))

run_dir = train(
    TrainConfig(
        env="PendulumWithCost-v0",
        preset="cpu",
        sim_steps=3_000,
        eval_every=1_000,
        eval_episodes=2,
        checkpoint_every=1_500,
        hyperparams={"cost_limit": 25.0, "learning_starts": 500},
        threads=1,
        verbose=0,
    ),
    out=None,  # runs/PendulumWithCost-v0_0_<timestamp>
)
print(report([run_dir], run_dir))
