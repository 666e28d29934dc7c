"""
Bursts of DS-SLAC's gradient steps: the steps of a burst on windows sampled at once, pipelined (each actor-critic batch
updated on in the step after its own), compiled with ``compile_updates`` (falling back to eager where that fails), one
host read per burst; and the latent model's pre-training, in the same bursts.
"""

import contextlib
import warnings
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.logger import Logger
from tqdm.auto import tqdm

from sb3_dsslac.common.buffers import SequenceBatch, SequenceReplayBuffer
from sb3_dsslac.common.timing import TimeAccount
from sb3_dsslac.engine.gradient_step import GradientStep
from sb3_dsslac.nn.numerics import GUARDED_LOSSES, NonFiniteGuard
from sb3_dsslac.nn.optim import init_adam_state

# Latent pre-training updates whose windows are drawn at once
PRETRAIN_BURST = 100


# The extremes among the logged statistics, by suffix: their reduction over bursts (over a burst's updates, the least or
# the most; the others are means)
EXTREMES: dict[str, Callable[[float, float], float]] = {"_min": min, "_max": max}


def _extreme(name: str) -> Callable[[float, float], float] | None:
    """The reduction over bursts of a ``*_min`` or ``*_max`` statistic; None for the others, which are means."""
    return next((reduction for suffix, reduction in EXTREMES.items() if name.endswith(suffix)), None)


def record_burst(logger: Logger, stats: dict[str, float]) -> None:
    """
    Log a burst's statistics as ``train/<key>``. The logger writes every few episodes, many bursts apart: a mean is
    the last burst's, a ``*_min`` or ``*_max`` the extreme over every burst since the last write, so no spike of the
    latent model goes unlogged.
    """
    logged = logger.name_to_value
    for key, value in stats.items():
        name = f"train/{key}"
        extreme = _extreme(key)
        logger.record(name, value if extreme is None or name not in logged else extreme(value, logged[name]))


def split_windows(batch: SequenceBatch, n_first: int) -> tuple[SequenceBatch, SequenceBatch]:
    """The first ``n_first`` windows of ``batch`` and the others: one view op per field (two slices take two)."""
    parts = [(None, None) if field is None else field.split([n_first, field.shape[0] - n_first]) for field in batch]
    return SequenceBatch(*(first for first, _ in parts)), SequenceBatch(*(rest for _, rest in parts))


def compiles_backward() -> bool:
    """
    Whether this torch compiles a whole gradient step, backward pass included: 2.13 or newer (a pre-release or local
    build such as NVIDIA's "2.13.0a0+..." counts). torch 2.11 has the option, but its inductor fails on the traced
    backward (an AssertionError after minutes, on an H200 at ``cpu_pixels32_bounded`` sizes).
    """
    release = tuple(int(part) for part in th.__version__.split(".")[:2])
    return release >= (2, 13) and hasattr(th._dynamo.config, "trace_autograd_ops")


class UpdateBursts:
    """
    Runs the gradient steps of ``step`` in bursts: ``train`` after each rollout, ``pretrain_latent`` once after the
    warm-up.

    :param step: the gradient step and its device state
    :param lagrange_raw: the multiplier's raw parameter, a float64 tensor on the host whatever the device (the training
        envs' steps read and move it there), filled into the device's copy at the start of a burst and, for the
        "critic" rule (which moves it on the device), read back with the burst's statistics at its end
    :param compile_updates: ``torch.compile`` the gradient steps as whole graphs (CUDA graphs on a GPU)
    :param time_account: where the first call of a compiled step counts its time, as ``compilation``
    """

    def __init__(self, step: GradientStep, lagrange_raw: th.Tensor, compile_updates: bool, time_account: TimeAccount) -> None:
        self.step = step
        self.lagrange_raw = lagrange_raw
        self.time_account = time_account
        self.compiled_steps: dict[str, Callable[..., dict[str, th.Tensor]]] = {}
        self._compiled_once: set[str] = set()
        if compile_updates:
            self._compile()

    def _compile(self) -> None:
        """Fill ``compiled_steps`` with the compiled ``full_step`` and ``last_actor_critic_step``, where torch can."""
        if not compiles_backward():
            warnings.warn(
                f"compile_updates needs a torch whose compiler traces the backward pass (2.13 or newer), this is "
                f"{th.__version__}: the updates run eagerly"
            )
            return
        # CUDA graphs on a GPU: the whole step is replayed as one graph. On a CPU the tensors keep the layouts that
        # eager mode found fastest: inductor's own choice, channels-last convolutions, transposed the 3-channel frames
        # and reconstructions on every step (28.5 against 25.7 updates/s at cpu_pixels32 sizes, one thread, AMD EPYC)
        if self.step.device.type == "cuda":
            options: dict[str, Any] = {"mode": "reduce-overhead"}
        else:
            options = {"options": {"layout_optimization": False}}
        self.compiled_steps = {
            step.__name__: th.compile(step, fullgraph=True, **options)
            for step in (self.step.full_step, self.step.last_actor_critic_step)
        }

    def train(
        self,
        replay_buffer: SequenceReplayBuffer,
        gradient_steps: int,
        batch_size: int,
        lagrange_learning_rate: float,
        n_updates: int,
        timestep: int,
    ) -> dict[str, float]:
        """
        One burst of ``gradient_steps`` updates on freshly sampled windows.

        :param replay_buffer: the buffer to sample from
        :param gradient_steps: the updates of the burst
        :param batch_size: sequences per actor-critic update
        :param lagrange_learning_rate: the multiplier's SGD step size now (for the "critic" rule)
        :param n_updates: the updates before this burst, and ``timestep`` the agent step: where a NaN error says it was
        :return: the burst's statistics (see ``end_burst``)
        """
        step = self.step
        if step.config.share_latent_batch:
            windows_per_update = max(step.config.latent_batch_size, batch_size)
        else:
            windows_per_update = step.config.latent_batch_size + batch_size
        indices = replay_buffer.sample_indices(gradient_steps, windows_per_update)
        history = self.burst(replay_buffer, indices, lagrange_learning_rate)
        return self.end_burst(history, n_updates, timestep)

    def pretrain_latent(
        self,
        replay_buffer: SequenceReplayBuffer,
        latent_updates: int,
        lagrange_learning_rate: float,
        n_updates: int,
        timestep: int,
        progress_bar: bool = False,
    ) -> float | None:
        """
        The one-off latent-model pre-training of Algorithm 1: ``latent_updates`` latent-model updates, eager, in bursts
        of ``PRETRAIN_BURST``.

        :param replay_buffer: the buffer of the random-policy data
        :param latent_updates: the latent-model updates
        :param lagrange_learning_rate: the multiplier's SGD step size now
        :param n_updates: the updates so far, and ``timestep`` the agent step: where a NaN error says it was
        :param progress_bar: show a progress bar
        :return: the mean latent loss of the last burst, read with its statistics: of the last ``PRETRAIN_BURST``
            updates, or of all of them where there are fewer (None without updates)
        """
        loss = None
        progress = tqdm(total=latent_updates, desc="latent pre-training", disable=not progress_bar)
        for done in range(0, latent_updates, PRETRAIN_BURST):
            count = min(PRETRAIN_BURST, latent_updates - done)
            indices = replay_buffer.sample_indices(count, self.step.config.latent_batch_size)
            history = self.burst(replay_buffer, indices, lagrange_learning_rate, latent_only=True)
            loss = self.end_burst(history, n_updates, timestep)["latent_loss"]
            progress.update(count)
        progress.close()
        return loss

    def burst(
        self, replay_buffer: SequenceReplayBuffer, indices: th.Tensor, lagrange_learning_rate: float, latent_only: bool = False
    ) -> dict[str, list[th.Tensor]]:
        """
        The gradient steps on the windows ``indices[k]`` (from ``sample_indices``), each actor-critic batch updated on in
        the step after its own (``GradientStep.full_step``) and the last one after them; with ``latent_only`` (the
        pre-training), latent-model updates alone, eager.

        :return: the steps' statistics by name, in order
        """
        self.begin_burst(lagrange_learning_rate)
        pipelined = not (latent_only or self.step.config.share_latent_batch)
        history: dict[str, list[th.Tensor]] = defaultdict(list)
        waiting = None
        for step_indices in indices.unbind(0):
            batch = replay_buffer.gather(step_indices)
            if latent_only:
                stats = self.step.latent_step(batch)
            elif pipelined:  # the step's latent batch now, its actor-critic batch in the next step
                latent_batch, next_waiting = split_windows(batch, self.step.config.latent_batch_size)
                stats = self.run_step(self.step.full_step, latent_batch, waiting)
                waiting = next_waiting
            else:
                stats = self.run_step(self.step.full_step, batch, None)
            for key, value in stats.items():
                history[key].append(value)
        if waiting is not None:
            for key, value in self.run_step(self.step.last_actor_critic_step, waiting).items():
                history[key].append(value)
        return history

    def run_step(self, step: Callable[..., dict[str, th.Tensor]], *args: Any) -> dict[str, th.Tensor]:
        """
        ``step(*args)`` (``full_step`` or ``last_actor_critic_step``), compiled with ``compile_updates`` (falling back to
        eager, with a warning, if that fails).
        """
        compiled = self.compiled_steps.get(step.__name__)
        if compiled is None:
            return step(*args)
        # The first call compiles (a minute or more on a CPU): its time is the compilation's
        first_call = self.time_account.measure("compilation") if step.__name__ not in self._compiled_once else None
        try:
            with th._dynamo.config.patch(trace_autograd_ops=True), first_call or contextlib.nullcontext():
                if self.step.device.type != "cuda":
                    return compiled(*args)
                # A CUDA graph's replay reuses its output memory: keep copies of this step's statistics
                th.compiler.cudagraph_mark_step_begin()
                return {key: value.clone() for key, value in compiled(*args).items()}
        except Exception as error:  # the compiler's errors have no common base class
            if step.__name__ in self._compiled_once:
                raise
            warnings.warn(f"compile_updates: the update could not be compiled ({type(error).__name__}: {error}); runs eagerly")
            self.compiled_steps = {}
            return step(*args)
        finally:
            self._compiled_once.add(step.__name__)

    def begin_burst(self, lagrange_learning_rate: float) -> None:
        """
        Bring the device copies of the step sizes and the multiplier up to date and clear the NaN notes: the steps read
        no Python value that changes during training, so a compiled step never recompiles for one. Each is a fill from
        a host value, no copy from host memory (which would wait for the device). Compiled, every optimizer gets its
        state now, and the step's device state is marked static, so that a CUDA graph holds and writes it in place.
        """
        step = self.step
        for optimizer, learning_rate in step.learning_rates.items():
            learning_rate.fill_(optimizer.param_groups[0]["lr"])
        if self.compiled_steps:
            for optimizer in step.optimizers:
                init_adam_state(optimizer)
            for tensor in step.device_state():  # after a load_state_dict the optimizers hold new tensors: every burst
                th._dynamo.mark_static_address(tensor)
        step.lagrange_raw.fill_(self.lagrange_raw)
        step.lagrange_learning_rate.fill_(lagrange_learning_rate)
        step.guard.reset()

    def end_burst(self, history: dict[str, list[th.Tensor]], n_updates: int, timestep: int) -> dict[str, float]:
        """
        The one host read of a burst: the mean of each logged statistic (the smallest of a ``*_min`` one, the largest of
        a ``*_max`` one) and the largest KL of an update (``kl_max``), the NaN notes and, for the "critic" rule, the
        multiplier. Raises if a loss became NaN or inf.

        Every statistic has one value per update, so the burst's values are one (statistics, updates) table, reduced
        row by row in three ops whatever the number of statistics.

        :param n_updates: the updates before this burst, and ``timestep`` the agent step: where a NaN error says it was
        """
        step = self.step
        names = list(history)
        lengths = {name: len(values) for name, values in history.items()}
        assert len(set(lengths.values())) == 1, lengths
        table = th.stack([value for values in history.values() for value in values]).float().view(len(names), -1)
        packed = th.cat(
            [
                table.mean(dim=1),
                table.amin(dim=1),
                table.amax(dim=1),
                step.guard.first_nonfinite_update.float(),
                step.lagrange_raw.view(1).float(),
            ]
        )
        values = packed.cpu().numpy().astype(np.float64)
        n_stats = len(names)
        means, smallest, largest = (values[k * n_stats : (k + 1) * n_stats] for k in range(3))
        NonFiniteGuard.raise_if_noted(values[3 * n_stats : 3 * n_stats + len(GUARDED_LOSSES)], n_updates, timestep)
        if step.config.critic_lagrange_budget is not None:
            self.lagrange_raw.fill_(values[-1])
        by_suffix = {"_min": smallest, "_max": largest}
        stats = {name: float(by_suffix.get(name[-4:], means)[k]) for k, name in enumerate(names)}
        if "kl" in names:  # a spike can last a single update: the burst's largest KL beside its mean
            stats["kl_max"] = float(largest[names.index("kl")])
        return stats
