"""The fast update path gives the plain path's numbers: precomputed features, channels-last convolutions, compiled
modules, bfloat16 autocast, one shared batch, fused Polyak updates and several envs per burst."""

import copy
import warnings

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_dsslac import DSSLAC
from sb3_dsslac.engine.bursts import split_windows
from sb3_dsslac.engine.dispatch import DispatchCounter, optimizer_step_tensors
from sb3_dsslac.nn import numerics
from sb3_dsslac.nn import latent as latent_module
from sb3_dsslac.nn.latent import LatentModel
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import SMALL, SMALL_POLICY, small_model


def image_batch(size: int, batch: int = 4, steps: int = 3, seed: int = 0) -> tuple[th.Tensor, ...]:
    """Smooth random images in [0, 1] (B, T+1, 3, size, size) and the matching actions, rewards, costs, terminations."""
    generator = th.Generator().manual_seed(seed)
    coarse = th.rand(batch * (steps + 1), 3, size // 8, size // 8, generator=generator)
    images = th.nn.functional.interpolate(coarse, size=(size, size), mode="bilinear").view(batch, steps + 1, 3, size, size)
    actions = 2.0 * th.rand(batch, steps, 2, generator=generator) - 1.0
    rewards = th.randn(batch, steps, generator=generator)
    costs = (th.rand(batch, steps, generator=generator) < 0.3).float()
    return images, actions, rewards, costs, th.zeros(batch, steps)


def burst(model: DSSLAC, indices: th.Tensor) -> dict[str, list[th.Tensor]]:
    """The statistics of one burst of ``model``'s gradient steps on the windows ``indices[k]`` of its buffer."""
    return model.updates.burst(model.replay_buffer, indices, model.current_lagrange_learning_rate)


def seeded_loss(model: LatentModel, batch: tuple[th.Tensor, ...], **kwargs) -> tuple[th.Tensor, dict[str, th.Tensor]]:
    th.manual_seed(7)
    return model.loss(*batch, **kwargs)


def test_precomputed_features_give_the_same_latent_loss() -> None:
    model = LatentModel((3, 32, 32), 2, feature_dim=16, z1_dim=4, z2_dim=8, hidden_units=(32, 32))
    batch = image_batch(32)
    plain, _ = seeded_loss(model, batch)
    shared, _ = seeded_loss(model, batch, features=model.encode(batch[0]))
    th.testing.assert_close(shared, plain)


def test_one_rollout_over_two_batches_gives_each_batch_its_own_numbers() -> None:
    th.manual_seed(0)
    model = LatentModel((3, 32, 32), 2, feature_dim=16, z1_dim=4, z2_dim=8, hidden_units=(32, 32)).double()
    own, other = (tuple(field.double() for field in image_batch(32, batch, seed=seed)) for batch, seed in ((3, 0), (2, 1)))
    noise = th.randn(4, 5, 4, dtype=th.float64), th.randn(4, 5, 8, dtype=th.float64)
    loss, parts, other_z = model.loss_and_filter(*own, other=other[:2], noise=noise)
    grads = th.autograd.grad(loss, list(model.parameters()), allow_unused=True)

    reference, reference_parts, _ = model.loss_and_filter(*own, noise=tuple(part[:, :3] for part in noise))
    reference_grads = th.autograd.grad(reference, list(model.parameters()), allow_unused=True)
    th.testing.assert_close(loss, reference)
    th.testing.assert_close(parts, reference_parts)
    for grad, reference_grad in zip(grads, reference_grads, strict=True):
        th.testing.assert_close(grad, reference_grad)
    with th.no_grad():
        other_rollout = model.posterior(model.encode(other[0]), other[1], tuple(part[:, 3:] for part in noise))
    th.testing.assert_close(other_z, th.cat([other_rollout.z1, other_rollout.z2], dim=-1))
    assert not other_z.requires_grad


def test_each_actor_critic_batch_is_filtered_after_its_own_latent_update(monkeypatch) -> None:
    # The actor-critic batch of a step is filtered in the next step's rollout: by the latent model as that step left it
    model = small_model(HazardPointEnv(obs_type="pixels"), learning_starts=10_000)
    model.learn(60)
    model.latent_pretrained = True
    latent_states, filtered = [], []
    step = model.updates.step
    latent_update, actor_critic_update = step.latent_update, step.actor_critic_update

    def recording_latent_update(*args, **kwargs):
        result = latent_update(*args, **kwargs)
        latent_states.append(copy.deepcopy(model.policy.latent.state_dict()))
        return result

    def recording_actor_critic_update(batch, latents):
        filtered.append((batch, latents))
        return actor_critic_update(batch, latents)

    monkeypatch.setattr(step, "latent_update", recording_latent_update)
    monkeypatch.setattr(step, "actor_critic_update", recording_actor_critic_update)
    monkeypatch.setattr(th, "randn", lambda *shape, **kwargs: th.zeros(*shape, **kwargs))  # the rollouts' means
    indices = model.replay_buffer.sample_indices(3, model.latent_batch_size + model.batch_size)
    burst(model, indices)
    assert len(latent_states) == len(filtered) == 3
    for k, (batch, latents) in enumerate(filtered):
        expected_batch = model.replay_buffer.gather(indices[k])
        th.testing.assert_close(batch.observations, expected_batch.observations[model.latent_batch_size :])
        reference = copy.deepcopy(model.policy.latent)
        reference.load_state_dict(latent_states[k])
        with th.no_grad():
            expected = reference.sample_latents(model.policy.preprocess(batch.observations), batch.actions)
        th.testing.assert_close(latents, expected)


def test_channels_last_convolutions_match_contiguous_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    th.manual_seed(0)
    model = LatentModel((3, 64, 64), 2, feature_dim=32, z1_dim=4, z2_dim=8, hidden_units=(32, 32))
    conv_weight = model.encoder[0].weight
    assert conv_weight.is_contiguous(memory_format=th.channels_last) and not conv_weight.is_contiguous()
    contiguous = copy.deepcopy(model).to(memory_format=th.contiguous_format)
    assert contiguous.encoder[0].weight.is_contiguous()
    batch = image_batch(64)
    loss, _ = seeded_loss(model, batch)
    reference, _ = seeded_loss(contiguous, batch)
    th.testing.assert_close(loss, reference, rtol=1e-5, atol=1e-3)
    loss.backward()
    reference.backward()
    th.testing.assert_close(model.decoder[0].weight.grad, contiguous.decoder[0].weight.grad, rtol=1e-4, atol=1e-4)
    # Narrow convolutions run channels-last only on an x86 CPU, where that layout was faster
    cases = [("AVX512", 64, True), ("AVX2", 64, True), ("AVX512", 32, True), ("AVX2", 32, True), ("DEFAULT", 64, False)]
    for capability, size, channels_last in cases:
        monkeypatch.setattr(th.backends.cpu, "get_cpu_capability", lambda capability=capability: capability)
        narrow = LatentModel(
            (3, size, size), 2, feature_dim=32, z1_dim=4, z2_dim=8, hidden_units=(32, 32), image_channels=(8, 16, 32, 64)
        )
        layouts = {layer.weight.is_contiguous() for layer in (narrow.encoder[0], narrow.decoder[-2], narrow.decoder[0])}
        assert layouts == {not channels_last}, (capability, size)


def test_bf16_latent_loss_is_within_one_percent_of_fp32() -> None:
    th.manual_seed(0)
    model = LatentModel((3, 64, 64), 2)  # the thesis's networks
    batch = image_batch(64)
    reference, reference_parts = seeded_loss(model, batch)
    with th.autocast("cpu", dtype=th.bfloat16):
        loss, parts = seeded_loss(model, batch)
    assert loss.dtype == th.float32
    assert loss.item() != reference.item()  # the autocast took effect
    assert abs(loss.item() - reference.item()) <= 1e-2 * abs(reference.item())
    assert abs(parts["image_loss"].item() - reference_parts["image_loss"].item()) <= 1e-2 * reference_parts["image_loss"].abs()


def warmed_up_pair(policy_kwargs: dict | None = None, both: dict | None = None, **fast: object) -> tuple[DSSLAC, DSSLAC]:
    """
    Two models with the same weights, optimizer states and replay buffer, both of ``policy_kwargs`` (added to the small
    policy's) and the keywords ``both``, the second with ``fast`` keywords.
    """
    policy_kwargs = {**SMALL_POLICY, **(policy_kwargs or {})}
    both = both or {}
    plain = small_model(HazardPointEnv(obs_type="pixels"), learning_starts=10_000, policy_kwargs=policy_kwargs, **both)
    plain.learn(60)  # warm-up data only
    other = small_model(HazardPointEnv(obs_type="pixels"), policy_kwargs=policy_kwargs, **both, **fast)
    other.policy.load_state_dict(plain.policy.state_dict())
    other.replay_buffer = plain.replay_buffer
    for model in (plain, other):
        model.latent_pretrained = True
    return plain, other


def seeded_updates(model: DSSLAC, indices: th.Tensor) -> dict[str, list[th.Tensor]]:
    """The statistics of one burst of gradient steps on the windows ``indices[k]``, from the same random seed."""
    th.manual_seed(11)
    return burst(model, indices)


LATENT_STATISTICS = {
    "latent_loss",
    "kl",
    "overshooting_kl",
    "overshooting_reward_loss",
    "image_loss",
    "reward_loss",
    "cost_loss",
    "prior_std_min",
    "posterior_std_min",
    "z_abs_max",
    "reconstruction_abs_max",
}


# Inductor draws its own random numbers unless told to use eager's generator (its config's own patch: monkeypatch's undo
# deletes the setting, and later compilations in the process then fail)
@th._inductor.config.patch(fallback_random=True)
@pytest.mark.parametrize(
    "recurrent_memory",
    [
        {},
        {
            "policy_kwargs": {
                "latent_recurrence": "gru",
                "latent_overshooting": 2,
                "latent_reward_overshooting": 1.0,
                "latent_overshooting_stride": 2,
                "actor_critic_memory": 8,
            },
            "actor_critic_transitions": 2,
            "burn_in": 2,
            "stored_beliefs": True,
        },
    ],
    ids=["thesis_update", "gru_stored_beliefs_overshooting_memory"],
)
def test_compiled_update_matches_eager(monkeypatch, recurrent_memory: dict) -> None:
    # Minutes on 2 cores with a cold Inductor cache (17 s with a warm one): torch.compile builds the whole gradient step
    # and the burst's last actor-critic step with Inductor's C++ kernels, whatever the networks' sizes. The cpu_pixels
    # presets' narrow first layer, channels-last (as on an x86 CPU), whatever this CPU; and the same with the GRU latent
    # and a burn-in from stored beliefs and latent overshooting of z1 and the reward from every second start
    # (cpu_pixels32_gru_stored's memory and its objectives, with an actor-critic memory over two learned transitions)
    monkeypatch.setattr(latent_module, "channels_last_is_faster", lambda widths, device: True)
    keywords = dict(recurrent_memory)
    policy_kwargs = {"image_channels": (8, 8, 16, 16), **keywords.pop("policy_kwargs", {})}
    eager, compiled = warmed_up_pair(policy_kwargs, both=keywords, compile_updates=True)
    assert compiled.policy.latent.channels_last
    indices = eager.replay_buffer.sample_indices(3, eager.latent_batch_size + eager.batch_size)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="compile_updates")  # no silent fallback to eager
        compiled_stats = seeded_updates(compiled, indices[:2])
    assert set(compiled.updates.compiled_steps) == {"full_step", "last_actor_critic_step"}
    eager_stats = seeded_updates(eager, indices[:2])
    assert eager_stats.keys() == compiled_stats.keys()
    for key, values in eager_stats.items():
        # The first statistics come before any weight moved. After that, Adam's first step moves each weight by about
        # its step size whatever its gradient's size, so a gradient that rounding alone keeps from zero (the two paths
        # sum the products of the dense convolutions in other orders) moves its weight by +-lr either way
        moved = 0
        if key in LATENT_STATISTICS:  # the actor-critic's first statistics are of the step after the first latent update
            th.testing.assert_close(compiled_stats[key][0], values[0], rtol=1e-4, atol=1e-4, msg=key)
            moved = 1
        th.testing.assert_close(th.stack(compiled_stats[key][moved:]), th.stack(values[moved:]), rtol=1e-2, atol=1e-3, msg=key)
    # The whole step is one graph: a few hundred ops where eager dispatches thousands, and no host read
    (batch, _), (_, waiting) = (
        split_windows(compiled.replay_buffer.gather(indices[k]), compiled.latent_batch_size) for k in (2, 0)
    )
    with DispatchCounter() as compiled_counter:
        compiled.updates.run_step(compiled.updates.step.full_step, batch, waiting)
    with DispatchCounter() as eager_counter:
        eager.updates.run_step(eager.updates.step.full_step, batch, waiting)
    assert compiled_counter.ops < eager_counter.ops / 4 and compiled_counter.syncs == 0


def test_compile_failure_falls_back_to_eager_with_a_warning(monkeypatch) -> None:
    def broken_compile(function, **kwargs):
        def fails(*args):
            raise RuntimeError("no compiler here")

        return fails

    monkeypatch.setattr(th, "compile", broken_compile)
    model = small_model(HazardPointEnv(), compile_updates=True)
    with pytest.warns(UserWarning, match="could not be compiled.*no compiler here"):
        model.learn(60)
    assert model.updates.compiled_steps == {} and model._n_updates > 0


def test_a_torch_older_than_2_13_runs_the_updates_eagerly_with_a_warning(monkeypatch) -> None:
    monkeypatch.setattr(th, "__version__", "2.11.0+cu130")
    with pytest.warns(UserWarning, match="2.13 or newer.*2.11.0"):
        model = small_model(HazardPointEnv(), compile_updates=True)
    model.learn(60)
    assert model.updates.compiled_steps == {} and model._n_updates > 0


def test_bf16_update_losses_are_within_one_percent_of_fp32(monkeypatch) -> None:
    monkeypatch.setattr(numerics, "has_native_bf16", lambda device: True)  # emulated bfloat16 computes the same
    fp32, bf16 = warmed_up_pair(bf16=True)
    indices = fp32.replay_buffer.sample_indices(1, fp32.latent_batch_size + fp32.batch_size)
    reference, stats = seeded_updates(fp32, indices), seeded_updates(bf16, indices)
    assert stats["latent_loss"][0] != reference["latent_loss"][0]  # the autocast took effect
    for key in ("latent_loss", "image_loss"):
        assert abs(stats[key][0] - reference[key][0]) <= 1e-2 * abs(reference[key][0]), key


class CountFrames:
    """Forward hook counting the frames an encoder sees."""

    def __init__(self) -> None:
        self.frames = 0

    def __call__(self, module: th.nn.Module, inputs: tuple[th.Tensor, ...], output: th.Tensor) -> None:
        self.frames += inputs[0].shape[0]


@pytest.mark.parametrize("share", [False, True])
def test_shared_batch_encodes_each_sampled_frame_once(share: bool) -> None:
    model = small_model(HazardPointEnv(obs_type="pixels"), share_latent_batch=share, learning_starts=10_000)
    model.learn(60)
    model.latent_pretrained = True
    counter = CountFrames()
    model.policy.latent.encoder.register_forward_hook(counter)
    model.train(gradient_steps=3, batch_size=model.batch_size)
    frames_per_sequence = model.sequence_length + 1
    sequences = max(model.batch_size, model.latent_batch_size) if share else model.batch_size + model.latent_batch_size
    assert counter.frames == 3 * sequences * frames_per_sequence


def test_fused_polyak_update_follows_the_formula() -> None:
    model = small_model(HazardPointEnv())
    model.learn(60)
    policy = model.policy
    th.nn.init.normal_(policy.critic_target.weights[0])  # make target and source differ
    before = policy.critic_target.weights[0].detach().clone()
    indices = model.replay_buffer.sample_indices(1, model.latent_batch_size + model.batch_size)
    seeded_updates(model, indices)
    expected = (1.0 - model.tau) * before + model.tau * policy.critic.weights[0].detach()
    th.testing.assert_close(policy.critic_target.weights[0], expected)


def test_target_critics_stay_out_of_autograd() -> None:
    # A Polyak update under autograd gave every target parameter a grad_fn, a chain growing by 18 nodes per update
    model = small_model(HazardPointEnv())
    model.learn(80)
    assert model._n_updates > 0
    for target in (model.policy.critic_target, model.policy.cost_critic_target):
        for param in target.parameters():
            assert param.grad_fn is None and not param.requires_grad


def test_a_burst_reads_the_host_at_most_once() -> None:
    model = small_model(HazardPointEnv(obs_type="pixels"), learning_starts=10_000)
    model.learn(60)
    model.latent_pretrained = True
    with DispatchCounter(ignore_sync_of=optimizer_step_tensors(model)) as counter:
        model.train(gradient_steps=10, batch_size=model.batch_size)
    assert counter.syncs <= 1


def test_several_envs_keep_one_update_per_agent_step() -> None:
    env = DummyVecEnv([HazardPointEnv for _ in range(4)])
    model = DSSLAC("LatentPolicy", env, **{**SMALL, "train_freq": 8, "gradient_steps": 8})
    assert model.train_freq.frequency == 2  # env.step calls of 4 agent steps each
    model.learn(200)
    assert model.num_timesteps == 200
    # Bursts of 8 updates every 8 agent steps from the first burst after the 40 warm-up steps
    assert model._n_updates == 8 * len(range(48, 201, 8))


def test_train_freq_not_a_multiple_of_n_envs_warns() -> None:
    env = DummyVecEnv([HazardPointEnv for _ in range(3)])
    with pytest.warns(UserWarning, match="not a multiple of n_envs=3"):
        model = DSSLAC("LatentPolicy", env, **{**SMALL, "train_freq": 10})
    assert model.train_freq.frequency == 4


def test_bf16_without_native_support_warns_and_keeps_float32(monkeypatch) -> None:
    monkeypatch.setattr(numerics, "has_native_bf16", lambda device: False)
    with pytest.warns(UserWarning, match="no native bfloat16"):
        model = small_model(HazardPointEnv(), bf16=True)
    assert not model.updates.step.config.bf16
    assert not small_model(HazardPointEnv(), bf16="auto").updates.step.config.bf16
    monkeypatch.setattr(numerics, "has_native_bf16", lambda device: True)
    assert small_model(HazardPointEnv(), bf16="auto").updates.step.config.bf16
    with pytest.raises(ValueError, match="bf16"):
        small_model(HazardPointEnv(), bf16="yes")


def test_fast_keywords_train_save_and_load(tmp_path) -> None:
    model = small_model(HazardPointEnv(obs_type="pixels"), share_latent_batch=True, bf16=True)
    model.learn(100)
    assert model._n_updates == 2 * 6
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip")
    assert loaded.share_latent_batch and loaded.bf16
    observation = np.asarray(model.env.reset())
    actions, _ = model.predict(observation, deterministic=True)
    loaded_actions, _ = loaded.predict(observation, deterministic=True)
    np.testing.assert_allclose(loaded_actions, actions, rtol=1e-5)
