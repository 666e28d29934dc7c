"""The Lagrange multiplier of the cost constraint and the callback that updates it on-policy."""

import math
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback


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


def softplus(x: float) -> float:
    """Numerically stable ``log(1 + exp(x))``."""
    return max(x, 0.0) + math.log1p(math.exp(-abs(x)))


def inverse_softplus(y: float) -> float:
    """The ``x`` with ``softplus(x) == y``, for ``y > 0``."""
    if y <= 0:
        raise ValueError(f"The Lagrange multiplier must start above 0, got {y}")
    return y + math.log(-math.expm1(-y))


def sgd_lagrange_step(raw: float, cost: float, budget_per_step: float, learning_rate: float) -> float:
    """
    One step of the rule behind the thesis numbers (Safe SLAC / DS-SLAC ``update_lag``).

    The loss ``(lambda / stopgrad(lambda)) * (budget_per_step - cost)`` is minimised by SGD on the raw
    parameter of ``lambda = softplus(raw)``. Its gradient with respect to ``raw`` is
    ``sigmoid(raw) / lambda * (budget_per_step - cost)``, so for a small multiplier the update is
    multiplicative: ``log(lambda) += learning_rate * (cost - budget_per_step)``.

    :param raw: the raw (pre-softplus) parameter
    :param cost: the cost of one agent step
    :param budget_per_step: the episode budget divided by the agent steps of an episode
    :param learning_rate: SGD step size
    :return: the new raw parameter
    """
    multiplier = softplus(raw)
    sigmoid = 1.0 / (1.0 + math.exp(-raw)) if raw >= 0 else math.exp(raw) / (1.0 + math.exp(raw))
    return raw + learning_rate * sigmoid / multiplier * (cost - budget_per_step)


class LagrangeCallback(BaseCallback):
    """
    Update the model's Lagrange multiplier on-policy from the real costs of its training envs.

    After every agent step, and only once the random warm-up is over (as in the reference), each training
    env's ``info["cost"]`` moves the multiplier up when it exceeds the per-step budget
    (``cost_limit / episode_length``) and down otherwise. ``DSSLAC.learn`` attaches this callback itself.
    """

    def _on_step(self) -> bool:
        model = self.model
        if model.num_timesteps <= model.learning_starts:
            return True
        raw = float(model.lagrange_raw.item())
        for info in self.locals["infos"]:
            raw = sgd_lagrange_step(raw, cost_from_info(info), model.cost_budget_per_step, model.lagrange_learning_rate)
        if not np.isfinite(raw):
            raise RuntimeError("The Lagrange multiplier update produced a non-finite value")
        with th.no_grad():
            model.lagrange_raw.fill_(raw)
        return True
