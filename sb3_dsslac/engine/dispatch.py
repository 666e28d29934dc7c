"""
Counting what a piece of PyTorch code dispatches: every ATen op (Python and dispatcher overhead on any device), the
view ops among them (``t``, ``view``, ``slice``...: new metadata on the same memory, no kernel on any device), so
that the others are the kernel launches on a GPU, and every host sync (a tensor's value read back to Python).

    with DispatchCounter(ignore_sync_of=optimizer_step_tensors(model)) as counter:
        model.train(gradient_steps=3, batch_size=model.batch_size)
    counter.ops / 3, counter.kernel_ops / 3, counter.syncs / 3, counter.top(8)
"""

from collections import Counter
from collections.abc import Iterable
from typing import Any

import torch as th
from torch.utils._python_dispatch import TorchDispatchMode

# ``.item()``, ``float(t)``, ``int(t)`` and ``bool(t)`` all read a tensor's value through this op
_SYNC_OP = th.ops.aten._local_scalar_dense


class DispatchCounter(TorchDispatchMode):
    """
    A context manager that counts the ATen ops dispatched inside it, by overload packet (``"aten.mm"``), the view ops
    among them (those whose schema says their output aliases an input: ``OpOverload.is_view``) and the host syncs
    (``aten._local_scalar_dense``). Counts add up over every ``with`` block of one counter; nested
    counters each count the ops of the inner block.

    Code compiled by ``torch.compile`` runs compiled inside it (the mode is off while Dynamo traces and Inductor
    compiles): the counts are what the compiled artifact dispatches at run time, not the ops it replaced.

    :param ignore_sync_of: tensors whose value reads are not counted as syncs (they still count as ops), e.g. the
        ``step`` tensors of non-capturable Adam optimizers: host tensors even on a GPU, so reading them waits for
        nothing. A read is left out when its tensor is one of these or shares its memory (a view of it)
    """

    def __init__(self, ignore_sync_of: Iterable[th.Tensor] = ()) -> None:
        super().__init__()
        ignored = list(ignore_sync_of)
        self._ignored_ids = {id(tensor) for tensor in ignored}
        self._ignored_ptrs = {tensor.data_ptr() for tensor in ignored if tensor.numel() > 0}
        self.op_counts: Counter[str] = Counter()
        self.view_ops = 0
        self.syncs = 0
        self.ignored_syncs = 0

    @classmethod
    def ignore_compile_internals(cls) -> bool:
        """Let ``torch.compile`` compile inside the counter (else Dynamo falls back to eager for every frame)."""
        return True

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        self.op_counts[str(func.overloadpacket)] += 1
        self.view_ops += func.is_view
        if func.overloadpacket is _SYNC_OP:
            if self._is_ignored(args[0]):
                self.ignored_syncs += 1
            else:
                self.syncs += 1
        return func(*args, **(kwargs or {}))

    def _is_ignored(self, tensor: th.Tensor) -> bool:
        return id(tensor) in self._ignored_ids or tensor.data_ptr() in self._ignored_ptrs

    @property
    def ops(self) -> int:
        """ATen ops dispatched in all, the syncs included."""
        return sum(self.op_counts.values())

    @property
    def kernel_ops(self) -> int:
        """The ops that are not views: each one launches at least one kernel on a GPU."""
        return self.ops - self.view_ops

    def top(self, n: int = 10) -> list[tuple[str, int]]:
        """The ``n`` most dispatched ops as ``(name, count)``, most first."""
        return self.op_counts.most_common(n)


def optimizer_step_tensors(model: Any) -> list[th.Tensor]:
    """
    The ``state["step"]`` tensors of every optimizer of a DSSLAC model: the attributes of ``model`` and
    ``model.policy`` whose name ends in ``optimizer`` (``policy.latent_optimizer``, ``actor_optimizer``,
    ``critic_optimizer``, ``cost_critic_optimizer``, ``model.ent_coef_optimizer`` if any). An optimizer has this state
    only once it has stepped, so call this after a first update.

    :param model: anything with optimizers as attributes, or a ``policy`` that has them
    :return: the step tensors, one per parameter with optimizer state
    """
    owners = [model, getattr(model, "policy", None)]
    optimizers = [
        value
        for owner in owners
        if owner is not None
        for name, value in sorted(vars(owner).items())
        if name.endswith("optimizer") and isinstance(getattr(value, "state", None), dict)
    ]
    return [
        state["step"]
        for optimizer in optimizers
        for state in optimizer.state.values()
        if isinstance(state.get("step"), th.Tensor)
    ]
