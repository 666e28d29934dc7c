"""
Gradient steps without host syncs: gradient-norm clipping on a list of gradients, and Adam steps that run eagerly
(the optimizer's fused kernel) or inside a ``torch.compile`` graph (the functional, capturable form on the same state).
"""

from typing import Any

import torch
from torch import Tensor
from torch.optim.adam import adam as functional_adam


def fast_adam_kwargs(optimizer_class: type[torch.optim.Optimizer], optimizer_kwargs: dict[str, Any]) -> dict[str, Any]:
    """
    ``optimizer_kwargs`` with ``fused=True`` added for Adam and AdamW unless the caller chose ``fused`` or ``foreach``:
    one kernel per parameter group instead of about ten per parameter (on CPUs and GPUs alike).
    """
    if issubclass(optimizer_class, torch.optim.Adam | torch.optim.AdamW) and not {"fused", "foreach"} & set(optimizer_kwargs):
        return {**optimizer_kwargs, "fused": True}
    return dict(optimizer_kwargs)


def clip_grads(grads: list[Tensor], max_norm: float) -> list[Tensor]:
    """
    ``grads`` scaled so that their joint L2 norm is at most ``max_norm``, as ``clip_grad_norm_`` does for ``.grad``,
    in a fixed handful of ops and without reading the norm on the host.
    """
    total_norm = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads)))
    # Divided by max((norm + 1e-6) / max_norm, 1): clip_grad_norm_'s factor min(max_norm / (norm + 1e-6), 1) in one op less
    return list(torch._foreach_div(grads, total_norm.add_(1e-6).div_(max_norm).clamp_(min=1.0)))


def init_adam_state(optimizer: torch.optim.Optimizer) -> None:
    """Create Adam's state (step, first and second moments) of every parameter that has none yet, as ``step`` would."""
    for group in optimizer.param_groups:
        for param in group["params"]:
            state = optimizer.state[param]
            if len(state) == 0:
                state["step"] = torch.zeros((), dtype=torch.float32, device=param.device)
                state["exp_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.preserve_format)
                if group["amsgrad"]:
                    state["max_exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.preserve_format)


def adam_step(optimizer: torch.optim.Optimizer, grads: list[Tensor], learning_rate: Tensor | None = None) -> None:
    """
    One Adam step of the optimizer's single parameter group with ``grads`` (in the order of its parameters).

    Eagerly, the gradients become ``.grad``, each in its parameter's strides as ``backward`` would store it (the
    gradients of ``torch.autograd.grad`` keep the layout their kernel chose, and CUDA's fused kernel refuses a gradient
    whose strides are not its parameter's); a fused Adam then runs its kernel directly, the arithmetic of
    ``optimizer.step()`` without its profiler ranges and hooks (two ops per step), and any other optimizer steps.
    While ``torch.compile`` traces, it is the functional capturable Adam on the optimizer's own state tensors instead
    (the optimizer's ``step`` breaks a graph), with the step size read from ``learning_rate`` (a 0-d tensor on the
    parameters' device), so that a new step size needs no recompilation. Call ``init_adam_state`` before tracing.
    """
    (group,) = optimizer.param_groups
    params: list[Tensor] = group["params"]
    compiling = torch.compiler.is_compiling()
    if not compiling:
        grads = [
            grad if grad.stride() == param.stride() else torch.empty_like(param).copy_(grad)
            for param, grad in zip(params, grads, strict=True)
        ]
        for param, grad in zip(params, grads, strict=True):
            param.grad = grad
        if not (isinstance(optimizer, torch.optim.Adam) and group["fused"]):
            optimizer.step()
            return
        init_adam_state(optimizer)
    states = [optimizer.state[param] for param in params]
    beta1, beta2 = group["betas"]
    with torch.no_grad():
        functional_adam(
            params,
            grads,
            [state["exp_avg"] for state in states],
            [state["exp_avg_sq"] for state in states],
            [state["max_exp_avg_sq"] for state in states] if group["amsgrad"] else [],
            [state["step"] for state in states],
            foreach=compiling,
            capturable=compiling,
            differentiable=False,
            fused=not compiling,
            grad_scale=None,
            found_inf=None,
            has_complex=False,
            decoupled_weight_decay=group.get("decoupled_weight_decay", False),
            amsgrad=group["amsgrad"],
            beta1=beta1,
            beta2=beta2,
            lr=group["lr"] if learning_rate is None or not compiling else learning_rate,
            weight_decay=group["weight_decay"],
            eps=group["eps"],
            maximize=group["maximize"],
        )
