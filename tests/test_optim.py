import pytest
import torch

from sb3_dsslac.engine.dispatch import DispatchCounter
from sb3_dsslac.nn.optim import adam_step, clip_grads


@pytest.mark.parametrize("max_norm", [0.5, 3.0, 100.0])
def test_clip_grads_scales_as_clip_grad_norm(max_norm) -> None:
    torch.manual_seed(0)
    params = [torch.nn.Parameter(torch.randn(4, 3)), torch.nn.Parameter(torch.randn(5))]
    grads = [torch.randn_like(param) for param in params]
    for param, grad in zip(params, grads, strict=True):
        param.grad = grad.clone()
    norm = torch.nn.utils.clip_grad_norm_(params, max_norm)
    clipped = clip_grads(grads, max_norm)
    for param, clipped_grad in zip(params, clipped, strict=True):
        torch.testing.assert_close(clipped_grad, param.grad)
    assert (norm > max_norm) == any(not torch.equal(a, b) for a, b in zip(clipped, grads, strict=True))


@pytest.mark.parametrize("optimizer_class", [torch.optim.Adam, torch.optim.AdamW])
def test_eager_fused_adam_step_is_the_optimizer_step_without_its_profiler_ranges(optimizer_class) -> None:
    torch.manual_seed(0)
    params = [torch.nn.Parameter(torch.randn(4, 3)), torch.nn.Parameter(torch.randn(5))]
    copies = [torch.nn.Parameter(param.detach().clone()) for param in params]
    optimizer = optimizer_class(params, lr=1e-2, weight_decay=0.1, fused=True)
    reference = optimizer_class(copies, lr=1e-2, weight_decay=0.1, fused=True)
    for step in range(3):
        grads = [torch.randn_like(param) for param in params]
        with DispatchCounter() as counter:
            adam_step(optimizer, grads)
        for copy, grad in zip(copies, grads, strict=True):
            copy.grad = grad.clone()
        reference.step()
        assert step == 0 or counter.ops == 2  # after the state's creation: the step counters' add and the fused kernel
    for param, copy in zip(params, copies, strict=True):
        torch.testing.assert_close(param, copy)
    for state, reference_state in zip(optimizer.state.values(), reference.state.values(), strict=True):
        for key in ("step", "exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(state[key], reference_state[key])


def test_eager_adam_step_gives_each_gradient_its_parameters_strides() -> None:
    # A channels-last weight with a gradient in the default layout, and a matrix with a transposed gradient: CUDA's
    # fused Adam refuses both (it ran on an H200 only once the strides matched)
    params = [
        torch.nn.Parameter(torch.randn(8, 3, 5, 5).to(memory_format=torch.channels_last)),
        torch.nn.Parameter(torch.randn(4, 6)),
    ]
    grads = [torch.randn(8, 3, 5, 5), torch.randn(6, 4).t()]
    copies = [torch.nn.Parameter(param.detach().clone()) for param in params]
    optimizer = torch.optim.Adam(params, lr=1e-2, fused=True)
    reference = torch.optim.Adam(copies, lr=1e-2)
    adam_step(optimizer, grads)
    for copy, grad in zip(copies, grads, strict=True):
        copy.grad = grad.clone()
    reference.step()
    for param, copy, grad in zip(params, copies, grads, strict=True):
        assert param.grad.stride() == param.stride()
        torch.testing.assert_close(param.grad, grad)
        torch.testing.assert_close(param, copy)
