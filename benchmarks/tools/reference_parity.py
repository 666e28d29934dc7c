"""
One update of this package beside one of the thesis code's (tsmir/ds-slac), run side by side on one fixed batch.

    git clone https://github.com/tsmir/ds-slac /tmp/ds-slac
    python benchmarks/tools/reference_parity.py --ref-dir /tmp/ds-slac

The thesis code has no licence: it is imported from ``--ref-dir`` at run time and nothing of it is copied here. Its
TorchScript modules run as Python (the tool restarts itself with ``PYTORCH_JIT=0``). Its ``algo.py`` imports
``scipy.stats`` and uses none of it: where SciPy is missing, an empty module stands in for it.

Both sides are built at the same shapes and hyperparameters: for ``thesis``, the thesis code from its own
``configuration.py`` and this package from the ``thesis`` preset (64x64x3 frames, sequences of 10 transitions (11
frames), z1 32, z2 200, features 200, hidden 256, 64 cosines and quantiles); for ``cpu``, both at the ``cpu`` preset's
shapes, except the IQN's 64 cosines, 64 quantiles and 512 hidden units, which the thesis code fixes. The thesis code's
initial weights are copied into ``LatentPolicy``'s modules, the entropy coefficient and the multiplier are set equal,
every normal draw is zero and the IQN's quantile fractions lie on the grid ``(arange(N) + 0.5) / N``, eager float32,
batches of 2 (latent) and 3 (actor-critic) sequences. Then one ``update_latent``, ``update_sac`` and ``update_lag``
there against ``GradientStep.full_step`` + ``last_actor_critic_step`` (the end of a burst) and ``sgd_lagrange_step``
here, compared component by component: the latent loss terms, the latents and actions fed to the critics and the target
critics, the targets' outputs, the critic, IQN, actor and entropy-coefficient losses, every module's clipped gradient,
each Adam step replayed here on the thesis code's gradients and parameters, both Polyak updates replayed in float64 on
both sides (in float32 the update, about 1e-6 per weight, is a few hundred ulps of the weight, and ``t + tau (s - t)``
here rounds Adam's uniform first step apart from ``(1 - tau) t + tau s`` there by 0.1% of it), and one multiplier step.
Error: ``||ours - thesis|| / ||thesis||`` (L2 over the component's values); for a step (Adam, Polyak, the multiplier's
SGD on its raw parameter), of the change it made. Every component must agree within 1e-4 (exit status 1 if not).

Then the departures, each shown by a run that brings it out (the rest as above), with the components it moves:

- ``log pi``'s tanh correction, exact here, ``log(1 - a^2 + 1e-6)`` there: the actor's means pushed to 10 (saturated);
- one next action a' for both TD targets here, one per target there: the actor's noise nonzero, the thesis code's
  second a' drawn from the same noise as its first (every component equal), then from its own.

``--write-fixture`` also runs the thesis shapes from the name-seeded weights of ``fixed_weights`` (copied into the
thesis code's modules) and writes the thesis code's numbers (``fingerprint``) to
``tests/data/thesis_update_reference.json``, which ``tests/test_thesis_drift.py`` compares with this package's update
without the thesis code. About 20 s on a 2-core CPU.
"""

import argparse
import contextlib
import copy
import importlib
import importlib.util
import json
import os
import subprocess
import sys
import types
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# Run from a checkout: the benchmarks' shared modules (machine.py)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gymnasium as gym
import numpy as np
import torch as th
from machine import cpu_model
from torch import nn

import sb3_dsslac.engine.gradient_step as gradient_step_module
from sb3_dsslac import DSSLAC
from sb3_dsslac.common.buffers import SequenceBatch
from sb3_dsslac.common.lagrange import sgd_lagrange_step
from sb3_dsslac.engine.gradient_step import GradientStep
from sb3_dsslac.nn.critics import TwinQCritic
from sb3_dsslac.nn.optim import adam_step
from sb3_dsslac.presets import preset_hyperparams

TOLERANCE = 1e-4
REPO = Path(__file__).resolve().parents[2]
FIXTURE = REPO / "tests" / "data" / "thesis_update_reference.json"
EPISODE_LENGTH = 500  # agent steps: 1000 simulator steps at the thesis's action repeat 2
ACTION_REPEAT = 2
STEP_COST = 1.0  # the cost of the agent step the multiplier learns from
SATURATED_MEAN = 10.0  # the actor's pre-tanh means in the saturated run: tanh(10) is 1.0 in float32

Record = dict[str, th.Tensor]


@dataclass(frozen=True)
class Setup:
    """
    A preset at shapes the thesis code's modules take.

    :param preset: the preset of this package
    :param overrides: DSSLAC keywords on top of the preset (where the thesis code fixes a value)
    :param thesis_configuration: build the thesis code from its own ``configuration.py`` (else from our model's values)
    :param latent_batch_size: sequences of the latent update
    :param batch_size: sequences of the actor-critic update
    """

    preset: str
    overrides: dict[str, Any] = field(default_factory=dict)
    thesis_configuration: bool = False
    latent_batch_size: int = 2
    batch_size: int = 3


THESIS = Setup("thesis", thesis_configuration=True)
CPU = Setup("cpu", {"n_quantiles": 64, "policy_kwargs": {"n_cosines": 64, "cost_critic_hidden_dim": 512}})


class FrameEnv(gym.Env):
    """The spaces of a Safety-Gym pixel task: uint8 frames (3, 64, 64) and 2 actions in [-1, 1]. Never stepped here."""

    metadata = {"render_modes": []}  # noqa: RUF012

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(0, 255, (3, 64, 64), np.uint8)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        return np.zeros(self.observation_space.shape, np.uint8), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        return np.zeros(self.observation_space.shape, np.uint8), 0.0, False, False, {"cost": 0.0}


def build_model(setup: Setup, seed: int = 0) -> DSSLAC:
    """The preset's model on ``FrameEnv``, eager on the CPU, with the setup's batch sizes."""
    hyperparams = preset_hyperparams(setup.preset, setup.overrides)
    hyperparams.update(
        batch_size=setup.batch_size,
        latent_batch_size=setup.latent_batch_size,
        buffer_size=1_000,
        compile_updates=False,
        episode_length=EPISODE_LENGTH,
    )
    return DSSLAC("LatentPolicy", FrameEnv(), seed=seed, device="cpu", **hyperparams)


def fixed_batches(model: DSSLAC, setup: Setup, seed: int = 0) -> tuple[SequenceBatch, SequenceBatch]:
    """
    The latent batch and the actor-critic batch, from their own generator: uint8 noise frames (B, L+1, 3, 64, 64),
    actions in [-0.9, 0.9], normal rewards, costs 0 or 1 (the last transition of the first actor-critic sequence unsafe)
    and the last actor-critic sequence terminated at its last transition (the thesis code's sequences end there).
    """
    generator = th.Generator().manual_seed(seed)
    frames, action_dim = model.sequence_length + 1, model.policy.action_dim

    def batch(size: int) -> SequenceBatch:
        observations = th.randint(0, 256, (size, frames, *model.observation_space.shape), generator=generator)
        actions = th.rand(size, frames - 1, action_dim, generator=generator) * 1.8 - 0.9
        rewards = th.randn(size, frames - 1, generator=generator)
        costs = (th.rand(size, frames - 1, generator=generator) < 0.3).float()
        costs[0, -1] = 1.0
        terminated = th.zeros(size, frames - 1)
        terminated[-1, -1] = 1.0
        return SequenceBatch(observations.to(th.uint8), actions, rewards, costs, terminated)

    return batch(setup.latent_batch_size), batch(setup.batch_size)


def fixed_weights(model: DSSLAC, seed: int = 0) -> None:
    """
    Set every network parameter from a generator seeded by its name (the target critics copied from the critics): the
    weights follow from the names and shapes alone. Weights uniform within Xavier's bound, biases within +-0.1.
    """
    policy = model.policy
    with th.no_grad():
        for name, param in policy.named_parameters():
            if name.startswith(("critic_target.", "cost_critic_target.")):
                continue
            generator = th.Generator().manual_seed(seed + zlib.crc32(name.encode()))
            if name.endswith("bias") or ".biases." in name:
                bound = 0.1
            elif param.dim() == 3:  # TwinQCritic's stacked (2, in, out) weights
                bound = (6.0 / (param.shape[1] + param.shape[2])) ** 0.5
            else:
                receptive = int(np.prod(param.shape[2:]))
                bound = (6.0 / ((param.shape[0] + param.shape[1]) * receptive)) ** 0.5
            param.copy_((th.rand(param.shape, generator=generator) * 2.0 - 1.0) * bound)
    policy.critic_target.load_state_dict(policy.critic.state_dict())
    policy.cost_critic_target.load_state_dict(policy.cost_critic.state_dict())


def quantile_grid(batch_size: int, n_quantiles: int, risk_level: float = 1.0) -> th.Tensor:
    """Quantile fractions ``1 - risk_level + risk_level * (arange(N) + 0.5) / N``, (batch_size, N)."""
    grid = (th.arange(n_quantiles, dtype=th.float32) + 0.5) / n_quantiles
    return (1.0 - risk_level + risk_level * grid).expand(batch_size, n_quantiles).clone()


@contextlib.contextmanager
def fixed_draws(action_dim: int, actor_noise: list[th.Tensor], samplers: list[tuple[Any, str, Callable]]) -> Iterator[None]:
    """
    Inside the block ``torch.randn`` and ``torch.randn_like`` give zeros, except the actor's draws ((n, action_dim)),
    which take ``actor_noise`` in turn when it is given (every one of them, or a RuntimeError), and each
    ``(module, name, replacement)`` of ``samplers`` replaces a quantile-fraction sampler.
    """
    queue = list(actor_noise)

    def normal_like(tensor: th.Tensor, *args: Any, **kwargs: Any) -> th.Tensor:
        if actor_noise and tensor.dim() == 2 and tensor.shape[-1] == action_dim:
            if not queue:
                raise RuntimeError("more actor draws than the noise given")
            return queue.pop(0).clone()
        return th.zeros_like(tensor)

    def normal(*size: Any, **kwargs: Any) -> th.Tensor:
        shape = size[0] if len(size) == 1 and isinstance(size[0], tuple | list | th.Size) else size
        return th.zeros(*shape, dtype=kwargs.get("dtype"), device=kwargs.get("device"))

    patches = [(th, "randn", normal), (th, "randn_like", normal_like), *samplers]
    saved = [(owner, name, getattr(owner, name)) for owner, name, _ in patches]
    for owner, name, value in patches:
        setattr(owner, name, value)
    try:
        yield
    finally:
        for owner, name, value in saved:
            setattr(owner, name, value)
    if queue:
        raise RuntimeError(f"{len(queue)} actor draws of the noise given did not happen")


def _record_inputs(record: Record, critic: nn.Module, target: nn.Module) -> list[Any]:
    """Hooks that keep the first (z, a) fed to ``critic`` and to ``target``, and the target's output; their handles."""

    def keep_inputs(prefix: str) -> Callable:
        def hook(module: nn.Module, args: tuple) -> None:
            if f"{prefix}/z" not in record:
                record[f"{prefix}/z"], record[f"{prefix}/a"] = (arg.detach().clone() for arg in args[:2])

        return hook

    def keep_output(module: nn.Module, args: tuple, output: Any) -> None:
        record["target/q"] = th.stack(list(output)).detach().reshape(2, -1).clone()

    return [
        critic.register_forward_pre_hook(keep_inputs("critic_input")),
        target.register_forward_pre_hook(keep_inputs("target_input")),
        target.register_forward_hook(keep_output),
    ]


def parameter_names(model: DSSLAC) -> dict[th.Tensor, str]:
    """Every parameter of the update by its name: the policy's, and ``log_ent_coef``."""
    names = {param: name for name, param in model.policy.named_parameters()}
    names[model.log_ent_coef] = "log_ent_coef"
    return names


def run_ours(model: DSSLAC, latent_batch: SequenceBatch, batch: SequenceBatch, actor_noise: list[th.Tensor]) -> Record:
    """
    One gradient step as the end of a burst runs it: ``full_step`` (the latent update) then ``last_actor_critic_step``
    (the actor-critic update on ``batch``, filtered by the updated latent model), and one step of the thesis's
    multiplier rule from an agent step of cost ``STEP_COST``.

    :return: the update's components by name (see ``compare``), the gradients as the Adam steps got them
    """
    step, policy = model.updates.step, model.policy
    names = parameter_names(model)
    record: Record = {}

    def recording_adam_step(optimizer: th.optim.Optimizer, grads: list[th.Tensor], learning_rate: th.Tensor) -> None:
        for param, grad in zip(optimizer.param_groups[0]["params"], grads, strict=True):
            record[f"grad/{names[param]}"] = grad.detach().clone()
        adam_step(optimizer, grads, learning_rate)

    def keep_quantiles(module: nn.Module, args: tuple, output: th.Tensor) -> None:
        record["target/quantiles"] = output.detach().clone()

    handles = _record_inputs(record, policy.critic, policy.critic_target)
    handles.append(policy.cost_critic_target.register_forward_hook(keep_quantiles))
    model.updates.begin_burst(model.current_lagrange_learning_rate)
    samplers = [(gradient_step_module, "sample_taus", lambda n, k, device, risk_level=1.0: quantile_grid(n, k, risk_level))]
    saved_adam_step = gradient_step_module.adam_step
    gradient_step_module.adam_step = recording_adam_step
    try:
        with fixed_draws(policy.action_dim, actor_noise, samplers):
            stats = step.full_step(latent_batch, None)
            stats.update(step.last_actor_critic_step(batch))
    finally:
        gradient_step_module.adam_step = saved_adam_step
        for handle in handles:
            handle.remove()
    for key, stat in (("kl", "kl"), ("image", "image_loss"), ("reward", "reward_loss"), ("cost", "cost_loss")):
        record[f"latent/{key}"] = stats[stat]
    for key in ("critic", "cost_critic", "actor", "ent_coef"):
        record[f"loss/{key}"] = stats[f"{key}_loss"]
    raw = float(model.lagrange_raw)
    new_raw = sgd_lagrange_step(raw, STEP_COST, model.cost_budget_per_step, model.current_lagrange_learning_rate)
    record["multiplier/step"] = th.tensor(new_raw - raw, dtype=th.float64)
    return record


@dataclass
class Pair:
    """
    One parameter here and the thesis code's parameters it is made of.

    :param ours: the parameter here
    :param thesis: the thesis code's: one, or for ``TwinQCritic``'s stacked layers those of both Q-networks
    :param kind: "same" (one tensor, same shape), "twin_weight" (ours (2, in, out) from two (out, in)) or "twin_bias"
        (ours (2, 1, out) from two (out,))
    """

    ours: th.Tensor
    thesis: list[th.Tensor]
    kind: str = "same"

    def from_thesis(self, tensors: list[th.Tensor]) -> th.Tensor:
        """Ours from the thesis code's tensors (values, gradients) of ``thesis``."""
        if self.kind == "twin_weight":
            return th.stack([tensor.t() for tensor in tensors])
        if self.kind == "twin_bias":
            return th.stack(tensors).unsqueeze(1)
        return tensors[0]

    def to_thesis(self, tensor: th.Tensor) -> list[th.Tensor]:
        """The thesis code's tensors from ours."""
        if self.kind == "twin_weight":
            return [tensor[0].t(), tensor[1].t()]
        if self.kind == "twin_bias":
            return [tensor[0, 0], tensor[1, 0]]
        return [tensor]


def _layers(module: nn.Module) -> list[nn.Module]:
    return [layer for layer in module.modules() if isinstance(layer, nn.Linear | nn.Conv2d | nn.ConvTranspose2d)]


def parameter_pairs(model: DSSLAC, algo: Any) -> list[Pair]:
    """Every parameter of the update here with its counterpart in the thesis code's ``DSSLACAlgorithm``, all of each."""
    policy, latent, reference = model.policy, model.policy.latent, algo.latent
    modules = [
        (latent.encoder, reference.encoder),
        (latent.decoder, reference.decoder),
        (latent.z2_init, reference.z2_prior_init),
        (latent.z1_prior, reference.z1_prior),
        (latent.z2_transition, reference.z2_prior),
        (latent.z1_posterior_init, reference.z1_posterior_init),
        (latent.z1_posterior, reference.z1_posterior),
        (latent.reward_decoder, reference.reward),
        (latent.cost_decoder, reference.cost),
        (policy.actor, algo.actor),
        (policy.cost_critic.cosine_net, algo.cos_network),
        (policy.cost_critic.quantile_net, algo.safety_critic),
        (policy.cost_critic_target.cosine_net, algo.cos_network_target),
        (policy.cost_critic_target.quantile_net, algo.safety_critic_target),
    ]
    pairs = [Pair(model.log_ent_coef, [algo.log_alpha])]
    for ours, theirs in modules:
        for mine, reference_layer in zip(_layers(ours), _layers(theirs), strict=True):
            for attribute in ("weight", "bias"):
                mine_param, reference_param = getattr(mine, attribute), getattr(reference_layer, attribute)
                if mine_param.shape != reference_param.shape:
                    raise ValueError(f"shapes differ: {tuple(mine_param.shape)} here, {tuple(reference_param.shape)} there")
                pairs.append(Pair(mine_param, [reference_param]))
    twins: list[tuple[TwinQCritic, Any]] = [(policy.critic, algo.critic), (policy.critic_target, algo.critic_target)]
    for ours, theirs in twins:
        first, second = _layers(theirs.net1), _layers(theirs.net2)
        for k, (weight, bias) in enumerate(zip(ours.weights, ours.biases, strict=True)):
            pairs.append(Pair(weight, [first[k].weight, second[k].weight], "twin_weight"))
            pairs.append(Pair(bias, [first[k].bias, second[k].bias], "twin_bias"))
    covered = {pair.ours for pair in pairs}
    assert covered == set(parameter_names(model)), "a parameter here has no counterpart"
    thesis_params = {param for pair in pairs for param in pair.thesis}
    modules_there = (algo.latent, algo.actor, algo.critic, algo.critic_target, algo.cos_network, algo.cos_network_target)
    modules_there += (algo.safety_critic, algo.safety_critic_target)
    assert thesis_params == {algo.log_alpha, *(p for module in modules_there for p in module.parameters())}
    return pairs


def to_our_names(pairs: list[Pair], names: dict[th.Tensor, str], values: dict[th.Tensor, th.Tensor]) -> dict[str, th.Tensor]:
    """The thesis code's tensors ``values`` (by its parameters) as ours, by our names, where all of a pair's are given."""
    return {
        names[pair.ours]: pair.from_thesis([values[param] for param in pair.thesis])
        for pair in pairs
        if all(param in values for param in pair.thesis)
    }


class ThesisCode:
    """
    The thesis code imported from a checkout of tsmir/ds-slac.

    :param directory: the checkout (holding ``dsslac/algo.py`` and ``configuration.py``)
    """

    def __init__(self, directory: Path) -> None:
        if not (directory / "dsslac" / "algo.py").is_file():
            raise SystemExit(f"error: {directory} is not a checkout of tsmir/ds-slac (no dsslac/algo.py)")
        if os.environ.get("PYTORCH_JIT") != "0":
            raise SystemExit("error: the thesis code's TorchScript modules run as Python only with PYTORCH_JIT=0")
        if importlib.util.find_spec("scipy") is None:  # imported by algo.py, not used
            scipy = types.ModuleType("scipy")
            scipy.stats = types.ModuleType("scipy.stats")  # type: ignore[attr-defined]
            sys.modules.update({"scipy": scipy, "scipy.stats": scipy.stats})  # type: ignore[attr-defined]
        sys.path.insert(0, str(directory))
        self.algo_module = importlib.import_module("dsslac.algo")
        self.configuration = importlib.import_module("configuration").get_default_config()
        head = subprocess.run(["git", "-C", str(directory), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        self.commit = head.stdout.strip() if head.returncode == 0 else "commit unknown: not a git checkout"

    def build(self, model: DSSLAC, setup: Setup, seed: int = 0) -> Any:
        """
        The thesis code's ``DSSLACAlgorithm`` at the setup's shapes: from its ``configuration.py`` for the thesis setup,
        else from ``model``'s values; the batch sizes and the start multiplier are ours.
        """
        policy = model.policy
        if setup.thesis_configuration:
            config = self.configuration
            keywords = {key: config[key] for key in ("num_sequences", "gamma_c", "feature_dim", "z2_dim", "hidden_units")}
            keywords.update({key: config[key] for key in ("lr_sac", "lr_latent", "start_alpha", "grad_clip_norm", "tau")})
            keywords.update(image_noise=config["image_noise"], risk_level=config["risk_level"])
            action_repeat = config["action_repeat"]
        else:
            keywords = dict(
                num_sequences=model.sequence_length,
                gamma=model.gamma,
                gamma_c=model.cost_gamma,
                feature_dim=policy.feature_dim,
                z1_dim=policy.z1_dim,
                z2_dim=policy.z2_dim,
                hidden_units=policy.hidden_units,
                lr_sac=model.learning_rate,
                lr_latent=model.latent_learning_rate,
                start_alpha=float(model.log_ent_coef.detach().exp()),
                grad_clip_norm=model.max_grad_norm,
                tau=model.tau,
                image_noise=policy.image_noise,
                risk_level=model.cvar_risk_level,
            )
            action_repeat = ACTION_REPEAT
        return self.algo_module.DSSLACAlgorithm(
            state_shape=model.observation_space.shape,
            action_shape=model.action_space.shape,
            action_repeat=action_repeat,
            device=th.device("cpu"),
            seed=seed,
            buffer_size=1,
            batch_size_sac=setup.batch_size,
            batch_size_latent=setup.latent_batch_size,
            start_lagrange=model.lagrange_multiplier,
            **keywords,
        )

    def run(self, algo: Any, latent_batch: SequenceBatch, batch: SequenceBatch, actor_noise: list[th.Tensor]) -> dict:
        """
        ``update_latent`` and ``update_sac`` on the two batches, then ``update_lag`` after an agent step of cost
        ``STEP_COST``.

        :return: the record by the thesis code's own tensors: ``values`` (as ``run_ours``'s record, the gradients as
            its optimizers got them, the multiplier's step from its gradient), ``before``/``grads``/``after`` (each
            optimizer step's parameters and gradients) and ``polyak_before``/``polyak_source``/``polyak_after``
        """
        record: Record = {}
        captured: dict[str, dict[th.Tensor, th.Tensor]] = {key: {} for key in ("before", "grads", "after")}
        captured.update({key: {} for key in ("polyak_before", "polyak_source")})
        optimizers = [algo.optim_latent, algo.optim_actor, algo.optim_critic, algo.optim_safety_critic]
        optimizers += [algo.optim_cos_network, algo.optim_alpha]

        def pre_step(optimizer: th.optim.Optimizer, args: tuple, kwargs: dict) -> None:
            for param in optimizer.param_groups[0]["params"]:
                captured["before"][param] = param.detach().clone()
                captured["grads"][param] = param.grad.detach().clone()

        def post_step(optimizer: th.optim.Optimizer, args: tuple, kwargs: dict) -> None:
            for param in optimizer.param_groups[0]["params"]:
                captured["after"][param] = param.detach().clone()

        def lagrange_step(optimizer: th.optim.Optimizer, args: tuple, kwargs: dict) -> None:
            learning_rate = optimizer.param_groups[0]["lr"]
            record["multiplier/step"] = -learning_rate * algo.raw_lag.grad.double().reshape(())

        soft_update = self.algo_module.soft_update

        def recording_soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
            for target_param, source_param in zip(target.parameters(), source.parameters(), strict=True):
                captured["polyak_before"][target_param] = target_param.detach().clone()
                captured["polyak_source"][source_param] = source_param.detach().clone()
            soft_update(target, source, tau)

        calculate_loss = algo.latent.calculate_loss

        def recording_calculate_loss(*args: th.Tensor) -> tuple[th.Tensor, ...]:
            terms = calculate_loss(*args)
            for key, term in zip(("kl", "image", "reward", "cost"), terms, strict=True):
                record[f"latent/{key}"] = term.detach().clone()
            return terms

        def keep_quantiles(module: nn.Module, args: tuple, output: th.Tensor) -> None:
            record["target/quantiles"] = output.detach().reshape(output.shape[0], -1).clone()

        handles = _record_inputs(record, algo.critic, algo.critic_target)
        handles.append(algo.safety_critic_target.register_forward_hook(keep_quantiles))
        handles += [optimizer.register_step_pre_hook(pre_step) for optimizer in optimizers]
        handles += [optimizer.register_step_post_hook(post_step) for optimizer in optimizers]
        handles.append(algo.optim_lagrange.register_step_pre_hook(lagrange_step))
        algo.latent.calculate_loss = recording_calculate_loss
        algo.buffer.sample_latent = lambda size: thesis_batch(latent_batch)
        algo.buffer.sample_sac = lambda size: thesis_batch(batch, last=True)
        self.algo_module.soft_update = recording_soft_update
        writer = ScalarWriter()
        algo.learning_steps_sac = 999  # the thesis code writes its losses when the step count reaches a multiple of 1000

        def grid_taus(batch_size: int, n: int, n_hat: int, device: Any, risk_level: float = 1.0) -> tuple[th.Tensor, ...]:
            return quantile_grid(batch_size, n, risk_level), quantile_grid(batch_size, n_hat, risk_level)

        try:
            with fixed_draws(algo.action_shape[0], actor_noise, [(self.algo_module, "generate_taus", grid_taus)]):
                algo.update_latent(writer)
                algo.update_sac(writer)
            algo.lastcost = STEP_COST
            algo.update_lag(0, writer)
        finally:
            self.algo_module.soft_update = soft_update
            del algo.latent.calculate_loss
            for handle in handles:
                handle.remove()
        for key, tag in (("critic", "loss/critic"), ("cost_critic", "loss/safety_critic"), ("actor", "loss/actor")):
            record[f"loss/{key}"] = th.tensor(writer.scalars[tag])
        record["loss/ent_coef"] = th.tensor(writer.scalars["loss/alpha"])
        captured["polyak_after"] = self.replay_polyak(algo, captured)
        return {"values": record, **captured}

    def replay_polyak(self, algo: Any, captured: dict[str, dict[th.Tensor, th.Tensor]]) -> dict[th.Tensor, th.Tensor]:
        """
        The thesis code's ``soft_update`` of each target network replayed in float64 from the parameters it had (in
        float32 the update, about 1e-6 per weight, is a few hundred ulps of the weight): the new target values by the
        thesis code's target parameters.
        """
        after = {}
        networks = [(algo.critic_target, algo.critic), (algo.safety_critic_target, algo.safety_critic)]
        networks.append((algo.cos_network_target, algo.cos_network))
        for target, source in networks:
            target_copy, source_copy = copy.deepcopy(target).double(), copy.deepcopy(source).double()
            with th.no_grad():
                for param, original in zip(target_copy.parameters(), target.parameters(), strict=True):
                    param.copy_(captured["polyak_before"][original])
                for param, original in zip(source_copy.parameters(), source.parameters(), strict=True):
                    param.copy_(captured["polyak_source"][original])
            self.algo_module.soft_update(target_copy, source_copy, algo.tau)
            for param, original in zip(target_copy.parameters(), target.parameters(), strict=True):
                after[original] = param.detach().clone()
        return after


class ScalarWriter:
    """Stands in for the thesis code's TensorBoard writer: keeps the last value of each tag."""

    def __init__(self) -> None:
        self.scalars: dict[str, float] = {}

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        self.scalars[tag] = value


def thesis_batch(batch: SequenceBatch, last: bool = False) -> tuple[th.Tensor, ...]:
    """
    A batch as the thesis code's buffer samples it: frames scaled to [0, 1], rewards, terminations and costs (B, L, 1),
    or with ``last`` those of the last transition (B, 1).
    """
    columns = [field.unsqueeze(-1) for field in (batch.rewards, batch.terminated, batch.costs)]
    if last:
        columns = [column[:, -1] for column in columns]
    return (batch.observations.float().div(255.0), batch.actions, *columns)


@dataclass
class Row:
    """One compared component: the thesis code's value, ours (scalars, else their L2 norm) and the error."""

    section: str
    component: str
    thesis: float
    ours: float
    error: float
    norm: bool = False


def _error(ours: th.Tensor, reference: th.Tensor) -> float:
    ours, reference = ours.double().flatten(), reference.double().flatten()
    return float((ours - reference).norm() / reference.norm().clamp_min(1e-30))


def _flat(values: dict[str, th.Tensor], names: list[str]) -> th.Tensor:
    return th.cat([values[name].double().flatten() for name in names])


def module_of(name: str) -> str:
    """A parameter's module as the table groups them: ``latent.encoder``, ``cost_critic.cosine_net``, ``actor`` ..."""
    parts = name.split(".")
    return ".".join(parts[:2]) if parts[0] in ("latent", "cost_critic") else parts[0]


COMPONENTS = {
    "latent/kl": ("latent model", "KL term"),
    "latent/image": ("latent model", "image term"),
    "latent/reward": ("latent model", "reward term"),
    "latent/cost": ("latent model", "cost term"),
    "critic_input/z": ("critics' inputs and targets", "z_t fed to the critics"),
    "critic_input/a": ("critics' inputs and targets", "a_t fed to the critics"),
    "target_input/z": ("critics' inputs and targets", "z_t+1 fed to the target critics"),
    "target_input/a": ("critics' inputs and targets", "a' ~ pi(z_t+1) fed to the target critics"),
    "target/q": ("critics' inputs and targets", "target critics' Q1, Q2 (z_t+1, a')"),
    "target/quantiles": ("critics' inputs and targets", "target IQN's quantiles (z_t+1, a')"),
    "loss/critic": ("losses", "reward critic"),
    "loss/cost_critic": ("losses", "IQN cost critic"),
    "loss/actor": ("losses", "actor"),
    "loss/ent_coef": ("losses", "entropy coefficient"),
}


def compare(model: DSSLAC, pairs: list[Pair], ours: Record, thesis: dict) -> list[Row]:
    """
    Every component of the two updates, and the Adam and Polyak steps replayed here on the thesis code's gradients and
    parameters (``model``'s optimizers and target critics are used for the replay and left changed).
    """
    names = parameter_names(model)
    reference = thesis["values"]
    rows = []
    for key, (section, component) in COMPONENTS.items():
        norm = ours[key].numel() > 1
        value = (lambda tensor: float(tensor.double().norm())) if norm else (lambda tensor: float(tensor))
        rows.append(Row(section, component, value(reference[key]), value(ours[key]), _error(ours[key], reference[key]), norm))

    thesis_grads = to_our_names(pairs, names, thesis["grads"])
    our_grads = {key.removeprefix("grad/"): value for key, value in ours.items() if key.startswith("grad/")}
    assert set(thesis_grads) == set(our_grads), set(thesis_grads) ^ set(our_grads)
    by_module: dict[str, list[str]] = {}
    for name in our_grads:
        by_module.setdefault(module_of(name), []).append(name)
    for module, members in by_module.items():
        theirs, mine = _flat(thesis_grads, members), _flat(our_grads, members)
        rows.append(Row("clipped gradients", module, float(theirs.norm()), float(mine.norm()), _error(mine, theirs), True))

    before, after = to_our_names(pairs, names, thesis["before"]), to_our_names(pairs, names, thesis["after"])
    optimizers = {"latent model": model.policy.latent_optimizer, "actor": model.policy.actor_optimizer}
    optimizers.update({"reward critic": model.policy.critic_optimizer, "IQN cost critic": model.policy.cost_critic_optimizer})
    optimizers["entropy coefficient"] = model.ent_coef_optimizer
    for label, optimizer in optimizers.items():
        members = [names[param] for param in optimizer.param_groups[0]["params"]]
        replayed = replay_adam(optimizer, [before[name] for name in members], [thesis_grads[name] for name in members])
        their_step = _flat(after, members) - _flat(before, members)
        our_step = th.cat([value.double().flatten() for value in replayed]) - _flat(before, members)
        row = Row("Adam steps, replayed", label, float(their_step.norm()), float(our_step.norm()), 0.0, True)
        row.error = float((our_step - their_step).norm() / their_step.norm())
        rows.append(row)

    polyak = {key: to_our_names(pairs, names, thesis[key]) for key in ("polyak_before", "polyak_source", "polyak_after")}
    step = model.updates.step
    # update_targets on float64 copies, as the thesis code's soft_update is replayed (``ThesisCode.replay_polyak``)
    targets = [polyak["polyak_before"][names[param]].double().clone() for param in step.target_params]
    sources = [polyak["polyak_source"][names[param]].double().clone() for param in step.source_params]
    GradientStep.update_targets(types.SimpleNamespace(target_params=targets, source_params=sources, config=step.config))
    replayed = {names[param]: value for param, value in zip(step.target_params, targets, strict=True)}
    for label, prefix in (("reward critic's target", "critic_target."), ("IQN's target", "cost_critic_target.")):
        members = [name for name in replayed if name.startswith(prefix)]
        start = _flat(polyak["polyak_before"], members)
        their_step, our_step = _flat(polyak["polyak_after"], members) - start, _flat(replayed, members) - start
        error = float((our_step - their_step).norm() / their_step.norm())
        rows.append(
            Row("Polyak updates, replayed in float64", label, float(their_step.norm()), float(our_step.norm()), error, True)
        )

    their_step, our_step = float(reference["multiplier/step"]), float(ours["multiplier/step"])
    error = abs(our_step / their_step - 1.0)
    rows.append(Row("multiplier", f"SGD step of its raw parameter (step cost {STEP_COST:g})", their_step, our_step, error))
    return rows


def replay_adam(optimizer: th.optim.Optimizer, values: list[th.Tensor], grads: list[th.Tensor]) -> list[th.Tensor]:
    """The parameters after a first step of a fresh optimizer like ``optimizer`` from ``values`` with ``grads``."""
    params = [nn.Parameter(value.clone()) for value in values]
    settings = {key: value for key, value in optimizer.param_groups[0].items() if key != "params"}
    adam_step(type(optimizer)(params, **settings), [grad.clone() for grad in grads])
    return [param.detach() for param in params]


def fingerprint(values: Record) -> dict[str, float]:
    """
    The numbers of an update that the drift test compares: the latent loss terms and the other losses, the L2 norms of
    the latents and actions fed to the critics and of the targets' outputs, the multiplier's step and the L2 norm of
    each parameter's clipped gradient (``grad/<name>``).
    """
    numbers = {key: float(values[key].double().norm()) for key in COMPONENTS if values[key].numel() > 1}
    numbers.update({key: float(values[key]) for key in COMPONENTS if values[key].numel() == 1})
    numbers["multiplier/step"] = float(values["multiplier/step"])
    numbers.update({key: float(value.double().norm()) for key, value in values.items() if key.startswith("grad/")})
    return numbers


def prepare(thesis: ThesisCode, setup: Setup, weights: str) -> tuple[DSSLAC, Any, list[Pair]]:
    """
    Both sides, built at the setup's shapes with the same weights, entropy coefficient and multiplier.

    :param weights: "thesis" (the thesis code's initial weights, copied here) or "fixed" (``fixed_weights``, copied there)
    """
    model = build_model(setup)
    algo = thesis.build(model, setup)
    pairs = parameter_pairs(model, algo)
    with th.no_grad():
        if weights == "fixed":
            fixed_weights(model)
            for pair in pairs:
                for param, value in zip(pair.thesis, pair.to_thesis(pair.ours.detach()), strict=True):
                    param.copy_(value)
        else:
            for pair in pairs:
                pair.ours.copy_(pair.from_thesis([param.detach() for param in pair.thesis]))
        algo.alpha = algo.log_alpha.exp()
        algo.raw_lag.copy_(model.lagrange_raw)
        algo.lagrange = th.nn.functional.softplus(algo.raw_lag)
    return model, algo, pairs


def run_both(
    thesis: ThesisCode,
    setup: Setup,
    weights: str = "thesis",
    ours_noise: list[th.Tensor] | None = None,
    thesis_noise: list[th.Tensor] | None = None,
    saturate: bool = False,
) -> tuple[list[Row], dict]:
    """
    One update on each side and their comparison.

    :param ours_noise: the actor's normal draws here, in the order drawn (None: zero); ``thesis_noise`` the thesis
        code's (its three: a' of the reward target, a' of the cost target, a of the actor loss)
    :param saturate: push the actor's pre-tanh means to ``SATURATED_MEAN`` (its last layer's mean biases, both sides)
    :return: the rows of ``compare`` and the thesis code's components as ``run_ours`` records ours
    """
    model, algo, pairs = prepare(thesis, setup, weights)
    if saturate:
        action_dim = model.policy.action_dim
        with th.no_grad():
            for output_layer in (_layers(model.policy.actor)[-1], _layers(algo.actor)[-1]):
                output_layer.weight[:action_dim].zero_()
                output_layer.bias[:action_dim].fill_(SATURATED_MEAN)
    latent_batch, batch = fixed_batches(model, setup)
    thesis_record = thesis.run(algo, latent_batch, batch, thesis_noise or [])
    ours = run_ours(model, latent_batch, batch, ours_noise or [])
    thesis_grads = to_our_names(pairs, parameter_names(model), thesis_record["grads"])
    thesis_values = {**thesis_record["values"], **{f"grad/{name}": grad for name, grad in thesis_grads.items()}}
    return compare(model, pairs, ours, thesis_record), thesis_values


def print_tables(title: str, rows: list[Row]) -> None:
    """One markdown table per section, then the summary line."""
    print(f"### {title}\n")
    sections = list(dict.fromkeys(row.section for row in rows))
    for section in sections:
        print(f"| {section} | thesis code | here | relative error |\n|---|---:|---:|---:|")
        for row in (row for row in rows if row.section == section):
            norm = "norm " if row.norm else ""
            print(f"| {row.component} | {norm}{row.thesis:.6g} | {norm}{row.ours:.6g} | {row.error:.1e} |")
        print()
    print(summary(title, rows) + "\n")


def summary(title: str, rows: list[Row]) -> str:
    """``<title>: k of n components equal within 1e-4 relative (largest: ...)``."""
    worst = max(rows, key=lambda row: row.error)
    equal = sum(row.error <= TOLERANCE for row in rows)
    tolerance = f"{TOLERANCE:.0e}".replace("e-0", "e-")
    return (
        f"**{title}: {equal} of {len(rows)} components equal within {tolerance} relative** "
        f"(largest error {worst.error:.1e}: {worst.section}, {worst.component})"
    )


def departures(thesis: ThesisCode) -> None:
    """The runs that bring out each departure, and the components each moves."""
    generator = th.Generator().manual_seed(1)
    n, action_dim = THESIS.batch_size, 2
    first, second, actor = (th.randn(n, action_dim, generator=generator) for _ in range(3))
    runs = [
        ("log pi's tanh correction", f"actor means at {SATURATED_MEAN:g} (tanh saturated), noise zero", {"saturate": True}),
        (
            "one a' for both TD targets",
            "actor noise nonzero, the thesis code's second a' from the same noise as its first",
            {"ours_noise": [first, actor], "thesis_noise": [first, first, actor]},
        ),
        (
            "one a' for both TD targets",
            "actor noise nonzero, the thesis code's second a' from its own noise",
            {"ours_noise": [first, actor], "thesis_noise": [first, second, actor]},
        ),
    ]
    print("### The departures, each brought out by a run (thesis shapes, the rest as above)\n")
    print("| departure | run | components apart by more than 1e-4 (relative error) |\n|---|---|---|")
    for departure, how, keywords in runs:
        rows, _ = run_both(thesis, THESIS, **keywords)
        apart = [f"{row.section}: {row.component} ({row.error:.1e})" for row in rows if row.error > TOLERANCE]
        print(f"| {departure} | {how} | {'; '.join(apart) or f'none: {len(rows)} of {len(rows)} equal'} |")
    print()


def write_fixture(thesis: ThesisCode, path: Path) -> None:
    """Run the thesis shapes from ``fixed_weights`` and write the thesis code's ``fingerprint`` to ``path``."""
    rows, values = run_both(thesis, THESIS, weights="fixed")
    print_tables("thesis preset, thesis shapes, from fixed_weights (the drift test's fixture)", rows)
    if any(row.error > TOLERANCE for row in rows):
        raise SystemExit("error: the update differs from the thesis code's: no fixture written")
    data = {
        "about": "The thesis code's numbers for one update of the thesis preset's shapes from fixed_weights on "
        "fixed_batches (benchmarks/tools/reference_parity.py --write-fixture); tests/test_thesis_drift.py compares ours",
        "thesis_commit": thesis.commit,
        "torch": th.__version__,
        "numbers": fingerprint(values),
    }
    path.write_text(json.dumps(data, indent=1) + "\n")
    print(f"Wrote {len(data['numbers'])} numbers to {path.relative_to(REPO)}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--ref-dir", type=Path, required=True, help="a checkout of tsmir/ds-slac")
    parser.add_argument("--write-fixture", action="store_true", help=f"also write {FIXTURE.name} for the drift test")
    args = parser.parse_args(argv)
    if os.environ.get("PYTORCH_JIT") != "0":  # read when torch is imported: start again with it
        os.execve(sys.executable, [sys.executable, *sys.argv], {**os.environ, "PYTORCH_JIT": "0"})
    th.set_num_threads(1)
    thesis = ThesisCode(args.ref_dir.resolve())
    print(f"## Our update beside the thesis code's (tsmir/ds-slac {thesis.commit})\n")
    command = "python benchmarks/tools/reference_parity.py --ref-dir DIR" + (" --write-fixture" if args.write_fixture else "")
    print(f"`{command}`: torch {th.__version__}, {cpu_model()}, one thread, eager float32\n")
    failed = False
    for title, setup in (("thesis preset, thesis shapes", THESIS), ("cpu preset's shapes (IQN at the thesis code's)", CPU)):
        rows, _ = run_both(thesis, setup)
        print_tables(title, rows)
        failed |= any(row.error > TOLERANCE for row in rows)
    departures(thesis)
    if args.write_fixture:
        write_fixture(thesis, FIXTURE)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
