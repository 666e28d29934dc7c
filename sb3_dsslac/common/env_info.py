"""What DS-SLAC reads from an env: its per-step cost, action repeat, episode length and whether its observations are finite."""

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env import VecEnv


def cost_from_info(info: dict[str, Any]) -> float:
    """
    Read the cost of one agent step from an env's ``info``.

    :param info: the info dict of one env step
    :return: ``info["cost"]`` as a float
    :raises ValueError: when the env does not report a cost
    """
    try:
        return float(info["cost"])
    except KeyError:
        raise ValueError(
            "The env did not report a cost: DS-SLAC needs the per-step cost in info['cost'] "
            "(the safety_envs tasks report it; wrap other envs so that step() adds it)."
        ) from None


def check_observations_finite(observations: np.ndarray, source: Callable[[int], str]) -> None:
    """
    Raise a ValueError when an observation holds NaN or inf, before the latent filter turns it into NaN actions.

    :param observations: (n_envs, *obs_shape), one row per env (integer frames cannot hold NaN: not looked at)
    :param source: row -> the words that name where that observation came from ("env 0 (<TimeLimit<...>>) at timestep
        120"), called for the first bad row only
    """
    if not np.issubdtype(observations.dtype, np.floating):
        return
    bad = ~np.isfinite(observations)
    if not bad.any():
        return
    row = int(np.flatnonzero(bad.reshape(len(observations), -1).any(axis=1))[0])
    where = [tuple(int(i) for i in index) for index in np.argwhere(bad[row])[:5]]
    observation = np.array2string(observations[row], threshold=32, edgeitems=4)
    raise ValueError(
        f"{source(row)} gave an observation with NaN or inf in {int(bad[row].sum())} of its {bad[row].size} values "
        f"(first at {where}): {observation}. DS-SLAC's latent filter cannot take it: fix the env, or wrap it so that "
        "its observations are finite (replace a missing sensor reading, clip an unbounded one)."
    )


def _attribute(env: gym.Env | VecEnv, name: str) -> Any:
    """``name`` of the (first) env, looked up through its wrappers; AttributeError when absent."""
    if not isinstance(env, VecEnv):
        return env.get_wrapper_attr(name)
    # Ask first: a SubprocVecEnv worker asked for a missing attribute dies instead of raising here
    if not env.has_attr(name):
        raise AttributeError(f"The envs have no attribute {name!r}")
    return env.get_attr(name)[0]


def action_repeat_of(env: gym.Env | VecEnv) -> int:
    """Simulator steps per agent step of ``env``: its ``action_repeat`` attribute, else 1."""
    try:
        return int(_attribute(env, "action_repeat"))
    except (AttributeError, TypeError):
        return 1


def episode_length_of(env: gym.Env | VecEnv, required: bool = False) -> int | None:
    """
    Agent steps per episode of ``env``: its registered time limit, else a ``TimeLimit`` wrapper's, else the env's own
    ``max_episode_steps`` (safety_envs: 1000 simulator steps / action repeat); None when it has none.

    :param required: raise a ValueError naming the fix instead of returning None
    """
    spec = _attribute(env, "spec")
    if spec is not None and spec.max_episode_steps is not None:
        return int(spec.max_episode_steps)
    for name in ("_max_episode_steps", "max_episode_steps"):
        try:
            return int(_attribute(env, name))
        except (AttributeError, TypeError):
            continue
    if required:
        raise ValueError(
            "Cannot tell how many agent steps an episode of this env has (it has no time limit): "
            "pass episode_length=<agent steps per episode> so that cost_limit can be spread over the steps."
        )
    return None
