"""``burn_in``: the frames before each window are filtered first, without gradient, as the acting filter runs."""

import numpy as np
import pytest
import torch as th

from sb3_dsslac import DSSLAC
from sb3_dsslac.nn.latent import LatentModel, LatentStart, gaussian_kl
from sb3_dsslac.nn.recurrent_latent import RecurrentLatentModel
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import SMALL_POLICY, small_model

BATCH, BURN_IN, FEATURES, Z1, Z2, ACTIONS = 3, 5, 16, 4, 8, 2


@pytest.fixture(params=[LatentModel, RecurrentLatentModel], ids=["gaussian", "gru"])
def latent(request) -> LatentModel:
    th.manual_seed(0)
    return request.param((3, 32, 32), ACTIONS, feature_dim=FEATURES, z1_dim=Z1, z2_dim=Z2, hidden_units=(32, 32))


def burn_in_inputs() -> tuple[th.Tensor, th.Tensor, th.Tensor]:
    """Features and actions of 3 rows' burn-ins; row 0's episode began before it, row 1's at its frame 2, row 2's after."""
    features = th.randn(BATCH, BURN_IN, FEATURES)
    actions = th.rand(BATCH, BURN_IN, ACTIONS) * 2 - 1
    return features, actions, th.tensor([0, 2, BURN_IN])


def test_the_burn_in_is_the_acting_filter(latent: LatentModel) -> None:
    features, actions, start_index = burn_in_inputs()
    th.manual_seed(1)
    start = latent.burn_in(features, actions, start_index)
    th.manual_seed(1)
    z2, previous = th.zeros(BATCH, Z2), th.zeros(BATCH, ACTIONS)
    for index in range(BURN_IN):
        _, z2 = latent.filter_step(features[:, index], z2, previous, (start_index == index) | (index == 0))
        previous = actions[:, index]
    th.testing.assert_close(start.z2, z2)
    th.testing.assert_close(start.action, actions[:, -1])
    assert start.episode_start.tolist() == [False, False, True]
    assert not start.z2.requires_grad


def test_a_burn_in_from_a_stored_belief_continues_it(latent: LatentModel) -> None:
    """Rows whose episode began before the burn-in (index -1) continue the stored belief; the others restart."""
    features, actions, _ = burn_in_inputs()
    start_index = th.tensor([-1, 2, BURN_IN])
    stored = (th.rand(BATCH, Z2) * 2 - 1, th.rand(BATCH, ACTIONS) * 2 - 1)
    th.manual_seed(1)
    start = latent.burn_in(features, actions, start_index, stored)
    th.manual_seed(1)
    z2, previous = stored
    for index in range(BURN_IN):
        _, z2 = latent.filter_step(features[:, index], z2, previous, start_index == index)
        previous = actions[:, index]
    th.testing.assert_close(start.z2, z2)
    th.manual_seed(1)
    from_first_frame = latent.burn_in(features, actions, start_index)
    assert not th.allclose(from_first_frame.z2[0], start.z2[0])
    th.testing.assert_close(from_first_frame.z2[1], start.z2[1])  # row 2's burn-in is another episode's: no matter


def test_frames_before_an_episode_start_leave_the_start_as_it_is(latent: LatentModel) -> None:
    features, actions, start_index = burn_in_inputs()
    th.manual_seed(1)
    start = latent.burn_in(features, actions, start_index)
    features[1, :2], actions[1, :2] = 100 * th.randn(2, FEATURES), th.ones(2, ACTIONS)  # another episode's frames
    th.manual_seed(1)
    other = latent.burn_in(features, actions, start_index)
    th.testing.assert_close(other.z2[1], start.z2[1])


def window(frames: int = 4) -> tuple[th.Tensor, th.Tensor, tuple[th.Tensor, th.Tensor]]:
    features = th.randn(BATCH, frames, FEATURES)
    actions = th.rand(BATCH, frames - 1, ACTIONS) * 2 - 1
    return features, actions, (th.randn(frames, BATCH, Z1), th.randn(frames, BATCH, Z2))


def test_a_window_that_opens_its_episode_rolls_out_as_without_a_burn_in(latent: LatentModel) -> None:
    features, actions, noise = window()
    opens = LatentStart(th.randn(BATCH, Z2), th.rand(BATCH, ACTIONS), th.ones(BATCH, dtype=th.bool))
    expected = latent.posterior(features, actions, noise)
    for field, value in zip(latent.posterior(features, actions, noise, opens), expected, strict=True):
        th.testing.assert_close(field, value)


def test_after_a_burn_in_the_window_continues_the_filter(latent: LatentModel) -> None:
    features, actions, _ = window()
    start = LatentStart(th.rand(BATCH, Z2) * 2 - 1, th.rand(BATCH, ACTIONS) * 2 - 1, th.zeros(BATCH, dtype=th.bool))
    rollout = latent.posterior(features, actions, (th.zeros(4, BATCH, Z1), th.zeros(4, BATCH, Z2)), start)
    z2, previous = start.z2, start.action
    for index in range(4):
        z1, z2 = latent.filter_step(features[:, index], z2, previous, th.zeros(BATCH, dtype=th.bool), deterministic=True)
        th.testing.assert_close(rollout.z1[:, index], z1)
        th.testing.assert_close(rollout.z2[:, index], z2)
        previous = actions[:, index] if index < 3 else previous


def test_the_first_kl_term_is_to_the_prior_after_the_burn_in(latent: LatentModel) -> None:
    """Rows that continue take the transition prior at their first frame; rows that open their episode N(0, I)."""
    th.manual_seed(2)
    observations = th.rand(BATCH, 2, 3, 32, 32)
    actions = th.rand(BATCH, 1, ACTIONS) * 2 - 1
    zeros = th.zeros(BATCH, 1)
    start = LatentStart(th.rand(BATCH, Z2) * 2 - 1, th.rand(BATCH, ACTIONS) * 2 - 1, th.tensor([False, True, False]))
    noise = (th.randn(2, BATCH, Z1), th.randn(2, BATCH, Z2))
    _, terms, _ = latent.loss_and_filter(observations, actions, zeros, zeros, zeros, noise=noise, start=start)
    rollout = latent.posterior(latent.encode(observations), actions, noise, start)
    opens = start.episode_start.view(-1, 1)
    first_mean, first_std = latent.z1_prior(start.z2, start.action)
    first_mean, first_std = first_mean.masked_fill(opens, 0.0), first_std.masked_fill(opens, 1.0)
    next_mean, next_std = latent.z1_prior(rollout.z2[:, 0], actions[:, 0])
    kl = gaussian_kl(rollout.z1_mean[:, 0], rollout.z1_std[:, 0], first_mean, first_std).sum(-1)
    kl = kl + gaussian_kl(rollout.z1_mean[:, 1], rollout.z1_std[:, 1], next_mean, next_std).sum(-1)
    th.testing.assert_close(terms["kl"], kl.mean())


@pytest.mark.parametrize(("recurrence", "share_latent_batch"), [("gaussian", False), ("gru", False), ("gaussian", True)])
def test_a_model_with_a_burn_in_learns_saves_and_loads(recurrence: str, share_latent_batch: bool, tmp_path) -> None:
    """Every update's windows are burned in: the latent model's and the actor-critic's, shared or not."""
    model = small_model(
        HazardPointEnv(obs_type="pixels"),
        burn_in=4,
        share_latent_batch=share_latent_batch,
        policy_kwargs={**SMALL_POLICY, "latent_recurrence": recurrence},
    )
    assert model.replay_buffer.burn_in == 4 and model.updates.step.config.burn_in == 4
    burned_in_rows: list[int] = []
    burn_in = model.policy.latent.burn_in
    model.policy.latent.burn_in = lambda features, *args: burned_in_rows.append(len(features)) or burn_in(features, *args)
    model.learn(80)
    assert model._n_updates > 0
    # 3 pre-training updates of 4 windows, then per burst of 2 updates: the latent batches (4) and the actor-critic
    # batches (8) of both, or the 8 shared windows of each
    per_burst = [8, 8] if share_latent_batch else [4, 4, 8, 8]
    assert sorted(burned_in_rows) == sorted([4] * 3 + per_burst * (model._n_updates // 2))
    assert all(th.isfinite(param).all() for param in model.policy.parameters())
    batch = model.replay_buffer.sample(2)
    assert batch.observations.shape[1] == 4 + 3 + 1 and batch.episode_start_index is not None
    model.save(tmp_path / "burn_in")
    loaded = DSSLAC.load(tmp_path / "burn_in")
    assert loaded.burn_in == 4 and loaded.updates.step.config.burn_in == 4


def test_stored_beliefs_are_the_acting_filters(tmp_path) -> None:
    """The buffer keeps the acting filter's z2 of each frame acted from; a model learns from them, saves and loads."""
    model = small_model(HazardPointEnv(obs_type="pixels"), burn_in=2, stored_beliefs=True)
    seen: list[th.Tensor] = []
    step = model.policy.belief_step

    def recording_step(*args, **kwargs):
        z, z2 = step(*args, **kwargs)
        seen.append(z2.clone())
        return z, z2

    model.policy.belief_step = recording_step  # type: ignore[method-assign]
    model.learn(80)
    del model.policy.belief_step
    buffer = model.replay_buffer
    assert buffer.stores_beliefs and model._n_updates > 0
    written = buffer.episode_ids[:, 0] >= 0
    last_frames = np.flatnonzero(written[:-1] & (buffer.episode_ids[1:, 0] != buffer.episode_ids[:-1, 0]))
    acted_from = np.setdiff1d(np.flatnonzero(written), [*last_frames, np.flatnonzero(written)[-1]])
    np.testing.assert_allclose(buffer.beliefs[acted_from, 0], th.cat(seen).numpy()[: len(acted_from)], rtol=1e-6)
    model.save(tmp_path / "stored")
    assert DSSLAC.load(tmp_path / "stored").stored_beliefs


def test_a_negative_burn_in_and_stored_beliefs_without_one_are_refused() -> None:
    with pytest.raises(ValueError, match="burn_in"):
        small_model(HazardPointEnv(), burn_in=-1)
    with pytest.raises(ValueError, match=r"stored_beliefs=True .* needs burn_in >= 1"):
        small_model(HazardPointEnv(), stored_beliefs=True)


def test_stored_beliefs_are_refreshed_after_the_pretraining_and_at_the_interval(tmp_path) -> None:
    """``belief_refresh_interval``: the buffer's beliefs are filtered again by the current model at the first burst
    (after the pre-training), then once the interval has passed; the schedule survives save and load."""
    model = small_model(HazardPointEnv(obs_type="pixels"), burn_in=2, stored_beliefs=True, belief_refresh_interval=25)
    buffer = model.replay_buffer
    refresh = buffer.refresh_beliefs
    refreshed_at: list[tuple[int, bool]] = []

    def recording_refresh(*args, **kwargs):
        refreshed_at.append((model.num_timesteps, model.latent_pretrained))
        return refresh(*args, **kwargs)

    buffer.refresh_beliefs = recording_refresh  # type: ignore[method-assign]
    model.learn(100)
    # bursts after steps 50, 60, ..., 100 (learning_starts 40, train_freq 10)
    assert refreshed_at == [(50, True), (80, True)]
    assert model.beliefs_refreshed_at == 80
    del buffer.refresh_beliefs
    stored = buffer.beliefs.copy()
    th.manual_seed(0)
    model._refresh_beliefs()
    written = buffer.episode_ids[:, 0] >= 0
    assert not np.allclose(stored[written], buffer.beliefs[written])  # the acting filter's, by an older model
    model.save(tmp_path / "refresh")
    loaded = DSSLAC.load(tmp_path / "refresh")
    assert loaded.belief_refresh_interval == 25 and loaded.beliefs_refreshed_at == 100


def test_a_refresh_without_stored_beliefs_is_refused() -> None:
    with pytest.raises(ValueError, match=r"belief_refresh_interval=10 .* needs stored_beliefs=True"):
        small_model(HazardPointEnv(), burn_in=2, belief_refresh_interval=10)
    with pytest.raises(ValueError, match="belief_refresh_interval"):
        small_model(HazardPointEnv(), burn_in=2, stored_beliefs=True, belief_refresh_interval=-1)
