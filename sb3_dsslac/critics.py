"""Reward critic (twin Q) and distributional cost critic (IQN) on the latent state z."""

import math
from functools import partial

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sb3_dsslac.latent import build_mlp, init_weights


class TwinQCritic(nn.Module):
    """
    Two independent Q-networks ``Q(z, a)``, each an MLP with LeakyReLU(0.2).

    :param z_dim: latent size
    :param action_dim: action size
    :param hidden_units: hidden layers of each Q-network
    """

    def __init__(self, z_dim: int, action_dim: int, hidden_units: tuple[int, ...] = (256, 256)) -> None:
        super().__init__()
        activation = partial(nn.LeakyReLU, 0.2)
        self.q1 = build_mlp(z_dim + action_dim, 1, hidden_units, activation)
        self.q2 = build_mlp(z_dim + action_dim, 1, hidden_units, activation)
        init_weights(self)

    def forward(self, z: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        """Latents (B, Z) and actions (B, A) -> Q-values of both networks, each (B, 1)."""
        x = torch.cat([z, actions], dim=-1)
        return self.q1(x), self.q2(x)


class IQNCostCritic(nn.Module):
    """
    Implicit quantile network of the discounted cost return, ``Z_tau(z, a)``.

    The quantile fraction is embedded as ``ReLU(Linear(cos(pi * i * tau)))``, i = 1..n_cosines, multiplied elementwise
    with the raw ``[z, a]`` and mapped to one quantile by ``Linear -> ReLU -> Linear`` (no output activation).

    :param z_dim: latent size
    :param action_dim: action size
    :param n_cosines: number of cosine features of tau
    :param hidden_dim: hidden width of the quantile head
    """

    def __init__(self, z_dim: int, action_dim: int, n_cosines: int = 64, hidden_dim: int = 512) -> None:
        super().__init__()
        input_dim = z_dim + action_dim
        self.register_buffer("cosine_frequencies", math.pi * torch.arange(1, n_cosines + 1, dtype=torch.float32))
        self.cosine_net = nn.Linear(n_cosines, input_dim)
        self.quantile_net = build_mlp(input_dim, 1, (hidden_dim,), nn.ReLU)
        init_weights(self)

    def forward(self, z: Tensor, actions: Tensor, taus: Tensor) -> Tensor:
        """Latents (B, Z), actions (B, A) and quantile fractions (B, N) in [0, 1] -> quantiles (B, N)."""
        tau_embedding = F.relu(self.cosine_net(torch.cos(taus.unsqueeze(-1) * self.cosine_frequencies)))  # (B, N, Z+A)
        x = torch.cat([z, actions], dim=-1).unsqueeze(1)  # (B, 1, Z+A)
        return self.quantile_net(x * tau_embedding).squeeze(-1)


def sample_taus(batch_size: int, n_quantiles: int, device: torch.device | str, risk_level: float = 1.0) -> Tensor:
    """
    Quantile fractions ``tau ~ U(1 - risk_level, 1)`` of shape (batch_size, n_quantiles).

    ``risk_level = 1`` gives U(0, 1) (risk-neutral mean); smaller values average the upper tail (CVaR of the cost).
    """
    if not 0.0 < risk_level <= 1.0:
        raise ValueError(f"risk_level must be in (0, 1], got {risk_level}")
    return 1.0 - risk_level + risk_level * torch.rand(batch_size, n_quantiles, device=device)


def quantile_huber_loss(current_quantiles: Tensor, target_quantiles: Tensor, taus: Tensor, kappa: float = 1.0) -> Tensor:
    """
    Quantile regression Huber loss of IQN.

    With ``delta_ij = target_j - current_i`` (B, N, N'), the loss is
    ``|tau_i - 1{delta_ij < 0}| * Huber_kappa(delta_ij) / kappa``, summed over i and averaged over j and the batch.

    :param current_quantiles: (B, N) quantiles at ``taus``
    :param target_quantiles: (B, N') target samples (detached by the caller)
    :param taus: (B, N) quantile fractions of ``current_quantiles``
    :param kappa: Huber threshold (> 0)
    :return: scalar loss
    """
    if current_quantiles.shape != taus.shape or target_quantiles.shape[0] != current_quantiles.shape[0]:
        raise ValueError(
            f"expected current (B, N) = taus (B, N) and target (B, N'), got {tuple(current_quantiles.shape)}, "
            f"{tuple(taus.shape)} and {tuple(target_quantiles.shape)}"
        )
    delta = target_quantiles.unsqueeze(1) - current_quantiles.unsqueeze(2)  # (B, N, N')
    huber = F.huber_loss(delta, torch.zeros_like(delta), reduction="none", delta=kappa)
    weight = (taus.unsqueeze(2) - (delta.detach() < 0).to(delta.dtype)).abs()
    return (weight * huber / kappa).sum(dim=1).mean()


class MeanCostCritic(nn.Module):
    """
    Safe SLAC's expectation critic of the discounted cost return, ``Q_c(z, a)``: an MLP with LeakyReLU(0.2) hidden
    layers and a LeakyReLU(0.01) output (costs are non-negative), its output bias starting at ``initial_value``.

    It answers every quantile fraction with the same expectation, so it plugs in where ``IQNCostCritic`` does.

    :param z_dim: latent size
    :param action_dim: action size
    :param hidden_units: hidden layers
    :param initial_value: initial output bias, e.g. the discounted per-episode budget (9.184 in Safe SLAC)
    """

    def __init__(
        self, z_dim: int, action_dim: int, hidden_units: tuple[int, ...] = (256, 256), initial_value: float = 0.0
    ) -> None:
        super().__init__()
        self.q = build_mlp(z_dim + action_dim, 1, hidden_units, partial(nn.LeakyReLU, 0.2), partial(nn.LeakyReLU, 0.01))
        init_weights(self)
        output_layer = self.q[-2]
        assert isinstance(output_layer, nn.Linear)
        nn.init.constant_(output_layer.bias, initial_value)

    def forward(self, z: Tensor, actions: Tensor, taus: Tensor) -> Tensor:
        """Latents (B, Z), actions (B, A), fractions (B, N) -> the expected cost return repeated N times, (B, N)."""
        return self.q(torch.cat([z, actions], dim=-1)).expand(-1, taus.shape[1])
