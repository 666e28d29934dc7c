"""Tanh-squashed Gaussian actor on the latent state z."""

import math
from functools import partial

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sb3_dsslac.nn.latent import build_mlp, init_weights

LOG_STD_MIN = -20.0
LOG_STD_MAX = 2.0
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


class LatentActor(nn.Module):
    """
    SAC actor ``pi(a | z)``: MLP with LeakyReLU(0.2) -> (mean, log_std), log_std clamped to [-20, 2], tanh squashing.

    :param z_dim: latent size
    :param action_dim: action size (actions in (-1, 1))
    :param hidden_units: hidden layers of the MLP
    """

    def __init__(self, z_dim: int, action_dim: int, hidden_units: tuple[int, ...] = (256, 256)) -> None:
        super().__init__()
        self.net = build_mlp(z_dim, 2 * action_dim, hidden_units, partial(nn.LeakyReLU, 0.2))
        init_weights(self)

    def _mean_log_std(self, z: Tensor) -> tuple[Tensor, Tensor]:
        mean, log_std = self.net(z).chunk(2, dim=-1)
        return mean, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX)

    def forward(self, z: Tensor, deterministic: bool = False) -> Tensor:
        """Latents (B, Z) -> actions (B, A) in (-1, 1): ``tanh(mean)`` if deterministic, else a tanh-Gaussian sample."""
        mean, log_std = self._mean_log_std(z)
        if deterministic:
            return torch.tanh(mean)
        return torch.tanh(torch.addcmul(mean, log_std.exp(), torch.randn_like(mean)))

    def action_log_prob(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """
        Reparameterised sample and its log-density.

        :param z: (B, Z) latents
        :return: actions (B, A) in (-1, 1) and ``log pi(a | z)`` (B,), including the tanh Jacobian correction
        """
        mean, log_std = self._mean_log_std(z)
        noise = torch.randn_like(mean)
        pre_tanh = torch.addcmul(mean, log_std.exp(), noise)
        gaussian_log_prob = -0.5 * noise.pow(2) - log_std - _HALF_LOG_2PI
        # log(1 - tanh(x)^2) = 2 * (log 2 - x - softplus(-2x))
        log_det = 2.0 * (math.log(2.0) - pre_tanh - F.softplus(-2.0 * pre_tanh))
        return torch.tanh(pre_tanh), (gaussian_log_prob - log_det).sum(dim=-1)
