"""
Latent overshooting (PlaNet, Hafner et al. 2019, section 4): the KL of z1's posterior to its prior rolled open-loop
several steps, so that the belief must hold what the frames of those steps will show.

SLAC's KL compares z1's posterior only with its one-step prior ``p(z1_{t+1} | z2_t, a_t)``, and the reconstruction
needs what the current frame shows: nothing asks the belief to keep what left the view (a pixel agent's belief held
the goal's bearing for 3-8 steps, ``benchmarks/goal_memory.py``). Rolled open-loop from ``z2_t`` over the actions, the
prior of ``z1_{t+d}`` can match the posterior of a frame in which the goal comes back only if ``z2_t`` knew where it
went.

The rolled states can also carry the reward decoder (``LatentModel``'s ``reward_overshooting_weight``; PlaNet trains
its reward on overshooting too): the reward of every step, not only of the rare frame in which the goal comes back,
depends on where the goal is, so predicting it several steps without frames asks ``z2_t`` for the goal's bearing at
each of them.
"""

import torch
from torch import Tensor, nn

from sb3_dsslac.nn.gaussian import gaussian_kl


def overshooting_roll(
    z1_prior: nn.Module,
    z2_transition: nn.Module,
    z2: Tensor,
    actions: Tensor,
    posterior_mean: Tensor,
    posterior_std: Tensor,
    depth: int,
    z1: Tensor | None = None,
    stride: int = 1,
) -> tuple[Tensor, list[Tensor]]:
    """
    Mean over ``d = 2 .. depth`` of ``KL(sg(q(z1_{t+d})) || p_d(z1_{t+d} | z2_t, a_t .. a_{t+d-1}))``, each summed over
    the window's starts ``t = 0, s, 2s, ..`` (stride ``s``) and z1, mean over the batch: the prior is rolled ``d`` steps
    from the posterior's ``z2_t`` with sampled z1s (z2's transition sampled too where it is a Gaussian) and the
    posterior is held fixed, as in PlaNet.

    :param z1_prior: ``p(z1_{t+1} | z2_t, a_t)``, ``(z2, action) -> (mean, std)``
    :param z2_transition: ``(z1_{t+1}, z2_t, a_t) -> (mean, std)`` of z2 (a GRU's std is zero)
    :param z2: (B, T+1, Z2) the posterior rollout's z2 (with gradient: it learns to hold what the prior needs)
    :param actions: (B, T, A)
    :param posterior_mean: (B, T+1, Z1) z1's posterior means
    :param posterior_std: (B, T+1, Z1) z1's posterior stds
    :param depth: the longest open-loop roll, 2 <= depth <= T
    :param z1: (B, T+1, Z1) the posterior rollout's z1 samples to also return the rolled transitions (one more sampled
        step after the KL's draws), or None
    :param stride: roll from every ``stride``-th start only. A roll's cost grows with its rows, about depth x starts: at
        depth 16 over windows of 20, stride 2 rolls 104 rows where every start rolls 200 (8-step rolls from every
        start: 132), as far. Measured in one run beside two learning runs, the update with the reward on such rolls
        costs 1.82x ``cpu_pixels32_pid``'s, with 8-step rolls from every start 1.67x; 1.43x with the cores to itself
        (``benchmarks/results/overshooting_speed.md``)
    :return: the scalar term, and with ``z1`` the rolled transitions of ``d = 1 .. depth``: ``[z_{t+d-1}, a_{t+d-1},
        z_{t+d}]`` (B, starts, 2 (Z1 + Z2) + A) with ``z = [z1, z2]`` rolled open-loop from the posterior's ``z_t`` (itself
        at d = 1), for every start t = 0, s, .. <= T-d; without ``z1`` an empty list
    """
    steps = actions.shape[1]
    if not 2 <= depth <= steps:
        raise ValueError(f"overshooting depth must be in [2, {steps}] (the window's transitions), got {depth}")
    if stride < 1:
        raise ValueError(f"overshooting stride must be at least 1 (1: a roll from every start), got {stride}")
    state = z2[:, :-1:stride]  # (B, starts, Z2): the roll from every start t = 0, s, .. <= T-1
    previous = None if z1 is None else torch.cat([z1[:, :-1:stride], state], dim=-1)  # z_{t+rolled} of every start
    terms, transitions = [], []
    for rolled in range(depth):
        starts = (steps - 1 - rolled) // stride + 1  # the starts whose roll stays inside the window
        state = state[:, :starts]
        action = actions[:, rolled : rolled + stride * starts : stride]
        prior_mean, prior_std = z1_prior(state, action)  # p(z1_{t+rolled+1} | ...), rolled steps open-loop
        if rolled >= 1:
            target = slice(rolled + 1, rolled + 1 + stride * starts, stride)
            kl = gaussian_kl(posterior_mean[:, target].detach(), posterior_std[:, target].detach(), prior_mean, prior_std)
            terms.append(kl.sum(dim=(1, 2)).mean())
        if rolled + 1 < depth or previous is not None:
            rolled_z1 = torch.addcmul(prior_mean, prior_std, torch.randn_like(prior_mean))
            z2_mean, z2_std = z2_transition(rolled_z1, state, action)
            state = torch.addcmul(z2_mean, z2_std, torch.randn_like(z2_mean))
            if previous is not None:
                current = torch.cat([rolled_z1, state], dim=-1)
                transitions.append(torch.cat([previous[:, :starts], action, current], dim=-1))
                previous = current
    return torch.stack(terms).mean(), transitions
