"""The parameters of the latent model's diagonal Gaussians from an MLP's output: the std's floor and optional ceiling,
the mean's optional bound, and their derivatives for the hand-written rollout backward pass; the KL of two of them."""

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

STD_EPS = 1e-5  # the reference code's floor on the standard deviation
_SOFTPLUS_THRESHOLD = 20.0  # torch.nn.functional.softplus's default


@dataclass(frozen=True)
class GaussianBounds:
    """
    How a Gaussian's mean and std follow from the raw outputs ``(mean_raw, raw)`` of its MLP.

    Without a ceiling ``std = softplus(raw) + min_std`` (the reference code); with one
    ``std = min_std + (max_std - min_std) * sigmoid(raw)``. Without a bound ``mean = mean_raw``; with one
    ``mean = mean_bound * tanh(mean_raw / mean_bound)``, the identity near 0. Bounded means and stds keep every latent
    sample within ``mean_bound + max_std * |noise|``, so a step of the optimizer cannot send the latents (and the
    decoder's input) off to 1e7, and the KL between two such Gaussians stays below
    ``log(max_std / min_std) + (max_std^2 + 4 mean_bound^2) / (2 min_std^2)`` per dimension.

    :param min_std: the floor on the std (> 0)
    :param max_std: the ceiling on the std (> min_std); None: none
    :param mean_bound: the bound on |mean| (> 0); None: none
    """

    min_std: float = STD_EPS
    max_std: float | None = None
    mean_bound: float | None = None

    def __post_init__(self) -> None:
        if not self.min_std > 0.0:
            raise ValueError(f"min_std must be > 0, got {self.min_std}")
        if self.max_std is not None and not self.max_std > self.min_std:
            raise ValueError(f"max_std must be > min_std = {self.min_std} (or None), got {self.max_std}")
        if self.mean_bound is not None and not self.mean_bound > 0.0:
            raise ValueError(f"mean_bound must be > 0 (or None), got {self.mean_bound}")

    def __call__(self, mean_raw: Tensor, raw: Tensor) -> tuple[Tensor, Tensor]:
        """The mean and std (each as its input's shape) from the MLP's raw outputs."""
        mean = mean_raw if self.mean_bound is None else self.mean_bound * torch.tanh(mean_raw / self.mean_bound)
        if self.max_std is None:
            return mean, F.softplus(raw) + self.min_std
        return mean, torch.sigmoid(raw) * (self.max_std - self.min_std) + self.min_std

    def backward(self, grad_mean: Tensor, grad_std: Tensor, mean: Tensor, raw: Tensor) -> tuple[Tensor, Tensor]:
        """
        The gradients at ``mean_raw`` and ``raw`` from those at the mean and the std.

        :param mean: the mean that ``__call__`` returned
        :param raw: the raw std that went in
        """
        if self.mean_bound is not None:  # d/dx b tanh(x / b) = 1 - tanh^2 = 1 - (mean / b)^2
            grad_mean = grad_mean * (1.0 - (mean / self.mean_bound).square())
        if self.max_std is None:
            return grad_mean, torch.ops.aten.softplus_backward(grad_std, raw, 1.0, _SOFTPLUS_THRESHOLD)
        sigmoid = torch.sigmoid(raw)
        return grad_mean, grad_std * (self.max_std - self.min_std) * sigmoid * (1.0 - sigmoid)


def gaussian_kl(mean_q: Tensor, std_q: Tensor, mean_p: Tensor, std_p: Tensor) -> Tensor:
    """Elementwise analytic ``KL(N(mean_q, std_q^2) || N(mean_p, std_p^2))``, same shape as the (broadcast) inputs."""
    var_ratio = (std_q / std_p).pow(2)
    mean_term = ((mean_q - mean_p) / std_p).pow(2)
    return 0.5 * (var_ratio + mean_term - 1.0 - torch.log(var_ratio))
