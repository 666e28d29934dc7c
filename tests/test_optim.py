import pytest
import torch

from sb3_dsslac.optim import clip_grads


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
