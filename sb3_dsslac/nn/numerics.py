"""
The numerics of DS-SLAC's training: TF32 while learning on CUDA, bfloat16 autocast of the latent model where the
device computes it natively, and the guards that stop training at a NaN or inf loss (noted on the device during a burst
of updates) or action.
"""

import contextlib
import warnings
from collections.abc import Iterator

import numpy as np
import torch as th


@contextlib.contextmanager
def float32_precision(precision: str) -> Iterator[None]:
    """
    CUDA float32 matrix products and cuDNN convolutions at ``precision`` ("tf32" or "ieee") inside the block, through
    ``fp32_precision``, the switches torch wants now (once a caller set them, torch raises on a read of the legacy
    ``allow_tf32``). They are process-wide: the previous values come back when the block ends, also on an error.
    """
    switches = (th.backends.cuda.matmul, th.backends.cudnn.conv)
    previous = [switch.fp32_precision for switch in switches]
    for switch in switches:
        switch.fp32_precision = precision
    try:
        yield
    finally:
        for switch, value in zip(switches, previous, strict=True):
            switch.fp32_precision = value


def tf32_matmul(enabled: bool) -> contextlib.AbstractContextManager:
    """TF32 for CUDA float32 matrix products and cuDNN convolutions inside the block when ``enabled``; else nothing."""
    return float32_precision("tf32") if enabled else contextlib.nullcontext()


def has_native_bf16(device: th.device) -> bool:
    """
    Whether ``device`` computes bfloat16 natively: a CUDA GPU of compute capability 8.0 or newer (Ampere on; older ones
    emulate it, which ``torch.cuda.is_bf16_supported()`` counts), asked of that GPU, not the current one; a CPU with
    AVX512-BF16 or AMX.
    """
    if device.type == "cuda":
        return th.cuda.get_device_capability(device) >= (8, 0)
    if device.type == "cpu":
        return th.cpu._is_avx512_bf16_supported() or th.cpu._is_amx_tile_supported()
    return False


def resolve_bf16(bf16: bool | str, device: th.device) -> bool:
    """
    Whether the latent model's passes run under bfloat16 autocast: ``"auto"`` where the device computes bfloat16
    natively; ``True`` too, with a warning and float32 instead where it does not (emulated bfloat16 made the update
    7x slower on an AVX2-only CPU); ``False`` never.
    """
    if bf16 not in (True, False, "auto"):
        raise ValueError(f"bf16 must be True, False or 'auto', got {bf16!r}")
    if bf16 is False:
        return False
    native = has_native_bf16(device)
    if bf16 is True and not native:
        warnings.warn(
            f"bf16=True, but this {device.type} has no native bfloat16 (no AVX512-BF16 or AMX on a CPU), where it is "
            "several times slower than float32: the latent model stays in float32. Pass bf16='auto' to choose silently."
        )
    return native


def autocast_enabled(device_type: str) -> bool:
    """Whether autocast is on for ``device_type`` ("cpu", "cuda"); False for a device without autocast ("meta")."""
    return th.amp.is_autocast_available(device_type) and th.is_autocast_enabled(device_type)


def bf16_autocast(enabled: bool, device: th.device) -> contextlib.AbstractContextManager:
    """bfloat16 autocast on ``device`` when ``enabled`` (the resolved ``bf16``), else nothing."""
    if enabled:
        return th.autocast(device.type, dtype=th.bfloat16)
    return contextlib.nullcontext()


# Losses checked for NaN/inf on the device during a burst, in the order an update computes them
GUARDED_LOSSES = ("latent_loss", "critic_loss", "cost_critic_loss", "actor_loss", "ent_coef_loss")


class NonFiniteGuard:
    """
    Notes on the device, without reading it, the first update of a burst in which each of ``GUARDED_LOSSES`` is NaN or
    inf; the burst reads the notes once, at its end, with its statistics (``raise_if_noted``).

    :param device: the device of the updates
    """

    def __init__(self, device: th.device) -> None:
        # The first update of the burst with a non-finite value of each guarded loss (-1: none yet)
        self.first_nonfinite_update = th.full((len(GUARDED_LOSSES),), -1, dtype=th.long, device=device)
        self.update_index = th.zeros((), dtype=th.long, device=device)  # updates of the burst so far
        # How many steps before their own each guarded loss is computed when the updates are pipelined
        lags = [0 if name == "latent_loss" else 1 for name in GUARDED_LOSSES]
        self.pipelined_lags = th.tensor(lags, dtype=th.long, device=device)

    def reset(self) -> None:
        """Clear the notes and the update count, at the start of a burst."""
        self.first_nonfinite_update.fill_(-1)
        self.update_index.zero_()

    def record(self, losses: dict[str, th.Tensor], pipelined: bool = False) -> None:
        """
        Note which guarded losses of ``losses`` (detached scalars; the guarded ones present must be a run of
        ``GUARDED_LOSSES``) are NaN or inf in the current update: one check for all of them.

        :param pipelined: the actor-critic losses belong to the step before the current one (``GradientStep.full_step``)
        """
        names = [name for name in GUARDED_LOSSES if name in losses]
        start = GUARDED_LOSSES.index(names[0])
        assert tuple(names) == GUARDED_LOSSES[start : start + len(names)], names
        first = self.first_nonfinite_update[start : start + len(names)]
        values = th.stack([losses[name] for name in names])
        not_finite = th.isnan(values) | th.isinf(values)  # three ops where ~isfinite dispatches five
        update = self.update_index
        if pipelined:
            update = update - self.pipelined_lags[start : start + len(names)]
        th.where((first < 0) & not_finite, update, first, out=first)  # in place: no copy

    def next_update(self) -> None:
        """Count one update of the burst."""
        self.update_index.add_(1)

    @staticmethod
    def raise_if_noted(first_nonfinite: np.ndarray, n_updates: int, timestep: int) -> None:
        """
        Stop training, naming the loss and the update, when a burst noted a NaN or inf loss.

        :param first_nonfinite: the notes read on the host (``first_nonfinite_update``)
        :param n_updates: the updates before the burst
        :param timestep: the agent step of the burst
        """
        # The earliest update, and in it the first loss computed (the others follow from it)
        bad = [(int(update), index) for index, update in enumerate(first_nonfinite) if update >= 0]
        if bad:
            update, index = min(bad)
            raise RuntimeError(
                f"DS-SLAC's {GUARDED_LOSSES[index]} became NaN or inf at update {n_updates + update} (timestep {timestep}); "
                "training stopped at the end of that burst of updates, so the weights may hold NaN: go back to the last "
                "checkpoint. Check the env's observations, rewards and costs for NaN/inf, or lower the learning rates."
            )


def raise_if_action_not_finite(action: np.ndarray, timestep: int, n_updates: int) -> None:
    """
    Stop training when an action of the training envs is NaN or inf: weights that overflowed in the last burst's final
    update, or finite weights whose filter overflows on a real frame (either way no later loss would be computed
    before the env rejects the action).

    :param action: the actions scaled to [-1, 1] (n_envs, action_dim)
    :param timestep: the agent step
    :param n_updates: the updates so far
    """
    if not np.isfinite(action).all():
        raise RuntimeError(
            f"DS-SLAC's action became NaN or inf at timestep {timestep} (after update {n_updates}): "
            "the latent filter or the actor overflowed, so the weights may hold NaN or huge values: go back to the "
            "last checkpoint. Check train/kl and train/image_loss for a spike, or lower latent_learning_rate."
        )
