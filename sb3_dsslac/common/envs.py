"""Env factories of the command line and the tuner: ``gym.make`` with the Safety-Gym tasks, training and evaluation envs."""

from functools import partial
from typing import Any

import gymnasium as gym
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv, VecTransposeImage


def make_env(
    env_id: str, obs_type: str | None = None, render_mode: str | None = None, env_kwargs: dict[str, Any] | None = None
) -> gym.Env:
    """
    ``gym.make`` with the Safety-Gym tasks registered and a clear error for an unknown id.

    :param env_id: a registered id (``SafetyGym/PointGoal1-v0``), or ``module:EnvId`` to import the module that registers it
    :param obs_type: passed to the env when given ("pixels" or "state" for the Safety-Gym tasks)
    :param render_mode: passed to the env when given ("rgb_array" for videos)
    :param env_kwargs: other keywords of the env
    """
    import safety_envs  # registers SafetyGym/*

    kwargs = dict(env_kwargs or {})
    if obs_type is not None:
        kwargs["obs_type"] = obs_type
    if render_mode is not None:
        kwargs["render_mode"] = render_mode
    try:
        return gym.make(env_id, **kwargs)
    except (gym.error.Error, ModuleNotFoundError) as error:
        raise ValueError(
            f"Cannot make env {env_id!r}: {str(error).rstrip('.')}. Safety-Gym tasks: {', '.join(safety_envs.env_ids())}. "
            "For your own env, register it with gymnasium.register and pass its id, or 'my_module:MyEnv-v0' "
            "so that my_module (which registers it) is imported first."
        ) from error


def make_train_env(
    env_id: str, n_envs: int = 1, obs_type: str | None = None, env_kwargs: dict[str, Any] | None = None
) -> gym.Env | VecEnv:
    """The training env: one env in this process, or ``n_envs`` envs in their own processes (see ``make_env``)."""
    if n_envs == 1:
        return make_env(env_id, obs_type, env_kwargs=env_kwargs)
    return SubprocVecEnv([partial(make_env, env_id, obs_type, env_kwargs=env_kwargs)] * n_envs)


def make_eval_env(env_id: str, seed: int, obs_type: str | None = None, env_kwargs: dict[str, Any] | None = None) -> VecEnv:
    """A separate, seeded, Monitor-wrapped evaluation VecEnv (channel-first images, as the training env)."""
    vec_env: VecEnv = DummyVecEnv([lambda: Monitor(make_env(env_id, obs_type, env_kwargs=env_kwargs))])
    if is_image_space(vec_env.observation_space) and not is_image_space_channels_first(vec_env.observation_space):  # type: ignore[arg-type]
        vec_env = VecTransposeImage(vec_env)
    vec_env.seed(seed)
    return vec_env
