"""The on-policy Lagrange multiplier rule."""

import math

import pytest

from sb3_dsslac.common.env_info import cost_from_info
from sb3_dsslac.common.lagrange import inverse_softplus, pid_lagrange_step, sgd_lagrange_step, softplus


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


def test_pid_step_by_hand() -> None:
    # Smoothed 0.5 * 40 + 0.5 * 20 = 30: P 0.1 * (30 - 25), I 0.01 * (20 - 25) floored at 0 from 1.0, D 0.2 * (30 - 40)^+
    multiplier, state = pid_lagrange_step([1.0, 40.0], 20.0, 25.0, kp=0.1, ki=0.01, kd=0.2, cost_ema=0.5)
    assert state == [pytest.approx(0.95), pytest.approx(30.0)]
    assert multiplier == pytest.approx(0.1 * 5 + 0.95)
    # The first episode starts the average: no derivative kick from a made-up previous cost of 0
    multiplier, state = pid_lagrange_step([0.0, None], 60.0, 25.0, kp=0.0, ki=0.0, kd=1.0, cost_ema=0.9)
    assert multiplier == 0.0 and state == [0.0, 60.0]


def test_pid_smoothing_removes_the_upward_bias_of_noisy_costs() -> None:
    # A steady mean cost at the budget, alternating 0 and 50: only the derivative term acts
    def mean_multiplier(cost_ema: float) -> float:
        state: list[float | None] = [0.0, None]
        multipliers = []
        for cost in [0.0, 50.0] * 100:
            multiplier, state = pid_lagrange_step(state, cost, 25.0, kp=0.0, ki=0.0, kd=1.0, cost_ema=cost_ema)
            multipliers.append(multiplier)
        return sum(multipliers[20:]) / len(multipliers[20:])

    assert mean_multiplier(0.0) == pytest.approx(25.0)
    assert mean_multiplier(0.9) < 0.15 * mean_multiplier(0.0)
