import math
from functools import partial

import pytest
import torch
from sb3_contrib.common.utils import quantile_huber_loss
from torch.distributions import Normal, kl_divergence

from sb3_dsslac.nn.actor import LatentActor
from sb3_dsslac.nn.critics import IQNCostCritic, TwinQCritic, sample_taus
from sb3_dsslac.nn.latent import LatentModel, build_mlp, fixed_std_gaussian_nll, gaussian_kl, gaussian_nll

Z1, Z2, FEATURES, HIDDEN = 4, 8, 16, (32, 32)
BATCH, STEPS, ACTION_DIM = 2, 3, 2


def make_model(observation_shape: tuple[int, ...], **kwargs) -> LatentModel:
    return LatentModel(
        observation_shape, ACTION_DIM, feature_dim=FEATURES, z1_dim=Z1, z2_dim=Z2, hidden_units=HIDDEN, **kwargs
    )


def make_batch(observation_shape: tuple[int, ...]) -> tuple[torch.Tensor, ...]:
    observations = torch.rand(BATCH, STEPS + 1, *observation_shape)
    actions = torch.rand(BATCH, STEPS, ACTION_DIM) * 2 - 1
    rewards = torch.randn(BATCH, STEPS)
    costs = torch.tensor([[0.0, 1.0, 0.0], [2.0, 0.0, 0.0]])
    terminated = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return observations, actions, rewards, costs, terminated


def test_quantile_huber_loss_hand_example():
    current = torch.tensor([[0.0, 1.0]], requires_grad=True)
    taus = torch.tensor([[0.25, 0.75]])
    target = torch.tensor([[0.5, 3.0]])
    # delta_ij = target_j - current_i: [[0.5, 3.0], [-0.5, 2.0]]
    # kappa = 1: Huber [[0.125, 2.5], [0.125, 1.5]]; weights |tau_i - 1{delta < 0}| [[0.25, 0.25], [0.25, 0.75]]
    # terms [[0.03125, 0.625], [0.03125, 1.125]]; sum over i: [0.0625, 1.75]; mean over j: 0.90625
    # sb3-contrib's loss, as DS-SLAC calls it: the fractions shaped (B, N, 1)
    loss = quantile_huber_loss(current, target, cum_prob=taus.unsqueeze(-1))
    assert loss.item() == pytest.approx(0.90625)
    # d/d current_i = -mean_j weight_ij * clip(delta_ij, -1, 1): [-(0.25*0.5 + 0.25*1)/2, -(0.25*-0.5 + 0.75*1)/2]
    loss.backward()
    torch.testing.assert_close(current.grad, torch.tensor([[-0.1875, -0.3125]]))


def test_quantile_huber_loss_needs_the_fractions_as_a_column():
    # With batch == N, fractions shaped (B, N) broadcast along the target axis instead: a different (wrong) loss
    current, target = torch.tensor([[0.0, 1.0], [2.0, 0.5]]), torch.tensor([[0.5, 3.0], [1.0, 0.0]])
    taus = torch.tensor([[0.25, 0.75], [0.1, 0.9]])
    right = quantile_huber_loss(current, target, cum_prob=taus.unsqueeze(-1))
    delta = target.unsqueeze(1) - current.unsqueeze(2)
    huber = torch.where(delta.abs() > 1, delta.abs() - 0.5, 0.5 * delta**2)
    expected = ((taus.unsqueeze(2) - (delta < 0).float()).abs() * huber).sum(dim=1).mean()
    assert right.item() == pytest.approx(expected.item())
    assert quantile_huber_loss(current, target, cum_prob=taus).item() != pytest.approx(expected.item())


def test_gaussian_kl():
    mean, std = torch.randn(4, 5), torch.rand(4, 5) + 0.1
    torch.testing.assert_close(gaussian_kl(mean, std, mean, std), torch.zeros(4, 5))
    mean_p, std_p = torch.randn(4, 5), torch.rand(4, 5) + 0.1
    expected = kl_divergence(Normal(mean, std), Normal(mean_p, std_p))
    torch.testing.assert_close(gaussian_kl(mean, std, mean_p, std_p), expected)


@pytest.mark.parametrize("observation_shape", [(3, 64, 64), (3, 32, 32), (1, 32, 32), (5,)])
def test_latent_model_shapes_and_gradients(observation_shape):
    model = make_model(observation_shape)
    assert model.z_dim == Z1 + Z2
    observations, actions, rewards, costs, terminated = make_batch(observation_shape)

    features = model.encode(observations)
    assert features.shape == (BATCH, STEPS + 1, FEATURES)
    rollout = model.posterior(features, actions)
    assert rollout.z1_mean.shape == rollout.z1_std.shape == rollout.z1.shape == (BATCH, STEPS + 1, Z1)
    assert rollout.z2.shape == (BATCH, STEPS + 1, Z2)
    assert (rollout.z1_std > 0).all()
    assert model.decode(torch.randn(BATCH, STEPS + 1, Z1 + Z2)).shape == observations.shape
    assert model.sample_latents(observations, actions).shape == (BATCH, STEPS + 1, Z1 + Z2)

    total, info = model.loss(observations, actions, rewards, costs, terminated)
    assert total.shape == ()
    terms = ("kl", "image_loss", "reward_loss", "cost_loss")
    assert set(info) == {*terms, "prior_std_min", "posterior_std_min", "z_abs_max", "reconstruction_abs_max"}
    assert all(not value.requires_grad and torch.isfinite(value) for value in info.values())
    torch.testing.assert_close(total.detach(), sum(info[name] for name in terms))
    assert 0 < info["posterior_std_min"] <= rollout.z1_std.max()
    assert info["kl"] >= 0
    total.backward()
    for name, param in model.named_parameters():
        assert param.grad is not None, name
        assert torch.isfinite(param.grad).all(), name


def test_latent_model_image_loss_uses_variance():
    model = make_model((5,), image_noise=0.4)
    observations, actions, rewards, costs, terminated = make_batch((5,))
    torch.manual_seed(0)
    z = model.sample_latents(observations, actions)
    nll = 0.5 * (observations - model.decode(z)).pow(2) / 0.4 + 0.5 * math.log(2 * math.pi * 0.4)
    torch.manual_seed(0)
    _, info = model.loss(observations, actions, rewards, costs, terminated)
    torch.testing.assert_close(info["image_loss"], nll.sum(dim=(1, 2)).mean().detach())


@pytest.mark.parametrize("observation_shape", [(3, 16, 16), (3, 31, 64), (3, 32, 160), (64, 64), (2, 3, 4, 5)])
def test_latent_model_rejects_unsupported_shapes(observation_shape):
    with pytest.raises(ValueError):
        make_model(observation_shape)


def test_latent_model_rejects_mismatched_actions():
    model = make_model((5,))
    observations, actions, rewards, costs, terminated = make_batch((5,))
    with pytest.raises(ValueError):
        model.loss(observations, actions[:, :-1], rewards, costs, terminated)


@pytest.mark.parametrize("logit", [0.3, -4.0, -30.0, 30.0])
def test_cost_loss_weights(logit):
    model = make_model((5,), cost_loss_weight=30.0, cost_positive_weight=100.0)
    output_layer = model.cost_decoder[-1]
    with torch.no_grad():
        output_layer.weight.zero_()
        output_layer.bias.fill_(logit)
    p = torch.sigmoid(torch.tensor(logit, dtype=torch.float64)).item()
    observations, actions, rewards, _, terminated = make_batch((5,))

    costs = torch.ones(BATCH, STEPS)  # y = 1 everywhere
    _, info = model.loss(observations, actions, rewards, costs, terminated)
    expected = -30.0 * 100.0 * STEPS * math.log(p + 1e-6)
    assert info["cost_loss"].item() == pytest.approx(expected, rel=1e-5)

    costs = torch.tensor([[0.0, 1.0, 0.0], [2.0, 0.0, 0.0]])  # y = 1 for 2 of the 6 steps
    _, info = model.loss(observations, actions, rewards, costs, terminated)
    expected = -30.0 * (100.0 * 2 * math.log(p + 1e-6) + 4 * math.log(1 - p + 1e-6)) / BATCH
    assert info["cost_loss"].item() == pytest.approx(expected, rel=1e-5)


def test_reward_loss_masked_by_termination():
    model = make_model((5,))
    observations, actions, rewards, costs, _ = make_batch((5,))
    torch.manual_seed(1)
    _, unmasked = model.loss(observations, actions, rewards, costs, torch.zeros(BATCH, STEPS))
    torch.manual_seed(1)
    _, masked = model.loss(observations, actions, rewards, costs, torch.ones(BATCH, STEPS))
    assert unmasked["reward_loss"] != 0
    assert masked["reward_loss"] == 0


def test_reward_loss_weight_scales_the_reward_term_only():
    observations, actions, rewards, costs, terminated = make_batch((5,))
    losses = {}
    for weight in (1.0, 25.0):
        torch.manual_seed(0)
        model = make_model((5,), reward_loss_weight=weight)
        torch.manual_seed(1)
        _, losses[weight] = model.loss(observations, actions, rewards, costs, terminated)
    assert losses[25.0]["reward_loss"].item() == pytest.approx(25.0 * losses[1.0]["reward_loss"].item(), rel=1e-6)
    for term in ("kl", "image_loss", "cost_loss"):
        assert losses[25.0][term].item() == pytest.approx(losses[1.0][term].item(), rel=1e-6)


def test_filter_step():
    model = make_model((3, 32, 32))
    n = 4
    feature = torch.randn(n, FEATURES)
    z2_prev, action_prev = torch.randn(n, Z2), torch.rand(n, ACTION_DIM) * 2 - 1
    episode_start = torch.tensor([True, False, True, False])
    with torch.no_grad():
        z1, z2 = model.filter_step(feature, z2_prev, action_prev, episode_start, deterministic=True)
        assert z1.shape == (n, Z1) and z2.shape == (n, Z2)
        z1_again, z2_again = model.filter_step(feature, z2_prev, action_prev, episode_start, deterministic=True)
        torch.testing.assert_close(z1, z1_again, rtol=0, atol=0)
        torch.testing.assert_close(z2, z2_again, rtol=0, atol=0)

        z1_other, z2_other = model.filter_step(feature, torch.randn(n, Z2), -action_prev, episode_start, deterministic=True)
        torch.testing.assert_close(z1_other[episode_start], z1[episode_start], rtol=0, atol=0)
        torch.testing.assert_close(z2_other[episode_start], z2[episode_start], rtol=0, atol=0)
        assert not torch.allclose(z1_other[~episode_start], z1[~episode_start])
        assert not torch.allclose(z2_other[~episode_start], z2[~episode_start])

        # Episode starts follow q(z1 | f) then p(z2 | z1); other rows the recurrent networks.
        start_mean, _ = model.z1_posterior_init(feature)
        torch.testing.assert_close(z1[episode_start], start_mean[episode_start])
        step_mean, _ = model.z1_posterior(feature, z2_prev, action_prev)
        torch.testing.assert_close(z1[~episode_start], step_mean[~episode_start])

        torch.manual_seed(0)
        z1_sampled, _ = model.filter_step(feature, z2_prev, action_prev, episode_start)
        assert not torch.allclose(z1_sampled, z1)


def test_twin_q_critic():
    critic = TwinQCritic(Z1 + Z2, ACTION_DIM, hidden_units=HIDDEN)
    q1, q2 = critic(torch.randn(5, Z1 + Z2), torch.rand(5, ACTION_DIM))
    assert q1.shape == q2.shape == (5, 1)
    assert not torch.allclose(q1, q2)


def test_iqn_cost_critic():
    critic = IQNCostCritic(Z1 + Z2, ACTION_DIM, n_cosines=16, hidden_dim=32)
    z, actions = torch.randn(5, Z1 + Z2), torch.rand(5, ACTION_DIM)
    taus = sample_taus(5, 7, "cpu")
    quantiles = critic(z, actions, taus)
    assert quantiles.shape == (5, 7)
    # Quantile i of a row depends only on that row's tau_i.
    taus_changed = taus.clone()
    taus_changed[:, 3] = 1.0 - taus_changed[:, 3]
    changed = critic(z, actions, taus_changed)
    torch.testing.assert_close(changed[:, [0, 1, 2, 4, 5, 6]], quantiles[:, [0, 1, 2, 4, 5, 6]])
    assert not torch.allclose(changed[:, 3], quantiles[:, 3])


@pytest.mark.parametrize("risk_level", [1.0, 0.25])
def test_sample_taus_range(risk_level):
    taus = sample_taus(64, 32, "cpu", risk_level=risk_level)
    assert taus.shape == (64, 32)
    assert (taus >= 1 - risk_level).all() and (taus <= 1).all()
    assert taus.min() < 1 - risk_level + 0.1 * risk_level and taus.max() > 1 - 0.1 * risk_level


@pytest.mark.parametrize("risk_level", [0.0, -0.5, 1.5])
def test_sample_taus_rejects_bad_risk_level(risk_level):
    with pytest.raises(ValueError):
        sample_taus(2, 3, "cpu", risk_level=risk_level)


def test_actor():
    torch.manual_seed(0)  # unseeded, a wide initial std can saturate tanh to exactly 1.0 in float32
    actor = LatentActor(Z1 + Z2, ACTION_DIM, hidden_units=HIDDEN)
    z = torch.randn(64, Z1 + Z2)
    actions = actor(z)
    assert actions.shape == (64, ACTION_DIM)
    assert (actions.abs() < 1).all()
    torch.testing.assert_close(actor(z, deterministic=True), actor(z, deterministic=True), rtol=0, atol=0)
    assert not torch.allclose(actor(z), actor(z))

    torch.manual_seed(3)
    sampled, log_prob = actor.action_log_prob(z)
    assert sampled.shape == (64, ACTION_DIM) and log_prob.shape == (64,)
    assert (sampled.abs() < 1).all()
    # Replay the noise and evaluate the tanh-Gaussian density directly in float64.
    torch.manual_seed(3)
    noise = torch.randn(64, ACTION_DIM).double()
    mean, log_std = actor.net(z).detach().double().chunk(2, dim=-1)
    std = log_std.clamp(-20, 2).exp()
    pre_tanh = mean + std * noise
    torch.testing.assert_close(sampled.detach().double(), torch.tanh(pre_tanh), rtol=0, atol=1e-5)
    expected = Normal(mean, std).log_prob(pre_tanh) - torch.log(1 - torch.tanh(pre_tanh).pow(2))
    torch.testing.assert_close(log_prob.detach().double(), expected.sum(dim=-1), rtol=0, atol=1e-4)
    log_prob.sum().backward()
    assert all(param.grad is not None and torch.isfinite(param.grad).all() for param in actor.parameters())


def test_actor_log_prob_stable_when_saturated():
    actor = LatentActor(Z1 + Z2, ACTION_DIM, hidden_units=HIDDEN)
    with torch.no_grad():
        actor.net[-1].bias[:ACTION_DIM] = 30.0  # tanh(mean) == 1 in float32
    _, log_prob = actor.action_log_prob(torch.randn(8, Z1 + Z2))
    assert torch.isfinite(log_prob).all()


@pytest.mark.parametrize("size", [64, 32])
def test_image_channels_set_the_conv_widths_and_the_decoder_mirrors_them(size):
    model = make_model((3, size, size), image_channels=(8, 16, 24, 40))
    used = (8, 16, 24, 40)[: 4 if size == 64 else 3]
    encoder_widths = [layer.out_channels for layer in model.encoder if isinstance(layer, torch.nn.Conv2d)]
    decoder_widths = [layer.out_channels for layer in model.decoder if isinstance(layer, torch.nn.ConvTranspose2d)]
    assert encoder_widths == [*used, FEATURES]
    assert decoder_widths == [*reversed(used), 3]
    observations, actions, rewards, costs, terminated = make_batch((3, size, size))
    loss, _ = model.loss(observations, actions, rewards, costs, terminated)
    assert torch.isfinite(loss)
    thesis = make_model((3, 64, 64)).encoder
    assert [layer.out_channels for layer in thesis if isinstance(layer, torch.nn.Conv2d)] == [32, 64, 128, 256, FEATURES]


@pytest.mark.parametrize("widths", [(8, 16, 32), (8, 16, 32, 0)])
def test_image_channels_must_be_four_positive_widths(widths):
    with pytest.raises(ValueError, match="image_channels"):
        make_model((3, 64, 64), image_channels=widths)


def test_twin_q_critic_loads_the_earlier_two_network_layout():
    # Models saved before the batched critic hold two nn.Sequential Q-networks, q1 and q2
    torch.manual_seed(0)
    old = torch.nn.ModuleDict(
        {name: build_mlp(Z1 + Z2 + ACTION_DIM, 1, HIDDEN, partial(torch.nn.LeakyReLU, 0.2)) for name in ("q1", "q2")}
    )
    critic = TwinQCritic(Z1 + Z2, ACTION_DIM, hidden_units=HIDDEN)
    critic.load_state_dict(old.state_dict())
    z, actions = torch.randn(5, Z1 + Z2), torch.rand(5, ACTION_DIM)
    x = torch.cat([z, actions], dim=-1)
    q1, q2 = critic(z, actions)
    torch.testing.assert_close(q1, old["q1"](x))
    torch.testing.assert_close(q2, old["q2"](x))


def test_fixed_std_nll_is_the_elementwise_nll_summed_per_row_and_averaged() -> None:
    torch.manual_seed(0)
    x, mean = torch.rand(3, 2, 3, 8, 8), torch.rand(3, 2, 3, 8, 8, requires_grad=True)
    std = 0.4**0.5
    expected = gaussian_nll(x, mean, torch.tensor(std)).flatten(1).sum(dim=1).mean()
    loss = fixed_std_gaussian_nll(x, mean, std)
    torch.testing.assert_close(loss, expected)
    (grad,) = torch.autograd.grad(loss, mean)
    (expected_grad,) = torch.autograd.grad(expected, mean)
    torch.testing.assert_close(grad, expected_grad)


def test_latent_min_std_keeps_the_kl_finite_when_the_prior_collapses():
    """A prior whose std is driven to its floor: the KL grows as 1 / floor^2, so a floor of 0.1 keeps it bounded."""
    kls = {}
    for min_std in (1e-5, 0.1):
        torch.manual_seed(0)
        model = make_model((5,), min_std=min_std)
        last = model.z1_prior.net[-1]
        with torch.no_grad():
            last.bias[Z1:] = -1e4  # softplus(raw std) underflows to 0: the prior std sits at the floor
            last.bias[:Z1] = 3.0  # and its mean away from the posterior's
        observations, actions, rewards, costs, terminated = make_batch((5,))
        total, info = model.loss(observations, actions, rewards, costs, terminated)
        total.backward()
        assert info["prior_std_min"] == pytest.approx(min_std)
        assert all(torch.isfinite(param.grad).all() for param in model.parameters())
        kls[min_std] = float(info["kl"])
    assert kls[1e-5] > 1e8
    assert math.isfinite(kls[0.1]) and kls[0.1] < 1e5


def test_latent_bounds_keep_latents_and_kl_bounded_when_the_networks_run_away():
    """Every latent Gaussian's last layer driven to huge outputs: unbounded, the latents and the KL follow (and the
    gradients overflow); bounded, |z| stays within mean_bound + max_std * |noise| and the KL within GaussianBounds's
    bound, with finite gradients."""
    bounds = {"min_std": 0.1, "max_std": 2.0, "mean_bound": 10.0}
    stats = {}
    for name, kwargs in (("unbounded", {"min_std": 0.1}), ("bounded", bounds)):
        torch.manual_seed(0)
        model = make_model((5,), **kwargs)
        with torch.no_grad():
            for mlp in (model.z1_posterior_init, model.z1_posterior, model.z1_prior, model.z2_init, model.z2_transition):
                mlp.net[-1].weight.mul_(1e3)
                mlp.net[-1].bias.fill_(1e3)
            model.z1_prior.net[-1].bias[:Z1] = -1e3  # the prior's mean far from the posterior's
        observations, actions, rewards, costs, terminated = make_batch((5,))
        total, info = model.loss(observations, actions, rewards, costs, terminated)
        total.backward()
        stats[name] = info
        finite = all(torch.isfinite(param.grad).all() for param in model.parameters())
        assert finite == (name == "bounded")  # unbounded, the image loss overflows float32
    assert stats["unbounded"]["z_abs_max"] > 1e6 and stats["unbounded"]["kl"] > 1e20
    assert stats["bounded"]["prior_std_min"] >= 0.1 and stats["bounded"]["z_abs_max"] < 10.0 + 2.0 * 6.0
    kl_bound_per_dim = math.log(2.0 / 0.1) + (2.0**2 + 4 * 10.0**2) / (2 * 0.1**2)
    assert 1e3 < stats["bounded"]["kl"] <= (STEPS + 1) * Z1 * kl_bound_per_dim


@pytest.mark.parametrize(
    "kwargs, message",
    [({"min_std": 0.0}, "min_std"), ({"min_std": 0.1, "max_std": 0.1}, "max_std"), ({"mean_bound": -1.0}, "mean_bound")],
)
def test_latent_bounds_are_checked(kwargs, message):
    with pytest.raises(ValueError, match=message):
        make_model((5,), **kwargs)


def _kl_gradients(model: LatentModel, batch: tuple[torch.Tensor, ...]) -> tuple[float, dict[str, torch.Tensor]]:
    """The KL term of one loss on ``batch`` and its gradient on the prior's and the posterior's parameters."""
    kl_terms = []

    def kept_kl(*args: torch.Tensor) -> torch.Tensor:
        kl_terms.append(LatentModel._kl(model, *args))
        return kl_terms[-1]

    model._kl = kept_kl  # the loss's own KL, its graph kept to take the gradient of the KL alone
    model.zero_grad()
    _, terms = model.loss(*batch)
    assert len(kl_terms) == 1
    kl_terms[0].backward()
    parts = {"prior": model.z1_prior, "posterior": model.z1_posterior}
    return terms["kl"].item(), {name: torch.cat([p.grad.flatten() for p in part.parameters()]) for name, part in parts.items()}


def test_kl_balance_keeps_the_kl_and_splits_its_gradient_between_prior_and_posterior():
    batch = make_batch((5,))
    results = {}
    for balance in (None, 0.0, 0.5, 0.8, 1.0):
        torch.manual_seed(0)
        results[balance] = _kl_gradients(make_model((5,), kl_balance=balance), batch)
    plain_kl, plain = results[None]
    for balance in (0.0, 0.5, 0.8, 1.0):
        kl, gradients = results[balance]
        assert kl == pytest.approx(plain_kl, rel=1e-6)  # the same value, logged as before
        # the prior's own parameters see the KL only through p: the share of its gradient
        torch.testing.assert_close(gradients["prior"], balance * plain["prior"], rtol=1e-4, atol=1e-6)
    assert results[0.0][1]["prior"].abs().max() == 0
    # the posterior's: (1 - share) of the gradient through q, the share of the one through p's input z2; 0.5 halves both
    torch.testing.assert_close(results[0.5][1]["posterior"], 0.5 * plain["posterior"], rtol=1e-4, atol=1e-6)
    mixed = 0.8 * results[1.0][1]["posterior"] + 0.2 * results[0.0][1]["posterior"]
    torch.testing.assert_close(results[0.8][1]["posterior"], mixed, rtol=1e-4, atol=1e-6)
    assert (results[0.0][1]["posterior"] - plain["posterior"]).abs().max() > 1e-3  # the path through p is cut


@pytest.mark.parametrize("balance", [-0.1, 1.5])
def test_kl_balance_is_a_share(balance):
    with pytest.raises(ValueError, match="kl_balance"):
        make_model((5,), kl_balance=balance)
