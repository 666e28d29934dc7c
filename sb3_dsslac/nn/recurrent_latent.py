"""
The latent model with a deterministic recurrent z2, as in an RSSM (PlaNet, Dreamer): ``z2_{t+1} = GRU(z2_t, [z1_{t+1},
a_t])`` in place of SLAC's Gaussian ``p(z2_{t+1} | z1_{t+1}, z2_t, a_t)``.

In SLAC every step draws z2 afresh from a Gaussian, so what a frame showed is diluted by new noise at each step; a
pixel agent's belief was measured to be a function of its last 2-4 frames
(``benchmarks/tools/diagnostics/filter_memory.py``). A gated deterministic state can hold what left the view for as
long as its update gate keeps it; ``benchmarks/goal_memory.py`` measures how much of the goal's bearing it holds.
z1 keeps its prior, posterior and KL, so the loss, the filter and the actor-critic's inputs are ``LatentModel``'s; z2
lies in (-1, 1).
"""

from typing import Any

import torch
from torch import Tensor, nn

from sb3_dsslac.nn.latent import LatentModel, build_mlp, init_weights


class GRUTransition(nn.Module):
    """
    Deterministic ``z2_{t+1} = GRUCell(ELU(Linear([z1_{t+1}, a_t])), z2_t)`` with the Gaussian interface of the z2
    transition it replaces: ``forward(z1, z2_prev, action) -> (z2, zero std)``, each (..., z2_dim).
    """

    def __init__(self, z1_dim: int, z2_dim: int, action_dim: int, input_units: int) -> None:
        super().__init__()
        self.inputs = build_mlp(z1_dim + action_dim, input_units, (), nn.ELU, nn.ELU)
        self.cell = nn.GRUCell(input_units, z2_dim)

    def forward(self, z1: Tensor, z2_prev: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
        """z1 (..., Z1), z2_prev (..., Z2), action (..., A) -> z2 (..., Z2) and its std, zero (..., Z2)."""
        inputs = self.inputs(torch.cat([z1, action], dim=-1))
        if z2_prev.dim() > 2:  # rows through the cell: a GRU cell takes 1-D or 2-D inputs only
            z2 = self.cell(inputs.reshape(-1, inputs.shape[-1]), z2_prev.reshape(-1, z2_prev.shape[-1])).view_as(z2_prev)
        else:
            z2 = self.cell(inputs, z2_prev)
        return z2, torch.zeros_like(z2)


class DeterministicInit(nn.Module):
    """The first z2 from the first z1, ``tanh(MLP(z1_0))`` in (-1, 1) as the GRU's states: ``z1 -> (z2, zero std)``."""

    def __init__(self, z1_dim: int, z2_dim: int, hidden_units: tuple[int, ...]) -> None:
        super().__init__()
        self.net = build_mlp(z1_dim, z2_dim, hidden_units, nn.ELU, nn.Tanh)

    def forward(self, z1: Tensor) -> tuple[Tensor, Tensor]:
        """z1 (N, Z1) -> z2 (N, Z2) and its std, zero (N, Z2)."""
        z2 = self.net(z1)
        return z2, torch.zeros_like(z2)


class RecurrentLatentModel(LatentModel):
    """
    ``LatentModel`` (same keywords) whose z2 is a deterministic GRU state: ``z2_init`` and ``z2_transition`` are
    ``DeterministicInit`` and ``GRUTransition``; the rollout runs step by step (the fused rollout is written for
    Gaussian MLPs). The GRU's input layer is ``hidden_units[0]`` wide.
    """

    uses_fused_rollout = False

    def __init__(self, observation_shape: tuple[int, ...], action_dim: int, **kwargs: Any) -> None:
        super().__init__(observation_shape, action_dim, **kwargs)
        self.z2_init = DeterministicInit(self.z1_dim, self.z2_dim, self.hidden_units)
        self.z2_transition = GRUTransition(self.z1_dim, self.z2_dim, action_dim, self.hidden_units[0])
        init_weights(self.z2_init)
        init_weights(self.z2_transition.inputs)  # the GRU cell keeps torch's uniform init
