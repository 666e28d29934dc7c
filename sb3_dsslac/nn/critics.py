"""Reward critic (twin Q) and distributional cost critic (IQN) on the latent state z; the IQN loss is sb3-contrib's."""

import itertools
import math
from functools import partial

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sb3_dsslac.nn.latent import build_mlp, init_weights


class TwinQCritic(nn.Module):
    """
    Two independent Q-networks ``Q(z, a)``, each an MLP with LeakyReLU(0.2), evaluated together: layer ``k`` of both
    networks is one batched matrix product with weights (2, in, out), so the pair costs the ops of one network.

    State dicts of the earlier layout (two ``nn.Sequential`` named ``q1`` and ``q2``) load into this one.

    :param z_dim: latent size
    :param action_dim: action size
    :param hidden_units: hidden layers of each Q-network
    """

    n_critics = 2

    def __init__(self, z_dim: int, action_dim: int, hidden_units: tuple[int, ...] = (256, 256)) -> None:
        super().__init__()
        sizes = (z_dim + action_dim, *hidden_units, 1)
        self.weights = nn.ParameterList(
            nn.Parameter(torch.empty(self.n_critics, d_in, d_out)) for d_in, d_out in itertools.pairwise(sizes)
        )
        self.biases = nn.ParameterList(nn.Parameter(torch.zeros(self.n_critics, 1, d_out)) for d_out in sizes[1:])
        for weight in self.weights:
            # Xavier-uniform (gain 1) per network, as ``init_weights`` does for a Linear layer
            bound = math.sqrt(6.0 / (weight.shape[1] + weight.shape[2]))
            nn.init.uniform_(weight, -bound, bound)
        self._register_load_state_dict_pre_hook(self._load_two_sequentials)

    def forward(self, z: Tensor, actions: Tensor) -> Tensor:
        """
        Latents (B, Z) and actions (B, A) -> the Q-values of both networks stacked, (2, B, 1): ``q1, q2 = critic(z, a)``
        unpacks them.
        """
        x = torch.cat([z, actions], dim=-1)
        h = x.unsqueeze(0).expand(self.n_critics, *x.shape)
        last = len(self.weights) - 1
        for k, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            h = torch.baddbmm(bias, h, weight)
            if k < last:
                h = F.leaky_relu(h, 0.2)
        return h

    @staticmethod
    def _load_two_sequentials(state_dict: dict[str, Tensor], prefix: str, *_args: object) -> None:
        """Rewrite ``q1.<2k>.weight`` (out, in) / ``q1.<2k>.bias`` of the earlier layout into the stacked tensors."""
        layer = 0
        while f"{prefix}q1.{2 * layer}.weight" in state_dict:
            keys = [f"{prefix}q{i}.{2 * layer}" for i in (1, 2)]
            weights = [state_dict.pop(f"{key}.weight") for key in keys]
            biases = [state_dict.pop(f"{key}.bias") for key in keys]
            state_dict[f"{prefix}weights.{layer}"] = torch.stack([w.t() for w in weights])
            state_dict[f"{prefix}biases.{layer}"] = torch.stack(biases).unsqueeze(1)
            layer += 1


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
        batch, n_taus = taus.shape
        # (B * N) rows through the layers: a linear layer on (B, N, .) adds two views each way
        tau_embedding = F.relu(self.cosine_net(torch.cos(taus.reshape(-1, 1) * self.cosine_frequencies)))
        x = torch.cat([z, actions], dim=-1).unsqueeze(1)  # (B, 1, Z+A)
        rows = (x * tau_embedding.view(batch, n_taus, -1)).view(batch * n_taus, -1)
        return self.quantile_net(rows).view(batch, n_taus)


def sample_taus(batch_size: int, n_quantiles: int, device: torch.device | str, risk_level: float = 1.0) -> Tensor:
    """
    Quantile fractions ``tau ~ U(1 - risk_level, 1)`` of shape (batch_size, n_quantiles).

    ``risk_level = 1`` gives U(0, 1) (risk-neutral mean); smaller values average the upper tail (CVaR of the cost).
    """
    if not 0.0 < risk_level <= 1.0:
        raise ValueError(f"risk_level must be in (0, 1], got {risk_level}")
    uniform = torch.rand(batch_size, n_quantiles, device=device)
    return uniform if risk_level == 1.0 else 1.0 - risk_level + risk_level * uniform


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
