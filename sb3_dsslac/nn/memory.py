"""A recurrent memory over the beliefs, for the actor and the critics (``LatentPolicy(actor_critic_memory=H)``)."""

import torch as th
from torch import nn


class BeliefMemory(nn.Module):
    """
    A GRU over the beliefs an agent acts on and the actions that led to them, ``h_t = GRUCell([z_t, a_{t-1}],
    h_{t-1})`` with ``h`` zero before an episode's first belief (or, in the update, a window's). The actor and the
    critics take ``[z_t, h_t]``; the reward critic's TD error trains it, so that it keeps what the return depends on
    and the belief has forgotten (where the goal went), as a recurrent model-free agent's history does.

    :param z_dim: size of the belief z = [z1, z2]
    :param action_dim: size of the actions (scaled to [-1, 1])
    :param memory_dim: size of the memory h
    """

    def __init__(self, z_dim: int, action_dim: int, memory_dim: int) -> None:
        super().__init__()
        self.memory_dim = memory_dim
        self.cell = nn.GRUCell(z_dim + action_dim, memory_dim)

    def forward(self, z: th.Tensor, action_prev: th.Tensor, memory: th.Tensor) -> th.Tensor:
        """
        One step: the memory after belief ``z`` (N, z_dim), reached by ``action_prev`` (N, action_dim), from the memory
        before it (N, memory_dim). Returns (N, memory_dim).
        """
        return self.cell(th.cat([z, action_prev], dim=-1), memory)

    def unroll(self, z: th.Tensor, action_prev: th.Tensor) -> th.Tensor:
        """
        The memory after each belief of windows of one episode each, from zero before their first.

        :param z: beliefs (B, T, z_dim)
        :param action_prev: the action that led to each belief (B, T, action_dim)
        :return: (B, T, memory_dim)
        """
        memory = z.new_zeros(z.shape[0], self.memory_dim)
        memories = []
        for step in range(z.shape[1]):
            memory = self(z[:, step], action_prev[:, step], memory)
            memories.append(memory)
        return th.stack(memories, dim=1)
