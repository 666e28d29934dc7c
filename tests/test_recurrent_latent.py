"""``latent_recurrence="gru"``: z2 is a deterministic GRU state, the same in training rollouts, the filter and a reload."""

import numpy as np
import pytest
import torch as th

from sb3_dsslac import DSSLAC
from sb3_dsslac.nn.recurrent_latent import GRUTransition, RecurrentLatentModel
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import SMALL_POLICY, small_model

GRU_POLICY = {**SMALL_POLICY, "latent_recurrence": "gru"}


def small_latent() -> RecurrentLatentModel:
    th.manual_seed(0)
    return RecurrentLatentModel((3, 32, 32), 2, feature_dim=16, z1_dim=4, z2_dim=8, hidden_units=(32, 32))


def test_z2_draws_no_noise_and_stays_in_the_gru_range() -> None:
    latent = small_latent()
    features, actions = th.randn(3, 5, 16), th.rand(3, 4, 2) * 2 - 1
    z1_noise = th.randn(5, 3, 4)
    first = latent.posterior(features, actions, (z1_noise, th.randn(5, 3, 8)))
    second = latent.posterior(features, actions, (z1_noise, 100 * th.randn(5, 3, 8)))
    th.testing.assert_close(first.z2, second.z2)
    assert first.z2.abs().max() < 1.0
    assert not th.equal(first.z2[:, 1:], first.z2[:, :-1])


def test_the_transition_is_a_gru_step_of_z1_and_the_action() -> None:
    transition = GRUTransition(z1_dim=4, z2_dim=8, action_dim=2, input_units=16)
    z1, z2, action = th.randn(5, 4), th.rand(5, 8) * 2 - 1, th.rand(5, 2)
    z2_next, std = transition(z1, z2, action)
    th.testing.assert_close(z2_next, transition.cell(transition.inputs(th.cat([z1, action], dim=-1)), z2))
    assert th.equal(std, th.zeros_like(z2_next))


def test_the_transition_takes_any_leading_dims_as_rows() -> None:
    """(B, T, .) inputs, as the Gaussian transition takes them (latent overshooting, latent_scale.py), step each row."""
    transition = GRUTransition(z1_dim=4, z2_dim=8, action_dim=2, input_units=16)
    z1, z2, action = th.randn(3, 5, 4), th.rand(3, 5, 8) * 2 - 1, th.rand(3, 5, 2)
    z2_next, std = transition(z1, z2, action)
    rows, _ = transition(z1.flatten(0, 1), z2.flatten(0, 1), action.flatten(0, 1))
    assert z2_next.shape == std.shape == (3, 5, 8)
    th.testing.assert_close(z2_next, rows.view(3, 5, 8))


def test_the_acting_filter_follows_the_training_rollout() -> None:
    """The filter's means step by step are the rollout's with zero noise: the actor acts on the beliefs it learned on."""
    latent = small_latent()
    features, actions = th.randn(2, 6, 16), th.rand(2, 5, 2) * 2 - 1
    rollout = latent.posterior(features, actions, (th.zeros(6, 2, 4), th.zeros(6, 2, 8)))
    z2 = th.zeros(2, 8)
    for step in range(6):
        previous = actions[:, step - 1] if step else th.zeros(2, 2)
        start = th.full((2,), step == 0)
        z1, z2 = latent.filter_step(features[:, step], z2, previous, start, deterministic=True)
        th.testing.assert_close(z1, rollout.z1[:, step])
        th.testing.assert_close(z2, rollout.z2[:, step])


def test_a_gru_model_learns_saves_and_loads(tmp_path) -> None:
    model = small_model(HazardPointEnv(obs_type="pixels"), policy_kwargs=GRU_POLICY)
    model.learn(60)
    assert isinstance(model.policy.latent, RecurrentLatentModel)
    assert model.latent_pretrained and model._n_updates > 0
    assert all(th.isfinite(param).all() for param in model.policy.parameters())
    model.save(tmp_path / "gru")
    loaded = DSSLAC.load(tmp_path / "gru")
    assert isinstance(loaded.policy.latent, RecurrentLatentModel)
    observation = np.zeros((32, 32, 3), dtype=np.uint8)
    expected, _ = model.predict(observation, deterministic=True)
    action, _ = loaded.predict(observation, deterministic=True)
    np.testing.assert_allclose(action, expected, rtol=1e-6)


def test_an_unknown_recurrence_is_refused() -> None:
    with pytest.raises(ValueError, match="latent_recurrence"):
        small_model(HazardPointEnv(), policy_kwargs={**SMALL_POLICY, "latent_recurrence": "lstm"})
