"""Latent overshooting (``latent_overshooting``): z1's KL to its prior rolled open-loop several steps, and the reward on
those rolls (``latent_reward_overshooting``)."""

import pytest
import torch as th
from stable_baselines3.common.logger import configure

from sb3_dsslac.nn.latent import LatentModel, gaussian_kl, gaussian_nll
from sb3_dsslac.nn.overshooting import overshooting_roll
from sb3_dsslac.nn.recurrent_latent import RecurrentLatentModel
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import SMALL_POLICY, small_model

BATCH, STEPS, Z1, Z2, ACTIONS = 3, 4, 4, 8, 2


@pytest.fixture(params=[LatentModel, RecurrentLatentModel], ids=["gaussian", "gru"])
def latent(request) -> LatentModel:
    th.manual_seed(0)
    return request.param((3, 32, 32), ACTIONS, feature_dim=16, z1_dim=Z1, z2_dim=Z2, hidden_units=(32, 32))


def rollout_inputs() -> tuple[th.Tensor, th.Tensor, th.Tensor, th.Tensor]:
    """A posterior's z2 (B, T+1, Z2), actions (B, T, A), z1's posterior means and stds (B, T+1, Z1)."""
    th.manual_seed(3)
    z2 = th.rand(BATCH, STEPS + 1, Z2, requires_grad=True)
    actions = th.rand(BATCH, STEPS, ACTIONS) * 2 - 1
    mean, std = th.randn(BATCH, STEPS + 1, Z1, requires_grad=True), th.rand(BATCH, STEPS + 1, Z1) + 0.5
    return z2, actions, mean, std


def reference_overshooting_kl(latent: LatentModel, z2, actions, mean, std, depth: int, stride: int = 1) -> th.Tensor:
    """Start by start and step by step, drawing the same noise tensors as ``overshooting_roll`` in the same order."""
    noise = []  # per rolled step: z1's (B, starts, Z1) and z2's (B * starts, Z2), indexed by start // stride
    for rolled in range(depth - 1):
        starts = len(range(0, STEPS - rolled, stride))
        noise.append((th.randn(BATCH, starts, Z1), th.randn(BATCH * starts, Z2).view(BATCH, starts, Z2)))
    per_depth = []
    for d in range(2, depth + 1):
        total = 0.0
        for row in range(BATCH):
            for start in range(0, STEPS - d + 1, stride):
                state = z2[row, start]
                for rolled in range(d - 1):
                    action = actions[row, start + rolled]
                    prior_mean, prior_std = latent.z1_prior(state, action)
                    z1 = prior_mean + prior_std * noise[rolled][0][row, start // stride]
                    z2_mean, z2_std = latent.z2_transition(z1[None], state[None], action[None])
                    state = (z2_mean + z2_std * noise[rolled][1][row, start // stride][None])[0]
                prior_mean, prior_std = latent.z1_prior(state, actions[row, start + d - 1])
                total = total + gaussian_kl(mean[row, start + d], std[row, start + d], prior_mean, prior_std).sum()
        per_depth.append(total / BATCH)
    return th.stack(per_depth).mean()


@pytest.mark.parametrize("depth, stride", [(2, 1), (4, 1), (3, 2), (4, 3)])
def test_overshooting_kl_is_the_kl_to_the_prior_rolled_open_loop(latent: LatentModel, depth: int, stride: int) -> None:
    z2, actions, mean, std = rollout_inputs()
    th.manual_seed(4)
    value, transitions = overshooting_roll(latent.z1_prior, latent.z2_transition, z2, actions, mean, std, depth, stride=stride)
    th.manual_seed(4)
    expected = reference_overshooting_kl(latent, z2, actions, mean, std, depth, stride)
    th.testing.assert_close(value, expected, rtol=1e-5, atol=1e-5)
    assert transitions == []  # asked for with z1 only


def reference_rolled_transitions(latent: LatentModel, z1, z2, actions, depth: int, stride: int = 1) -> list[th.Tensor]:
    """Start by start, the transitions [z_{t+d-1}, a_{t+d-1}, z_{t+d}] rolled from the posterior's z_t, same noise order."""
    noise = []  # per rolled step, the z1 and z2 draws of every start, indexed by start // stride
    for rolled in range(depth):
        starts = len(range(0, STEPS - rolled, stride))
        noise.append((th.randn(BATCH, starts, Z1), th.randn(BATCH, starts, Z2)))
    per_depth = []
    for d in range(1, depth + 1):
        rows = []
        for row in range(BATCH):
            starts = []
            for start in range(0, STEPS - d + 1, stride):
                z1_now, state = z1[row, start], z2[row, start]
                for rolled in range(d):
                    action = actions[row, start + rolled]
                    prior_mean, prior_std = latent.z1_prior(state[None], action[None])
                    z1_next = (prior_mean + prior_std * noise[rolled][0][row, start // stride])[0]
                    z2_mean, z2_std = latent.z2_transition(z1_next[None], state[None], action[None])
                    previous = th.cat([z1_now, state])
                    state = (z2_mean + z2_std * noise[rolled][1][row, start // stride])[0]
                    z1_now = z1_next
                starts.append(th.cat([previous, action, z1_now, state]))
            rows.append(th.stack(starts))
        per_depth.append(th.stack(rows))
    return per_depth


@pytest.mark.parametrize("stride", [1, 2])
def test_the_rolled_transitions_chain_open_loop_steps_from_the_posterior(latent: LatentModel, stride: int) -> None:
    z2, actions, mean, std = rollout_inputs()
    z1 = th.randn(BATCH, STEPS + 1, Z1)
    th.manual_seed(4)
    plain, _ = overshooting_roll(latent.z1_prior, latent.z2_transition, z2, actions, mean, std, 3, stride=stride)
    th.manual_seed(4)
    value, transitions = overshooting_roll(latent.z1_prior, latent.z2_transition, z2, actions, mean, std, 3, z1, stride)
    th.testing.assert_close(value, plain)  # the transitions' extra draws come after the KL's
    th.manual_seed(4)
    expected = reference_rolled_transitions(latent, z1, z2, actions, 3, stride)
    starts = [len(range(0, STEPS - d + 1, stride)) for d in (1, 2, 3)]  # stride 2: starts 0, 2 up to depth 2, then 0
    assert [tuple(step.shape) for step in transitions] == [(BATCH, count, 2 * (Z1 + Z2) + ACTIONS) for count in starts]
    for step, reference in zip(transitions, expected, strict=True):
        th.testing.assert_close(step, reference, rtol=1e-5, atol=1e-5)


def test_reward_overshooting_adds_the_weighted_reward_likelihood_of_the_rolls(latent: LatentModel) -> None:
    th.manual_seed(5)
    observations = th.rand(BATCH, STEPS + 1, 3, 32, 32)
    actions = th.rand(BATCH, STEPS, ACTIONS) * 2 - 1
    rewards, zeros = th.randn(BATCH, STEPS), th.zeros(BATCH, STEPS)
    noise = (th.randn(STEPS + 1, BATCH, Z1), th.randn(STEPS + 1, BATCH, Z2))
    latent.overshooting_depth = 3
    th.manual_seed(6)
    total, terms, _ = latent.loss_and_filter(observations, actions, rewards, zeros, zeros, noise=noise)
    assert "overshooting_reward_loss" not in terms
    losses = {}
    for weight in (1.0, 3.0):
        latent.reward_overshooting_weight = weight
        th.manual_seed(6)
        losses[weight] = latent.loss_and_filter(observations, actions, rewards, zeros, zeros, noise=noise)
    weighted_total, weighted_terms, _ = losses[1.0]
    for key in ("kl", "overshooting_kl", "image_loss", "reward_loss", "cost_loss"):
        th.testing.assert_close(weighted_terms[key], terms[key])
    th.testing.assert_close(weighted_total, total + weighted_terms["overshooting_reward_loss"])
    th.testing.assert_close(losses[3.0][1]["overshooting_reward_loss"], 3.0 * weighted_terms["overshooting_reward_loss"])
    latent.zero_grad()
    (weighted_total - total.detach()).backward()  # the term's own gradient (the rest is the same graph's)
    assert all(param.grad is not None and param.grad.abs().sum() > 0 for param in latent.reward_decoder.parameters())
    assert any(param.grad is not None and param.grad.abs().sum() > 0 for param in latent.z2_transition.parameters())


def test_the_rolled_reward_of_a_strided_roll_is_scored_against_the_rewards_its_starts_reach(latent: LatentModel) -> None:
    z2, actions, mean, std = rollout_inputs()
    z1 = th.randn(BATCH, STEPS + 1, Z1)
    rewards, terminated = th.randn(BATCH, STEPS), (th.rand(BATCH, STEPS) < 0.3).float()
    latent.overshooting_stride = 2
    _, transitions = overshooting_roll(latent.z1_prior, latent.z2_transition, z2, actions, mean, std, 3, z1, stride=2)
    per_depth = []
    for d, rolled in enumerate(transitions, start=1):  # depth d from start t scores the reward of t+d-1 -> t+d
        total = 0.0
        for index, start in enumerate(range(0, STEPS - d + 1, 2)):
            reward_mean, reward_std = latent.reward_decoder(rolled[:, index])
            nll = gaussian_nll(rewards[:, start + d - 1], reward_mean[:, 0], reward_std[:, 0])
            total = total + nll * (1 - terminated[:, start + d - 1])
        per_depth.append(total.mean())
    expected = th.stack(per_depth).mean()
    th.testing.assert_close(latent._rolled_reward_nll(transitions, rewards, terminated), expected, rtol=1e-5, atol=1e-5)


def test_reward_overshooting_needs_a_roll() -> None:
    with pytest.raises(ValueError, match=r"latent_reward_overshooting=0.5 .* needs latent_overshooting >= 2, got 1"):
        small_model(HazardPointEnv(), policy_kwargs={**SMALL_POLICY, "latent_reward_overshooting": 0.5})
    refused = "reward_overshooting_weight must be 0, or positive with overshooting_depth >= 2"
    with pytest.raises(ValueError, match=rf"{refused} .* got -1 with overshooting_depth=2"):
        policy_kwargs = {**SMALL_POLICY, "latent_overshooting": 2, "latent_reward_overshooting": -1}
        small_model(HazardPointEnv(), policy_kwargs=policy_kwargs)
    with pytest.raises(ValueError, match=rf"{refused} .* got 1.0 with overshooting_depth=1"):
        LatentModel((4,), ACTIONS, reward_overshooting_weight=1.0)


def test_overshooting_trains_the_prior_and_the_belief_not_the_posterior(latent: LatentModel) -> None:
    """PlaNet holds the posterior fixed: the gradient reaches z2 (what the belief holds) and the prior, not z1's posterior."""
    z2, actions, mean, std = rollout_inputs()
    overshooting_roll(latent.z1_prior, latent.z2_transition, z2, actions, mean, std, 3)[0].backward()
    assert mean.grad is None
    assert z2.grad is not None and z2.grad[:, :-1].abs().sum() > 0
    assert th.all(z2.grad[:, -1] == 0)  # the last frame starts no roll
    assert all(param.grad is not None for param in latent.z1_prior.parameters())


def test_depth_one_is_the_thesis_loss_and_deeper_adds_the_term(latent: LatentModel) -> None:
    th.manual_seed(5)
    observations = th.rand(BATCH, STEPS + 1, 3, 32, 32)
    actions = th.rand(BATCH, STEPS, ACTIONS) * 2 - 1
    zeros = th.zeros(BATCH, STEPS)
    noise = (th.randn(STEPS + 1, BATCH, Z1), th.randn(STEPS + 1, BATCH, Z2))
    total, terms, _ = latent.loss_and_filter(observations, actions, zeros, zeros, zeros, noise=noise)
    assert "overshooting_kl" not in terms
    latent.overshooting_depth = 3
    th.manual_seed(6)
    deeper, deeper_terms, _ = latent.loss_and_filter(observations, actions, zeros, zeros, zeros, noise=noise)
    for key in ("kl", "image_loss", "reward_loss", "cost_loss"):
        th.testing.assert_close(deeper_terms[key], terms[key])
    assert deeper_terms["overshooting_kl"] > 0
    th.testing.assert_close(deeper, total + deeper_terms["overshooting_kl"])


def test_a_model_with_overshooting_learns_and_logs_the_terms(tmp_path) -> None:
    overshooting = {"latent_overshooting": 3, "latent_reward_overshooting": 1.0, "latent_overshooting_stride": 2}
    policy_kwargs = {**SMALL_POLICY, **overshooting}
    model = small_model(HazardPointEnv(obs_type="pixels"), policy_kwargs=policy_kwargs)
    latent = model.policy.latent
    assert latent.overshooting_depth == 3 and latent.reward_overshooting_weight == 1.0 and latent.overshooting_stride == 2
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(100, log_interval=1)
    logged = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    assert "train/overshooting_kl" in logged and "train/overshooting_reward_loss" in logged
    assert all(th.isfinite(param).all() for param in model.policy.parameters())


def test_a_roll_beyond_the_window_or_under_one_step_is_refused() -> None:
    with pytest.raises(ValueError, match=r"latent_overshooting .* sequence_length=3 .* \[1, 3\], got 4"):
        small_model(HazardPointEnv(), policy_kwargs={**SMALL_POLICY, "latent_overshooting": 4})
    with pytest.raises(ValueError, match="overshooting_depth must be at least 1"):
        small_model(HazardPointEnv(), policy_kwargs={**SMALL_POLICY, "latent_overshooting": 0})
    with pytest.raises(ValueError, match=r"latent_overshooting_stride=2 .* needs latent_overshooting >= 2, got 1"):
        small_model(HazardPointEnv(), policy_kwargs={**SMALL_POLICY, "latent_overshooting_stride": 2})
    with pytest.raises(ValueError, match="overshooting_stride must be at least 1"):
        policy_kwargs = {**SMALL_POLICY, "latent_overshooting": 2, "latent_overshooting_stride": 0}
        small_model(HazardPointEnv(), policy_kwargs=policy_kwargs)
    with pytest.raises(ValueError, match="overshooting stride must be at least 1"):
        overshooting_roll(th.nn.Identity(), th.nn.Identity(), *rollout_inputs(), 2, stride=0)
    with pytest.raises(ValueError, match="overshooting depth must be in"):
        overshooting_roll(th.nn.Identity(), th.nn.Identity(), *rollout_inputs()[:2], *rollout_inputs()[2:], STEPS + 1)
