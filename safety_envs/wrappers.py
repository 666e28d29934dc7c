"""Wrappers: action repeat for single-step envs, and the episode cost for SB3's episode logging."""

from typing import Any

import gymnasium as gym
import numpy as np

COST_KEYS = (
    "cost",
    "cost_hazards",
    "cost_vases",
    "cost_vases_contact",
    "cost_vases_velocity",
    "cost_pillars",
    "cost_buttons",
    "cost_gremlins",
)


class ActionRepeat(gym.Wrapper):
    """Repeat each action ``repeat`` times, summing the reward and the ``info`` costs; stops early at episode end.

    ``goal_met`` is True if any repeated step met the goal; the other info keys come from the last step.
    Prefer ``SafetyGymEnv(action_repeat=k)``, which renders once per agent step instead of once per repeat.

    :param env: an env whose ``info`` carries ``cost`` (e.g. ``SafetyGymEnv(action_repeat=1)``)
    :param repeat: number of env steps per agent step
    """

    def __init__(self, env: gym.Env, repeat: int = 2) -> None:
        if int(repeat) != repeat or repeat < 1:
            raise ValueError(f"repeat must be a positive integer, got {repeat!r}")
        super().__init__(env)
        self.repeat = int(repeat)
        if env.metadata.get("render_fps"):  # one frame per step of this wrapper: the wrapped env's rate / repeat
            self.metadata = {**env.metadata, "render_fps": env.metadata["render_fps"] / self.repeat}

    def step(self, action: np.ndarray):
        total_reward = 0.0
        sums = dict.fromkeys(COST_KEYS, 0.0)
        goal_met = False
        for _ in range(self.repeat):
            obs, reward, terminated, truncated, info = self.env.step(action)
            total_reward += float(reward)
            for key in COST_KEYS:
                sums[key] += float(info.get(key, 0.0))
            goal_met = goal_met or bool(info.get("goal_met", False))
            if terminated or truncated:
                break
        info = {**info, **{key: value for key, value in sums.items() if key in info}, "goal_met": goal_met}
        return obs, total_reward, terminated, truncated, info


class CostMonitor(gym.Wrapper):
    """Sum ``info["cost"]`` over the episode and report it at the episode's last step.

    The total goes to ``info["episode_cost"]`` and, when SB3's ``Monitor`` has put ``info["episode"]``
    (``r``, ``l``, ``t``) there, to ``info["episode"]["c"]`` as well. Wrap *outside* the Monitor:
    ``CostMonitor(Monitor(env))``, which is what ``make_vec_env(..., wrapper_class=CostMonitor)`` builds.
    (Inside it, ``Monitor`` would overwrite ``info["episode"]``; then pass
    ``Monitor(CostMonitor(env), info_keywords=("episode_cost",))``.)

    :param env: an env whose ``info`` carries ``cost``
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.episode_cost = 0.0

    def reset(self, **kwargs: Any):
        self.episode_cost = 0.0
        return self.env.reset(**kwargs)

    def step(self, action: np.ndarray):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if "cost" not in info:
            raise KeyError(f"CostMonitor needs info['cost'], which {self.env} does not provide")
        self.episode_cost += float(info["cost"])
        if terminated or truncated:
            info["episode_cost"] = self.episode_cost
            if isinstance(info.get("episode"), dict):
                info["episode"]["c"] = self.episode_cost
        return obs, reward, terminated, truncated, info
