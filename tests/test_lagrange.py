"""The on-policy Lagrange multiplier rule."""

import math

import pytest

from sb3_dsslac.env_info import cost_from_info
from sb3_dsslac.lagrange import inverse_softplus, sgd_lagrange_step, softplus


@pytest.mark.parametrize("value", [1e-3, 0.02, 1.0, 30.0])
def test_inverse_softplus_round_trip(value: float) -> None:
    assert softplus(inverse_softplus(value)) == pytest.approx(value, rel=1e-9)


def test_inverse_softplus_rejects_non_positive() -> None:
    with pytest.raises(ValueError, match="above 0"):
        inverse_softplus(0.0)


def test_multiplier_rises_over_budget_and_falls_under() -> None:
    raw = inverse_softplus(0.02)
    assert softplus(sgd_lagrange_step(raw, cost=2.0, budget_per_step=0.05, learning_rate=2e-4)) > 0.02
    assert softplus(sgd_lagrange_step(raw, cost=0.0, budget_per_step=0.05, learning_rate=2e-4)) < 0.02
    assert sgd_lagrange_step(raw, cost=0.05, budget_per_step=0.05, learning_rate=2e-4) == raw


def test_small_multiplier_update_is_multiplicative() -> None:
    # For a small multiplier, one episode moves log(lambda) by about lr * (episode cost - budget)
    raw = inverse_softplus(0.02)
    costs = [1.0] * 100 + [0.0] * 400  # 100 cost units in a 500-step episode against a budget of 25
    for cost in costs:
        raw = sgd_lagrange_step(raw, cost, budget_per_step=25 / 500, learning_rate=2e-4)
    assert math.log(softplus(raw) / 0.02) == pytest.approx(2e-4 * (100 - 25), rel=0.05)


def test_multiplier_never_negative() -> None:
    raw = inverse_softplus(1e-4)
    for _ in range(10_000):
        raw = sgd_lagrange_step(raw, cost=0.0, budget_per_step=1.0, learning_rate=1e-2)
    assert softplus(raw) > 0.0


def test_cost_from_info_names_the_fix() -> None:
    assert cost_from_info({"cost": 2}) == 2.0
    with pytest.raises(ValueError, match=r"info\['cost'\]"):
        cost_from_info({})
