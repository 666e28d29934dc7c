"""Beyond the thesis: CVaR safety term, multiplier rules and the Safe SLAC mean cost critic."""

import numpy as np
import pytest
import torch as th
from sb3_contrib.common.utils import quantile_huber_loss

from sb3_dsslac import DSSLAC
from sb3_dsslac.common.lagrange import pid_lagrange_step
from sb3_dsslac.nn.critics import IQNCostCritic, sample_taus
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import small_model


def test_risk_level_one_draws_the_risk_neutral_taus() -> None:
    th.manual_seed(3)
    neutral = th.rand(4, 8)
    th.manual_seed(3)
    np.testing.assert_array_equal(sample_taus(4, 8, "cpu", risk_level=1.0).numpy(), neutral.numpy())
    th.manual_seed(3)
    np.testing.assert_allclose(sample_taus(4, 8, "cpu", risk_level=0.25).numpy(), 0.75 + 0.25 * neutral.numpy(), rtol=1e-6)


def test_cvar_is_at_least_the_mean_on_a_trained_critic() -> None:
    th.manual_seed(0)
    critic = IQNCostCritic(z_dim=3, action_dim=1, n_cosines=16, hidden_dim=64)
    optimizer = th.optim.Adam(critic.parameters(), lr=3e-3)
    z, actions = th.ones(64, 3), th.ones(64, 1)  # IQN multiplies [z, a] by the tau embedding: 0 would erase tau
    for _ in range(400):  # fit the cost-return distribution Exponential(mean 2)
        taus = sample_taus(64, 16, "cpu")
        targets = th.distributions.Exponential(0.5).sample((64, 16))
        loss = quantile_huber_loss(critic(z, actions, taus), targets, cum_prob=taus.unsqueeze(-1))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with th.no_grad():
        mean = critic(z[:1], actions[:1], th.linspace(0.005, 0.995, 100)[None]).mean()
        cvar = critic(z[:1], actions[:1], th.linspace(0.505, 0.995, 50)[None]).mean()
    assert mean == pytest.approx(2.0, rel=0.25)
    assert cvar > mean + 0.5  # the upper half of Exponential(mean 2) averages 2 (1 + ln 2) = 3.39


def test_pid_multiplier_moves_the_right_way_and_never_goes_negative() -> None:
    gains = (0.05, 0.005, 0.02)
    multiplier, state = pid_lagrange_step([0.0, 0.0], 75.0, 25.0, *gains)
    assert multiplier > 0.0
    higher, state = pid_lagrange_step(state, 75.0, 25.0, *gains)
    assert higher > 0.0 and state[0] > 0.0
    values = []
    for _ in range(200):
        value, state = pid_lagrange_step(state, 0.0, 25.0, *gains)
        values.append(value)
    assert min(values) >= 0.0 and values[-1] == 0.0 and state[0] == 0.0
    assert values[0] < higher


@pytest.mark.parametrize(
    "variant",
    [
        dict(lagrange="episode"),
        dict(lagrange="pid"),
        dict(lagrange="critic"),
        dict(cvar_risk_level=0.5),
        dict(cost_critic="mean"),
    ],
)
def test_variant_trains_saves_and_loads(variant: dict, tmp_path) -> None:
    unsafe = HazardPointEnv(max_episode_steps=10)
    unsafe.hazard_radius = 10.0  # every step costs 1: a budget of 2 per episode is always exceeded
    model = small_model(unsafe, cost_limit=2.0, lagrange_learning_rate=1e-2, learning_starts=20, **variant)
    start = model.lagrange_multiplier
    model.learn(60)
    if variant.get("lagrange") in ("episode", "pid"):
        assert model.lagrange_multiplier > start
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip", env=unsafe)
    assert loaded.lagrange == model.lagrange and loaded.cost_critic == model.cost_critic
    assert loaded.lagrange_multiplier == pytest.approx(model.lagrange_multiplier)
    assert loaded.pid_state == model.pid_state
    obs = unsafe.reset(seed=0)[0]
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])


def test_critic_rule_moves_the_multiplier_during_training() -> None:
    model = small_model(HazardPointEnv(), lagrange="critic", lagrange_learning_rate=1e-2)
    start = model.lagrange_multiplier
    model.learn(60)
    assert model.lagrange_multiplier != start


def test_mean_cost_critic_starts_at_the_discounted_budget() -> None:
    model = small_model(HazardPointEnv(max_episode_steps=500), cost_critic="mean")
    assert model.discounted_cost_budget == pytest.approx(9.184, abs=1e-3)
    z = th.zeros(2, model.policy.latent.z_dim)
    with th.no_grad():
        value = model.policy.cost_critic(z, th.zeros(2, 2), th.rand(2, 5))
    assert value.shape == (2, 5)
    np.testing.assert_allclose(value.numpy(), 9.184, atol=1e-3)


def test_unknown_rules_list_the_valid_ones() -> None:
    with pytest.raises(ValueError, match="'sgd' or 'episode' or 'pid' or 'critic'"):
        small_model(HazardPointEnv(), lagrange="adam")
    with pytest.raises(ValueError, match="'iqn'"):
        small_model(HazardPointEnv(), cost_critic="twin")
    with pytest.raises(ValueError, match=r"\(0, 1\]"):
        small_model(HazardPointEnv(), cvar_risk_level=0.0)
