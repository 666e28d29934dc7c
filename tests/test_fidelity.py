"""Pins of the behaviour behind the thesis numbers: defaults, step-size milestone, TD targets, losses and isolation."""

import inspect

import pytest
import torch as th
from torch import nn
from torch.distributions import Normal, kl_divergence

import sb3_dsslac.dsslac as dsslac_module
import sb3_dsslac.engine.gradient_step as gradient_step_module
from sb3_dsslac import DSSLAC, LatentPolicy
from sb3_dsslac.common import lagrange
from sb3_dsslac.common.buffers import SequenceBatch
from sb3_dsslac.nn import numerics
from sb3_dsslac.nn.latent import LatentModel, LatentRollout
from sb3_dsslac.nn.optim import adam_step
from sb3_dsslac.presets import PRESETS, THESIS_LR_DECAY_MILESTONE
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import SMALL, small_model

OPTIMIZERS = ("latent_optimizer", "actor_optimizer", "critic_optimizer", "cost_critic_optimizer")


def step_sizes(model: DSSLAC) -> dict[str, float]:
    """Every optimizer's step size and the multiplier's."""
    sizes = {name: getattr(model.policy, name).param_groups[0]["lr"] for name in OPTIMIZERS}
    assert model.ent_coef_optimizer is not None
    sizes["ent_coef_optimizer"] = model.ent_coef_optimizer.param_groups[0]["lr"]
    sizes["lagrange"] = model.current_lagrange_learning_rate
    return sizes


# ----------------------------------------------------------------------------------------------------------------------
# Step-size milestone
# ----------------------------------------------------------------------------------------------------------------------


def test_thesis_milestone_is_the_reference_codes() -> None:
    # MultiStepLR(milestones=[400]) stepped every 1000 simulator steps after the 60k-simulator-step warm-up
    assert THESIS_LR_DECAY_MILESTONE * 2 == 60_000 + 400 * 1000
    for name in ("thesis", "thesis_fast"):
        assert PRESETS[name]["lr_decay_milestone"] == 230_000
    assert "lr_decay_milestone" not in PRESETS["cpu"]


def test_milestone_halves_every_step_size_once() -> None:
    model = small_model(HazardPointEnv(), lr_decay_milestone=100, learning_rate=3e-4, latent_learning_rate=2e-4)
    model.learn(45)
    model.num_timesteps = 99
    model.train(gradient_steps=1, batch_size=8)
    before = step_sizes(model)
    assert before == {
        "latent_optimizer": 2e-4,
        "actor_optimizer": 3e-4,
        "critic_optimizer": 3e-4,
        "cost_critic_optimizer": 3e-4,
        "ent_coef_optimizer": 3e-4,
        "lagrange": 2e-4,
    }
    model.num_timesteps = 100
    for _ in range(2):  # the factor applies once, not once per train() call
        model.train(gradient_steps=1, batch_size=8)
        assert step_sizes(model) == {name: pytest.approx(0.5 * value) for name, value in before.items()}


def test_no_milestone_no_decay() -> None:
    model = small_model(HazardPointEnv())
    model.learn(45)
    model.num_timesteps = 10**9
    model.train(gradient_steps=1, batch_size=8)
    assert step_sizes(model)["actor_optimizer"] == 2e-4 and step_sizes(model)["latent_optimizer"] == 1e-4


@pytest.mark.parametrize("rule", ["sgd", "episode", "critic"])
def test_multiplier_steps_with_the_decayed_step_size(rule: str, monkeypatch) -> None:
    rates = []
    original = lagrange.sgd_lagrange_step

    def spy(raw: float, cost: float, budget: float, learning_rate: float) -> float:
        rates.append(learning_rate)
        return original(raw, cost, budget, learning_rate)

    def device_spy(raw: th.Tensor, cost: th.Tensor, budget: float, learning_rate: th.Tensor) -> th.Tensor:
        rates.append(float(learning_rate))
        return lagrange.sgd_lagrange_step_on_device(raw, cost, budget, learning_rate)

    monkeypatch.setattr("sb3_dsslac.common.lagrange.sgd_lagrange_step", spy)
    monkeypatch.setattr("sb3_dsslac.engine.gradient_step.sgd_lagrange_step_on_device", device_spy)  # the "critic" rule
    model = small_model(HazardPointEnv(), lagrange=rule, lr_decay_milestone=50, lr_decay_factor=0.25)
    model.learn(80)
    assert rates and set(rates) <= {2e-4, 0.25 * 2e-4}
    assert rates[-1] == pytest.approx(0.25 * 2e-4)


def test_milestone_is_saved_and_a_resumed_run_keeps_the_decayed_step_sizes(tmp_path) -> None:
    model = small_model(HazardPointEnv(), lr_decay_milestone=60, lr_decay_factor=0.1)
    model.learn(50)
    assert step_sizes(model)["actor_optimizer"] == pytest.approx(2e-4)
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip", env=HazardPointEnv())
    assert (loaded.lr_decay_milestone, loaded.lr_decay_factor) == (60, 0.1)
    loaded.learn(30, reset_num_timesteps=False)
    assert loaded.num_timesteps == 80
    assert step_sizes(loaded) == pytest.approx({name: 0.1 * value for name, value in step_sizes(model).items()})
    loaded.save(tmp_path / "resumed.zip")
    again = DSSLAC.load(tmp_path / "resumed.zip", env=HazardPointEnv())
    again.learn(10, reset_num_timesteps=False)
    assert step_sizes(again) == pytest.approx(step_sizes(loaded))


def test_bad_milestone_keywords_are_rejected() -> None:
    with pytest.raises(ValueError, match="lr_decay_factor"):
        small_model(HazardPointEnv(), lr_decay_factor=0.0)
    with pytest.raises(ValueError, match="lr_decay_milestone"):
        small_model(HazardPointEnv(), lr_decay_milestone=-1)


# ----------------------------------------------------------------------------------------------------------------------
# Keywords given twice
# ----------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "value", "other"),
    [
        ("image_noise", 0.1, 0.2),
        ("cost_loss_weight", 3.0, 4.0),
        ("cost_positive_weight", 10.0, 20.0),
        ("latent_learning_rate", 1e-3, 2e-3),
        ("cost_critic", "mean", "iqn"),
    ],
)
def test_a_keyword_given_twice_must_agree(name: str, value, other) -> None:
    policy_kwargs = {**SMALL["policy_kwargs"], name: other}
    with pytest.raises(ValueError, match=rf"{name}={value!r} and policy_kwargs=.*{other!r}"):
        small_model(HazardPointEnv(), policy_kwargs=policy_kwargs, **{name: value})
    agreeing = small_model(HazardPointEnv(), policy_kwargs={**SMALL["policy_kwargs"], name: value}, **{name: value})
    assert agreeing.policy_kwargs[name] == value


def test_policy_kwargs_alone_are_used_and_not_modified(tmp_path) -> None:
    policy_kwargs = {**SMALL["policy_kwargs"], "image_noise": 0.05, "latent_learning_rate": 3e-4, "cost_critic": "mean"}
    given = dict(policy_kwargs)
    model = small_model(HazardPointEnv(), policy_kwargs=policy_kwargs)
    assert policy_kwargs == given
    assert model.policy.latent.image_std == pytest.approx(0.05**0.5)
    assert model.latent_learning_rate == 3e-4 and model.policy.latent_optimizer.param_groups[0]["lr"] == 3e-4
    assert model.cost_critic == "mean" and type(model.policy.cost_critic).__name__ == "MeanCostCritic"
    default = small_model(HazardPointEnv())
    assert default.policy.latent.image_std == pytest.approx(0.4**0.5) and default.cost_critic == "iqn"

    policy_kwargs = {**SMALL["policy_kwargs"], "reward_loss_weight": 20.0}
    model = small_model(HazardPointEnv(), image_noise=0.07, cost_loss_weight=5.0, policy_kwargs=policy_kwargs)
    model.learn(45)
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip", env=HazardPointEnv())
    assert loaded.policy.latent.image_std == pytest.approx(0.07**0.5)
    assert loaded.policy.latent.cost_loss_weight == 5.0 and loaded.policy.latent.reward_loss_weight == 20.0
    loaded.learn(10, reset_num_timesteps=False)


# ----------------------------------------------------------------------------------------------------------------------
# Table 5.2 and the reference code's values
# ----------------------------------------------------------------------------------------------------------------------


def defaults(function) -> dict:
    return {name: p.default for name, p in inspect.signature(function).parameters.items()}


def test_table_5_2_defaults() -> None:
    model = DSSLAC("LatentPolicy", HazardPointEnv(max_episode_steps=500), _init_setup_model=False)
    expected = {
        "learning_rate": 2e-4,
        "latent_learning_rate": 1e-4,
        "buffer_size": 200_000,
        "learning_starts": 30_000,  # W_p = 60k simulator steps at action repeat 2
        "latent_pretrain_steps": 30_000,  # W_t
        "batch_size": 64,
        "latent_batch_size": 32,
        "sequence_length": 10,
        "tau": 5e-3,
        "gamma": 0.99,
        "cost_gamma": 0.995,
        "gradient_steps": 100,
        "cost_limit": 25.0,
        "lagrange": "sgd",
        "lagrange_init": 0.02,
        "lagrange_learning_rate": 2e-4,
        "n_quantiles": 64,  # N = N' = K
        "cvar_risk_level": 1.0,
        "max_grad_norm": 40.0,
        "actor_max_grad_norm": 80.0,
        "cost_critic": "iqn",
        "ent_coef": "auto_4e-3",
        "share_latent_batch": False,
        "bf16": False,
        "lr_decay_milestone": None,
    }
    assert {name: getattr(model, name) for name in expected} == expected
    assert {name: model.policy_kwargs[name] for name in ("image_noise", "cost_loss_weight", "cost_positive_weight")} == {
        "image_noise": 0.4,
        "cost_loss_weight": 30.0,
        "cost_positive_weight": 100.0,
    }
    assert model.cost_budget_per_step == pytest.approx(0.05)
    policy = defaults(LatentPolicy.__init__)
    assert (policy["z1_dim"], policy["z2_dim"], policy["feature_dim"], policy["hidden_units"]) == (32, 200, 200, (256, 256))
    assert (policy["n_cosines"], policy["cost_critic_hidden_dim"]) == (64, 512)

    model._setup_model()
    assert model.train_freq.frequency == 100
    assert th.exp(model.log_ent_coef).item() == pytest.approx(4e-3)
    assert model.lagrange_multiplier == pytest.approx(0.02)
    assert model.target_entropy == -2.0
    assert model.policy.latent.image_std == pytest.approx(0.4**0.5)


# ----------------------------------------------------------------------------------------------------------------------
# TD targets
# ----------------------------------------------------------------------------------------------------------------------


class FakeTwinQ(nn.Module):
    """Q1 = 10 z_0 + a_0, Q2 = 10 z_0 + 5: the min picks Q1 for small actions."""

    def forward(self, z: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """Both networks stacked (2, B, 1), as ``TwinQCritic``."""
        return th.stack([10 * z[:, :1] + actions[:, :1], 10 * z[:, :1] + 5])


class FakeQuantiles(nn.Module):
    """Z_tau = 100 z_0 + a_0 + tau."""

    def forward(self, z: th.Tensor, actions: th.Tensor, taus: th.Tensor) -> th.Tensor:
        return 100 * z[:, :1] + actions[:, :1] + taus


@pytest.mark.parametrize("transitions", [1, SMALL["sequence_length"]])
def test_td_targets_on_a_hand_built_batch(transitions: int, monkeypatch) -> None:
    model = small_model(HazardPointEnv(), gamma=0.9, cost_gamma=0.5, actor_critic_transitions=transitions)
    policy = model.policy
    monkeypatch.setattr(policy, "critic_target", FakeTwinQ())
    monkeypatch.setattr(policy, "cost_critic_target", FakeQuantiles())

    def action_log_prob(z: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        return th.full((z.shape[0], 2), 0.5) * z[:, :1], -z[:, 0]  # a' = 0.5 z'_0, log pi = -z'_0

    monkeypatch.setattr(policy.actor, "action_log_prob", action_log_prob)
    batch_size, steps, z_dim = 3, SMALL["sequence_length"], policy.latent.z_dim
    # z_0 of frame t is t + 1 + 10 * sequence: the index each term reads shows in the result
    latents = (th.arange(steps + 1.0) + 1).repeat(batch_size, 1) + 10 * th.arange(batch_size)[:, None]
    latents = latents[..., None].expand(batch_size, steps + 1, z_dim).clone()
    rewards = th.arange(batch_size * steps, dtype=th.float32).reshape(batch_size, steps)
    costs = rewards * 0.1
    # Sequence 0 runs on; 1 is terminated at its last transition; 2 was terminated at the previous one only (as a time
    # limit truncation, the last transition bootstraps)
    terminated = th.zeros(batch_size, steps)
    terminated[1, -1] = 1.0
    terminated[2, -2] = 1.0
    batch = SequenceBatch(th.zeros(batch_size, steps + 1, 4), th.zeros(batch_size, steps, 2), rewards, costs, terminated)
    ent_coef = th.tensor([0.2])
    n = batch_size * transitions
    taus = th.rand(n, 5)

    step = model.updates.step
    target_q, target_quantiles = step.td_targets(step.transitions(batch, latents), ent_coef, taus)

    # The last `transitions` transitions of each sequence, sequence-major: z' is frame t + 1 of transition t
    assert target_q.shape == (n, 1) and target_quantiles.shape == (n, 5)
    last = slice(steps - transitions, steps)
    next_z0 = latents[:, last.start + 1 :, 0].reshape(n, 1)
    next_a0 = 0.5 * next_z0
    next_q = th.minimum(10 * next_z0 + next_a0, 10 * next_z0 + 5) - 0.2 * (-next_z0)
    alive = (1.0 - terminated[:, last]).reshape(n, 1)
    th.testing.assert_close(target_q, rewards[:, last].reshape(n, 1) + 0.9 * alive * next_q)
    th.testing.assert_close(target_quantiles, costs[:, last].reshape(n, 1) + 0.5 * alive * (100 * next_z0 + next_a0 + taus))
    assert not target_q.requires_grad and not target_quantiles.requires_grad


@pytest.mark.parametrize("transitions", [1, 3])
def test_the_update_learns_from_the_last_transitions(transitions: int) -> None:
    """One transition: z at index -2 (the thesis's); k of them: z at indices -k-1 .. -2 with their actions."""
    model = small_model(HazardPointEnv(), actor_critic_transitions=transitions)
    model.learn(45)
    seen = []
    model.policy.critic.register_forward_pre_hook(lambda module, args: seen.append([arg.detach().clone() for arg in args]))
    latents = th.randn(8, SMALL["sequence_length"] + 1, model.policy.latent.z_dim)
    batch = model.replay_buffer.gather(model.replay_buffer.sample_indices(1, 8)[0])
    model.updates.step.actor_critic_update(batch, latents)
    z, actions = seen[0]
    th.testing.assert_close(z, latents[:, -transitions - 1 : -1].reshape(8 * transitions, -1))
    th.testing.assert_close(actions, batch.actions[:, -transitions:].reshape(8 * transitions, -1))
    if transitions == 1:
        th.testing.assert_close(z, latents[:, -2])


def test_actor_critic_transitions_must_fit_the_sequence() -> None:
    with pytest.raises(ValueError, match="actor_critic_transitions"):
        small_model(HazardPointEnv(), actor_critic_transitions=SMALL["sequence_length"] + 1)
    with pytest.raises(ValueError, match="actor_critic_transitions"):
        small_model(HazardPointEnv(), actor_critic_transitions=0)


# ----------------------------------------------------------------------------------------------------------------------
# Latent model loss
# ----------------------------------------------------------------------------------------------------------------------


def test_kl_is_against_n01_at_t0_and_the_teacher_forced_prior_after(monkeypatch) -> None:
    th.manual_seed(0)
    model = LatentModel((4,), 2, feature_dim=8, z1_dim=3, z2_dim=5, hidden_units=(16,))
    batch, steps = 2, 4
    z1_mean, z1_std = th.randn(batch, steps + 1, 3), th.rand(batch, steps + 1, 3) + 0.2
    rollout = LatentRollout(z1_mean, z1_std, th.randn(batch, steps + 1, 3), th.randn(batch, steps + 1, 5))
    monkeypatch.setattr(model, "posterior", lambda features, actions, noise=None, start=None: rollout)
    actions = th.rand(batch, steps, 2) * 2 - 1
    zeros = th.zeros(batch, steps)
    _, parts = model.loss(th.randn(batch, steps + 1, 4), actions, zeros, zeros, zeros)

    posterior = Normal(rollout.z1_mean, rollout.z1_std)
    expected = kl_divergence(Normal(posterior.loc[:, 0], posterior.scale[:, 0]), Normal(0.0, 1.0)).sum(dim=-1)
    for t in range(1, steps + 1):
        prior_mean, prior_std = model.z1_prior(rollout.z2[:, t - 1], actions[:, t - 1])  # posterior z2, real action
        expected = expected + kl_divergence(
            Normal(rollout.z1_mean[:, t], rollout.z1_std[:, t]), Normal(prior_mean, prior_std)
        ).sum(dim=-1)
    th.testing.assert_close(parts["kl"], expected.mean())


# ----------------------------------------------------------------------------------------------------------------------
# Quantile fractions and isolation of the actor's loss
# ----------------------------------------------------------------------------------------------------------------------


def test_cvar_taus_reach_only_the_actor(monkeypatch) -> None:
    model = small_model(HazardPointEnv(), cvar_risk_level=0.2)
    model.learn(45)
    loss_taus, target_taus, critic_taus = [], [], []
    step = model.updates.step
    original_loss, original_targets = gradient_step_module.quantile_huber_loss, step.td_targets
    monkeypatch.setattr(
        gradient_step_module,
        "quantile_huber_loss",
        lambda c, t, cum_prob: loss_taus.append(cum_prob.squeeze(-1)) or original_loss(c, t, cum_prob=cum_prob),
    )
    monkeypatch.setattr(step, "td_targets", lambda t, e, taus: target_taus.append(taus) or original_targets(t, e, taus))
    model.policy.cost_critic.register_forward_pre_hook(lambda module, args: critic_taus.append(args[2].detach()))
    model.train(gradient_steps=2, batch_size=8)

    for taus in (*loss_taus, *target_taus):  # the critic learns every quantile: U(0, 1), never the tail only
        assert taus.min() < 0.5 and taus.max() <= 1.0
    assert len(loss_taus) == len(target_taus) == 2
    tail_calls = [taus for taus in critic_taus if taus.min() >= 0.8]
    assert len(tail_calls) == 2  # one CVaR batch per update, for the actor
    assert th.equal(critic_taus[0], loss_taus[0])  # and the critic's own forward uses its U(0, 1) fractions


def test_the_actor_loss_leaves_the_critics_alone(monkeypatch) -> None:
    model = small_model(HazardPointEnv())
    model.learn(45)
    policy = model.policy
    critics = [*policy.critic.parameters(), *policy.cost_critic.parameters()]
    snapshots: dict[str, list[th.Tensor]] = {}

    names = {policy.cost_critic_optimizer: "critic_grads", policy.actor_optimizer: "grads_at_actor_step"}

    def spying_adam_step(optimizer: th.optim.Optimizer, grads: list[th.Tensor], learning_rate: th.Tensor) -> None:
        adam_step(optimizer, grads, learning_rate)
        if optimizer in names:
            snapshots[names[optimizer]] = [p.grad.clone() for p in critics]

    # The critics' gradients when their own steps are taken, and again when the actor steps
    monkeypatch.setattr(gradient_step_module, "adam_step", spying_adam_step)
    actor_before = [p.detach().clone() for p in policy.actor.parameters()]
    batch = model.replay_buffer.gather(model.replay_buffer.sample_indices(1, 8)[0])
    latents = th.randn(8, SMALL["sequence_length"] + 1, policy.latent.z_dim)
    model.updates.step.actor_critic_update(batch, latents)

    policy.critic_optimizer.zero_grad(set_to_none=False)  # the reward critic's grads came before the snapshot
    for before, at_actor_step in zip(snapshots["critic_grads"], snapshots["grads_at_actor_step"], strict=True):
        th.testing.assert_close(before, at_actor_step, rtol=0, atol=0)
    assert any(not th.equal(a, p) for a, p in zip(actor_before, policy.actor.parameters(), strict=True))


# ----------------------------------------------------------------------------------------------------------------------
# Smaller deviations: clipping, TF32, the critic rule's budget, the PID rule's smoothing
# ----------------------------------------------------------------------------------------------------------------------


def clipped_cost_critic_grads(model: DSSLAC, scale_of, monkeypatch) -> list[th.Tensor]:
    """The cost critic's gradients as its Adam step gets them, for a loss whose gradient is ``scale_of(i)`` on param i."""
    optimizer = model.policy.cost_critic_optimizer
    params = optimizer.param_groups[0]["params"]
    loss = sum(param.sum() * scale_of(index) for index, param in enumerate(params))
    seen: list[list[th.Tensor]] = []
    monkeypatch.setattr(gradient_step_module, "adam_step", lambda optimizer, grads, learning_rate: seen.append(grads))
    step = model.updates.step
    step.optimizer_step(optimizer, loss, model.max_grad_norm, step.cost_critic_clip_groups)
    return seen[0]


def test_iqn_cosine_and_quantile_nets_are_clipped_each(monkeypatch) -> None:
    model = small_model(HazardPointEnv())
    n_cosine = len(list(model.policy.cost_critic.cosine_net.parameters()))
    # A small gradient on the cosine net (far under 40), a large one on the quantile net
    grads = clipped_cost_critic_grads(model, lambda index: 1e-3 if index < n_cosine else 100.0, monkeypatch)
    # One joint clip would have shrunk the cosine net's gradient with the quantile net's
    assert all(th.allclose(grad, th.full_like(grad, 1e-3)) for grad in grads[:n_cosine])
    assert th.nn.utils.get_total_norm(grads[n_cosine:]).item() == pytest.approx(40.0, rel=1e-4)

    mean = small_model(HazardPointEnv(), cost_critic="mean")
    grads = clipped_cost_critic_grads(mean, lambda index: 100.0, monkeypatch)
    assert th.nn.utils.get_total_norm(grads).item() == pytest.approx(40.0, rel=1e-4)


def test_tf32_scope_restores_the_process_settings() -> None:
    switches = th.backends.cuda.matmul, th.backends.cudnn.conv
    before = tuple(switch.fp32_precision for switch in switches)
    th.backends.cuda.matmul.fp32_precision = "ieee"
    try:
        with numerics.tf32_matmul(True):
            assert tuple(switch.fp32_precision for switch in switches) == ("tf32", "tf32")
        assert th.backends.cuda.matmul.fp32_precision == "ieee"
        with pytest.raises(KeyError), numerics.tf32_matmul(True):
            raise KeyError
        assert th.backends.cuda.matmul.fp32_precision == "ieee"
        with numerics.tf32_matmul(False):
            assert th.backends.cuda.matmul.fp32_precision == "ieee"
    finally:
        for switch, precision in zip(switches, before, strict=True):
            switch.fp32_precision = precision


def test_tf32_is_requested_only_for_learning_on_cuda(monkeypatch) -> None:
    requested = []
    original = dsslac_module.tf32_matmul
    monkeypatch.setattr(dsslac_module, "tf32_matmul", lambda enabled: requested.append(enabled) or original(enabled))
    before = th.backends.cuda.matmul.fp32_precision
    model = small_model(HazardPointEnv(), device="cpu")
    assert th.backends.cuda.matmul.fp32_precision == before and requested == []  # not at construction
    model.learn(10)
    assert requested == [False]  # a CPU model leaves the switches alone
    model.device = th.device("cuda")  # what the scope asks for on CUDA (nothing runs: no steps left)
    model.learn(0, reset_num_timesteps=False)
    model.tf32 = False
    model.learn(0, reset_num_timesteps=False)
    assert requested == [False, True, False]


def test_critic_rule_budget_is_the_infinite_horizon_value(monkeypatch) -> None:
    model = small_model(HazardPointEnv(max_episode_steps=500), lagrange="critic")
    assert model.critic_cost_budget == pytest.approx(10.0)
    assert model.discounted_cost_budget == pytest.approx(9.184, abs=1e-3)  # still the mean critic's initial bias
    budgets = []
    original = gradient_step_module.sgd_lagrange_step_on_device
    monkeypatch.setattr(
        gradient_step_module, "sgd_lagrange_step_on_device", lambda r, c, b, lr: budgets.append(b) or original(r, c, b, lr)
    )
    model.learn(50)
    assert budgets and budgets == pytest.approx([10.0] * len(budgets))


def test_pid_rule_uses_the_smoothing_and_saves_its_state(tmp_path, monkeypatch) -> None:
    seen = []
    original = lagrange.pid_lagrange_step
    monkeypatch.setattr(lagrange, "pid_lagrange_step", lambda *args: seen.append(args[-1]) or original(*args))
    model = small_model(HazardPointEnv(), lagrange="pid", pid_cost_ema=0.7, learning_starts=20)
    model.learn(60)
    assert seen == [0.7, 0.7] and model.pid_state[1] is not None  # episodes end at steps 30 and 60
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip")
    assert loaded.pid_state == model.pid_state and loaded.pid_cost_ema == 0.7
    with pytest.raises(ValueError, match="pid_cost_ema"):
        small_model(HazardPointEnv(), pid_cost_ema=1.0)
