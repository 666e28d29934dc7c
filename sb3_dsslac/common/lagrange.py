"""The Lagrange multiplier of the cost constraint, its budgets, and the callback that updates it on-policy."""

import math

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.type_aliases import MaybeCallback
from torch.nn import functional as F

from sb3_dsslac.common.env_info import cost_from_info


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


def sgd_lagrange_step_on_device(
    raw: th.Tensor, cost: th.Tensor, budget_per_step: float, learning_rate: float | th.Tensor
) -> th.Tensor:
    """
    ``sgd_lagrange_step`` in tensor ops (no host read), for the rule that steps inside a burst of updates.

    :param raw: the raw parameter (0-d tensor)
    :param cost: the cost estimate (0-d tensor)
    :param learning_rate: SGD step size (a float, or a 0-d tensor on the device)
    :return: the new raw parameter (0-d tensor)
    """
    return raw + learning_rate * th.sigmoid(raw) / F.softplus(raw) * (cost - budget_per_step)


def pid_lagrange_step(
    state: list[float | None], episode_cost: float, cost_limit: float, kp: float, ki: float, kd: float, cost_ema: float = 0.0
) -> tuple[float, list[float | None]]:
    """
    One update of the PID Lagrangian (Stooke, Achiam and Abbeel, 2020) from a finished episode's cost.

    The proportional and derivative terms act on a moving average of the episode costs,
    ``smoothed = cost_ema * smoothed + (1 - cost_ema) * episode_cost``, as PID Lagrangian implementations smooth them
    (Stooke et al.'s and OmniSafe's ``pid_delta_p_ema_alpha`` and ``pid_delta_d_ema_alpha``): the derivative of single
    noisy episode costs, clipped at 0, is positive on average even at a steady cost, and pushes the multiplier up. The
    integral sums the raw errors.

    :param state: ``[integral, smoothed episode cost]``, the latter None before the first episode (which starts it)
    :param episode_cost: total cost of the finished episode
    :param cost_limit: the episode budget
    :param kp: proportional gain (per unit of episode cost over the budget)
    :param ki: integral gain
    :param kd: derivative gain (only rising costs push the multiplier up)
    :param cost_ema: weight of the past in the moving average, in [0, 1); 0 uses each episode's own cost
    :return: the multiplier (>= 0) and the new state
    """
    integral, previous = state
    assert integral is not None
    if previous is None:
        previous = episode_cost
    integral = max(0.0, integral + ki * (episode_cost - cost_limit))
    smoothed = cost_ema * previous + (1.0 - cost_ema) * episode_cost
    derivative = max(0.0, smoothed - previous)
    return max(0.0, kp * (smoothed - cost_limit) + integral + kd * derivative), [integral, smoothed]


# Multipliers below this are stored as this (softplus never reaches 0)
MIN_MULTIPLIER = 1e-8

LAGRANGE_RULES = ("sgd", "episode", "pid", "critic")


class LagrangeCallback(BaseCallback):
    """
    Update the model's Lagrange multiplier on-policy from the real costs of its training envs.

    Only once the random warm-up is over (as in the reference), following ``model.lagrange``:

    - ``"sgd"`` (default, the thesis rule): after every agent step, each env's ``info["cost"]`` moves the multiplier
      up when it exceeds the per-step budget (``episode_cost_target / episode_length``) and down otherwise;
    - ``"episode"``: the same SGD rule once per finished episode, from its total cost against ``episode_cost_target``;
    - ``"pid"``: a PID Lagrangian on each finished episode's cost against ``episode_cost_target`` (smoothed by
      ``model.pid_cost_ema``);
    - ``"critic"``: nothing here; ``DSSLAC.train`` drives the multiplier from the cost critic against
      ``model.critic_cost_budget``.

    The SGD rules step with ``model.current_lagrange_learning_rate`` (the step size after any ``lr_decay_milestone``).
    ``DSSLAC.learn`` attaches this callback itself.
    """

    def _on_step(self) -> bool:
        model = self.model
        if model.num_timesteps <= model.learning_starts or model.lagrange == "critic":
            return True
        costs = np.array([cost_from_info(info) for info in self.locals["infos"]])
        # The model adds this step's cost to its running episode costs after the callbacks
        finished = [float(model._episode_costs[i] + costs[i]) for i in np.flatnonzero(self.locals["dones"])]

        raw = float(model.lagrange_raw.item())
        if model.lagrange == "sgd":
            for cost in costs:
                raw = sgd_lagrange_step(raw, float(cost), model.cost_budget_per_step, model.current_lagrange_learning_rate)
        elif model.lagrange == "episode":
            for cost in finished:
                raw = sgd_lagrange_step(raw, cost, model.episode_cost_target, model.current_lagrange_learning_rate)
        else:
            for cost in finished:
                multiplier, model.pid_state = pid_lagrange_step(
                    model.pid_state, cost, model.episode_cost_target, *model.pid_gains, model.pid_cost_ema
                )
                raw = inverse_softplus(max(multiplier, MIN_MULTIPLIER))
        if not np.isfinite(raw):
            raise RuntimeError(f"The Lagrange multiplier's {model.lagrange!r} update produced a non-finite value")
        with th.no_grad():
            model.lagrange_raw.fill_(raw)
        return True


def _has_lagrange_callback(callback: MaybeCallback) -> bool:
    if isinstance(callback, LagrangeCallback):
        return True
    if isinstance(callback, CallbackList):
        return any(_has_lagrange_callback(child) for child in callback.callbacks)
    if isinstance(callback, list):
        return any(_has_lagrange_callback(child) for child in callback)
    return False


def with_lagrange_callback(callback: MaybeCallback) -> MaybeCallback:
    """``callback`` with a ``LagrangeCallback`` in front, unless it holds one (also inside a list or a ``CallbackList``)."""
    if _has_lagrange_callback(callback):
        return callback
    if callback is None:
        return [LagrangeCallback()]
    if isinstance(callback, list):
        return [LagrangeCallback(), *callback]
    return [LagrangeCallback(), callback]


class CostBudget:
    """
    The cost budget in the units of each multiplier rule, the multiplier and its step size now: properties of
    ``DSSLAC``, which mixes this class in, from its hyperparameters of the same names.
    """

    cost_limit: float
    cost_target: float | None
    episode_length: int | None
    cost_gamma: float
    lagrange_learning_rate: float
    lagrange_raw: th.Tensor
    lr_decay_milestone: int | None
    lr_decay_factor: float
    num_timesteps: int

    @property
    def episode_cost_target(self) -> float:
        """The episode cost the multiplier aims at: ``cost_target``, else ``cost_limit``."""
        return self.cost_limit if self.cost_target is None else self.cost_target

    @property
    def cost_budget_per_step(self) -> float:
        """The multiplier's episode target spread over the agent steps of an episode (25 / 500 = 0.05 for the thesis)."""
        assert self.episode_length is not None
        return self.episode_cost_target / self.episode_length

    @property
    def discounted_cost_budget(self) -> float:
        """The per-step budget discounted over an episode with ``cost_gamma``: 9.184 for the thesis setting."""
        assert self.episode_length is not None
        return self.cost_budget_per_step * (1.0 - self.cost_gamma**self.episode_length) / (1.0 - self.cost_gamma)

    @property
    def critic_cost_budget(self) -> float:
        """
        The budget of the "critic" rule: ``cost_budget_per_step / (1 - cost_gamma)``, 10.0 for the thesis setting, the
        value the critic's (infinite-horizon, time-limit-bootstrapped) estimate converges to at exactly the per-step
        budget. Against ``discounted_cost_budget`` (9.184, discounting stopped at the episode end) the rule would hold
        the episode cost to about 23 instead of 25.
        """
        return self.cost_budget_per_step / (1.0 - self.cost_gamma)

    @property
    def lagrange_multiplier(self) -> float:
        """The current Lagrange multiplier (softplus of its raw parameter, a host tensor: reading it waits for no device)."""
        return softplus(float(self.lagrange_raw.numpy()))

    @property
    def lr_decay_multiplier(self) -> float:
        """The factor on every step size now: ``lr_decay_factor`` from agent step ``lr_decay_milestone`` on, else 1."""
        if self.lr_decay_milestone is not None and self.num_timesteps >= self.lr_decay_milestone:
            return self.lr_decay_factor
        return 1.0

    @property
    def current_lagrange_learning_rate(self) -> float:
        """The multiplier's SGD step size now: ``lagrange_learning_rate`` times ``lr_decay_multiplier``."""
        return self.lagrange_learning_rate * self.lr_decay_multiplier
