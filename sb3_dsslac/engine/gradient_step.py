"""One gradient step of DS-SLAC (Algorithm 1) on the device: the latent-model update, the TD targets, the actor-critic
update and the Polyak update of the target critics, and the device state they read."""

from dataclasses import dataclass
from typing import NamedTuple

import torch as th
from sb3_contrib.common.utils import quantile_huber_loss
from torch.nn import functional as F

from sb3_dsslac.common.buffers import SequenceBatch
from sb3_dsslac.common.lagrange import sgd_lagrange_step_on_device
from sb3_dsslac.common.policies import LatentPolicy
from sb3_dsslac.nn.critics import IQNCostCritic, sample_taus
from sb3_dsslac.nn.latent import LatentStart
from sb3_dsslac.nn.numerics import NonFiniteGuard, bf16_autocast
from sb3_dsslac.nn.optim import adam_step, clip_grads


class Transitions(NamedTuple):
    """N transitions on the latent state, each a (N, ...) tensor: ``z``, ``a``, ``r`` and ``c`` (N, 1), ``terminated``
    (N, 1, 1.0 where the transition ended its episode by a true termination) and ``z'``."""

    latents: th.Tensor
    actions: th.Tensor
    rewards: th.Tensor
    costs: th.Tensor
    terminated: th.Tensor
    next_latents: th.Tensor


@dataclass(frozen=True)
class UpdateConfig:
    """
    The hyperparameters one gradient step reads, built by ``DSSLAC.update_config`` from the model's own.

    :param target_entropy: target entropy of the learned coefficient
    :param gamma: discount of the reward
    :param cost_gamma: discount of the cost
    :param tau: Polyak factor of the target critics
    :param batch_size: sequences per actor-critic update
    :param latent_batch_size: sequences per latent-model update
    :param actor_critic_transitions: transitions of each sequence, its last ones, that the actor-critic update learns
        from (1: the last one, as the thesis; ``sequence_length``: all of them, ``batch_size`` times as many samples)
    :param share_latent_batch: one sampled batch and one encoder pass per update (see ``full_step``)
    :param n_quantiles: quantile fractions sampled per update by the IQN critic and the actor
    :param cvar_risk_level: beta in (0, 1]: the actor's fractions are drawn from U(1 - beta, 1)
    :param max_grad_norm: gradient-norm clip of the latent model, the critics and the entropy coefficient
    :param actor_max_grad_norm: gradient-norm clip of the actor
    :param critic_lagrange_budget: with the "critic" multiplier rule, its budget (``DSSLAC.critic_cost_budget``): every
        actor-critic update moves the multiplier from the cost critic's estimate against it. None for the other rules
    :param bf16: run the latent model's passes under bfloat16 autocast (the resolved ``DSSLAC.bf16``)
    :param burn_in: frames before each window filtered without gradient (``DSSLAC.burn_in``; 0: none, the thesis's)
    """

    target_entropy: float
    gamma: float
    cost_gamma: float
    tau: float
    batch_size: int
    latent_batch_size: int
    actor_critic_transitions: int
    share_latent_batch: bool
    n_quantiles: int
    cvar_risk_level: float
    max_grad_norm: float
    actor_max_grad_norm: float
    critic_lagrange_budget: float | None
    bf16: bool
    burn_in: int


class GradientStep:
    """
    One gradient step of Algorithm 1, on the device and free of host syncs: a latent-model update, then an actor-critic
    update. It reads no Python value that changes during training: the step sizes, the Lagrange multiplier and the NaN
    notes are device tensors that the burst around the steps (``UpdateBursts``) brings up to date, so that a compiled
    step never recompiles for a new value.

    :param policy: the latent model, actor and critics, with their optimizers
    :param optimizers: every optimizer the step takes a step of: the policy's and the entropy coefficient's, if learned
    :param log_ent_coef: the log of the learned entropy coefficient (1,); None when it is fixed
    :param ent_coef_optimizer: the optimizer of ``log_ent_coef``; None when the coefficient is fixed
    :param ent_coef_tensor: the fixed entropy coefficient (scalar); None when it is learned
    :param config: the hyperparameters the step reads; ``DSSLAC.train`` replaces it when the model's values change
    :param device: the device of the policy
    """

    def __init__(
        self,
        policy: LatentPolicy,
        optimizers: list[th.optim.Optimizer],
        log_ent_coef: th.Tensor | None,
        ent_coef_optimizer: th.optim.Optimizer | None,
        ent_coef_tensor: th.Tensor | None,
        config: UpdateConfig,
        device: th.device,
    ) -> None:
        self.policy = policy
        self.optimizers = optimizers
        self.log_ent_coef = log_ent_coef
        self.ent_coef_optimizer = ent_coef_optimizer
        self.ent_coef_tensor = ent_coef_tensor
        self.config = config
        self.device = device
        # The device copies of the host values the step reads
        self.learning_rates = {optimizer: th.zeros((), device=device) for optimizer in optimizers}
        self.lagrange_raw = th.zeros((), device=device)
        # float64 like the host's step sizes: the SGD rules step with exactly the same value on the host and the device
        self.lagrange_learning_rate = th.zeros((), dtype=th.float64, device=device)
        self.guard = NonFiniteGuard(device)
        self.target_params = [*policy.critic_target.parameters(), *policy.cost_critic_target.parameters()]
        self.source_params = [*policy.critic.parameters(), *policy.cost_critic.parameters()]
        # The reference trains the IQN's cosine and quantile nets with two optimizers, each clipped at 40: clipped apart
        self.cost_critic_clip_groups: tuple[slice, ...] = (slice(None),)
        if isinstance(policy.cost_critic, IQNCostCritic):
            n_cosine = len(list(policy.cost_critic.cosine_net.parameters()))
            assert list(policy.cost_critic.parameters())[:n_cosine] == list(policy.cost_critic.cosine_net.parameters())
            self.cost_critic_clip_groups = (slice(0, n_cosine), slice(n_cosine, None))

    def device_state(self) -> list[th.Tensor]:
        """
        Every tensor the step reads or writes that is not a parameter or buffer of the policy's modules: the device
        copies of the step sizes and the multiplier, the NaN notes, the entropy coefficient and each optimizer's state
        (Adam's moments and step counts, once created). A step replayed as a CUDA graph holds them at fixed addresses
        (``UpdateBursts`` marks them static): the graph may then write them, and none is copied in at each replay.
        """
        guard = self.guard
        tensors = [*self.learning_rates.values(), self.lagrange_raw, self.lagrange_learning_rate]
        tensors += [guard.first_nonfinite_update, guard.update_index, guard.pipelined_lags]
        tensors += [tensor for tensor in (self.log_ent_coef, self.ent_coef_tensor) if tensor is not None]
        for optimizer in self.optimizers:
            tensors += [
                value for state in optimizer.state.values() for value in state.values() if isinstance(value, th.Tensor)
            ]
        return tensors

    def full_step(self, batch: SequenceBatch, waiting: SequenceBatch | None) -> dict[str, th.Tensor]:
        """
        One gradient step of Algorithm 1: a latent-model update, then an actor-critic update (``compile_updates``
        compiles this whole method).

        As in the reference code, the actor-critic batch is filtered by the latent model after the latent update of its
        step. That filtering runs in the rollout of the next step's latent update, one rollout over both batches: each
        step updates the actor and critics on the previous step's batch (``waiting``) and leaves its own for the next
        step, or for ``last_actor_critic_step`` at the end of the burst. The latent model and the actor-critic share no
        parameter, so this order computes the same updates with one rollout and first-frame pass fewer per step (the
        waiting batch is still encoded on its own, without gradient).

        :param batch: the step's latent batch, ``latent_batch_size`` windows (its actor-critic batch, sampled with it, waits
            in the burst), or with ``share_latent_batch`` the step's ``max(latent_batch_size, batch_size)`` windows
        :param waiting: the previous step's actor-critic batch, None in a burst's first step or with ``share_latent_batch``
        :return: the detached statistics of the step
        """
        latent = self.policy.latent
        if not self.config.share_latent_batch:
            batch, start = self.burn_in(batch)
            if waiting is not None:
                waiting, waiting_start = self.burn_in(waiting)
                start = None if start is None else LatentStart.cat([start, waiting_start])
            stats, latents = self.latent_update(batch, filter_batch=waiting, start=start)
            if waiting is not None:
                stats.update(self.actor_critic_update(waiting, latents.float()))
        else:
            n_latent, batch_size = self.config.latent_batch_size, self.config.batch_size
            batch, start = self.burn_in(batch)
            latent_batch, ac_batch = batch.rows(slice(0, n_latent)), batch.rows(slice(0, batch_size))
            with bf16_autocast(self.config.bf16, self.device):
                observations = self.policy.preprocess(batch.observations)
                latent_features = latent.encode(observations[:n_latent])
                with th.no_grad():
                    features = latent_features.detach()
                    if batch_size > n_latent:
                        features = th.cat([features, latent.encode(observations[n_latent:batch_size])])
                    ac_start = None if start is None else start.rows(slice(0, batch_size))
                    latents = latent.latents_from_features(features[:batch_size], ac_batch.actions, ac_start)
            latent_start = None if start is None else start.rows(slice(0, n_latent))
            stats, _ = self.latent_update(latent_batch, features=latent_features, start=latent_start)
            stats.update(self.actor_critic_update(ac_batch, latents.float()))
        self.guard.record(stats, pipelined=not self.config.share_latent_batch)
        self.guard.next_update()
        return stats

    def last_actor_critic_step(self, batch: SequenceBatch) -> dict[str, th.Tensor]:
        """
        The actor-critic update on the actor-critic batch of a burst's last gradient step (see ``full_step``), filtered
        by the latent model as that step left it; its NaN notes name that step.
        """
        batch, start = self.burn_in(batch)
        with th.no_grad(), bf16_autocast(self.config.bf16, self.device):
            latents = self.policy.latent.sample_latents(self.policy.preprocess(batch.observations), batch.actions, start)
        stats = self.actor_critic_update(batch, latents.float())
        self.guard.record(stats, pipelined=True)
        return stats

    def latent_step(self, batch: SequenceBatch) -> dict[str, th.Tensor]:
        """A latent-model update alone, as in the pre-training: its loss (detached)."""
        batch, start = self.burn_in(batch)
        stats, _ = self.latent_update(batch, start=start)
        self.guard.record(stats)
        self.guard.next_update()
        return {"latent_loss": stats["latent_loss"]}

    def burn_in(self, batch: SequenceBatch) -> tuple[SequenceBatch, LatentStart | None]:
        """
        The windows of ``batch`` after their burn-in (``config.burn_in`` frames), and the belief the latent model's
        filter reaches over the burn-in, without gradient, from the acting filter's stored belief where the batch
        brings one; the batch itself and None without a burn-in.
        """
        frames = self.config.burn_in
        if frames == 0:
            return batch, None
        assert batch.episode_start_index is not None, "a burn-in needs windows sampled with one (SequenceReplayBuffer)"
        stored = None
        if batch.stored_belief is not None and batch.stored_action is not None:
            stored = (batch.stored_belief, batch.stored_action)
        with th.no_grad(), bf16_autocast(self.config.bf16, self.device):
            features = self.policy.latent.encode(self.policy.preprocess(batch.observations[:, :frames]))
            start = self.policy.latent.burn_in(features, batch.actions[:, :frames], batch.episode_start_index, stored)
        return batch.without_burn_in(frames), start

    def latent_update(
        self,
        batch: SequenceBatch,
        features: th.Tensor | None = None,
        filter_batch: SequenceBatch | None = None,
        start: LatentStart | None = None,
    ) -> tuple[dict[str, th.Tensor], th.Tensor | None]:
        """
        One latent-model update on a batch of sequences (``features``: their encoder features, if already computed).

        :param filter_batch: other sequences to filter, without gradient, in the same rollout (before the update)
        :param start: the belief before the first frame of each sequence, ``batch``'s then ``filter_batch``'s (their
            burn-in's), None: their first frames open the rollout
        :return: the update's detached losses, and the posterior samples of ``filter_batch`` (B', L+1, z_dim) or None
        """
        with bf16_autocast(self.config.bf16, self.device):
            observations = self.policy.preprocess(batch.observations)
            other = None
            if filter_batch is not None:
                other = (self.policy.preprocess(filter_batch.observations), filter_batch.actions)
            loss, parts, latents = self.policy.latent.loss_and_filter(
                observations,
                batch.actions,
                batch.rewards,
                batch.costs,
                batch.terminated,
                features=features,
                other=other,
                start=start,
            )
        self.optimizer_step(self.policy.latent_optimizer, loss, self.config.max_grad_norm)
        return {"latent_loss": loss.detach(), **parts}, latents

    @th.no_grad()
    def td_targets(self, transitions: Transitions, ent_coef: th.Tensor, target_taus: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """
        TD targets of both critics, with ``a' ~ pi(z')`` from the current actor; terminations stop the bootstrap, time
        limits (truncations) do not.

        :param transitions: the transitions learned from (N of them)
        :param ent_coef: the entropy coefficient (scalar or (1,))
        :param target_taus: the target quantile fractions (N, N')
        :return: ``r + gamma * (1 - terminated) * (min(Q1', Q2')(z', a') - alpha * log pi(a' | z'))`` (N, 1) and
            ``c + gamma_c * (1 - terminated) * Z'_tau'(z', a')`` (N, N')
        """
        policy = self.policy
        next_z = transitions.next_latents
        not_terminated = 1.0 - transitions.terminated
        next_actions, next_log_prob = policy.actor.action_log_prob(next_z)
        next_q = policy.critic_target(next_z, next_actions).amin(dim=0) - ent_coef * next_log_prob.unsqueeze(-1)
        target_q = transitions.rewards + not_terminated * self.config.gamma * next_q
        next_quantiles = policy.cost_critic_target(next_z, next_actions, target_taus)
        target_quantiles = transitions.costs + not_terminated * self.config.cost_gamma * next_quantiles
        return target_q, target_quantiles

    def transitions(self, batch: SequenceBatch, latents: th.Tensor) -> Transitions:
        """
        The last ``actor_critic_transitions`` transitions of each sequence, flattened: ``z = latents[:, t]`` to
        ``z' = latents[:, t + 1]`` for the last ``k`` steps ``t`` (N = B * k, sequence-major). With the policy's
        ``previous_action_input`` each state is ``[latents[:, t], actions[:, t - 1]]``, and with its actor-critic memory
        ``[latents[:, t], h_t]`` (the memory run from frame 1, with gradient; ``z'`` without): the window's first frame
        has no previous action in the window, so ``k <= L - 1`` (``DSSLAC`` checks it).

        :param batch: the sequences (B, L+1 frames)
        :param latents: their posterior samples (B, L+1, z_dim)
        """
        k = self.config.actor_critic_transitions
        if self.policy.previous_action_input or self.policy.memory is not None:  # the states of frames 1..L (B, L, D)
            latents = self.policy.window_states(latents, batch.actions)
        if k == 1:  # the thesis's: one view of each field (the general form below takes two)
            rewards, costs, terminated = (field[:, -1:] for field in (batch.rewards, batch.costs, batch.terminated))
            return Transitions(latents[:, -2], batch.actions[:, -1], rewards, costs, terminated, latents[:, -1].detach())
        z_dim = latents.shape[-1]
        return Transitions(
            latents=latents[:, -k - 1 : -1].reshape(-1, z_dim),
            actions=batch.actions[:, -k:].reshape(-1, batch.actions.shape[-1]),
            rewards=batch.rewards[:, -k:].reshape(-1, 1),
            costs=batch.costs[:, -k:].reshape(-1, 1),
            terminated=batch.terminated[:, -k:].reshape(-1, 1),
            next_latents=latents[:, -k:].detach().reshape(-1, z_dim),
        )

    def actor_critic_update(self, batch: SequenceBatch, latents: th.Tensor) -> dict[str, th.Tensor]:
        """
        One update of the reward critic, the cost critic, the actor and the entropy coefficient on the last
        ``actor_critic_transitions`` transitions of each sequence, then of the target critics.

        :param batch: the sequences (B, L+1 frames)
        :param latents: their posterior samples (B, L+1, z_dim), no gradient (the policy's actor-critic memory over them
            learns from the reward critic's loss)
        :return: the update's detached losses and cost estimates
        """
        policy = self.policy
        transitions = self.transitions(batch, latents)
        z, actions = transitions.latents, transitions.actions
        n = z.shape[0]
        ent_coef = self.ent_coef_tensor
        if self.log_ent_coef is not None:
            with th.no_grad():
                ent_coef = self.log_ent_coef.exp()
        multiplier = F.softplus(self.lagrange_raw)

        target_taus = sample_taus(n, self.config.n_quantiles, self.device)
        target_q, target_quantiles = self.td_targets(transitions, ent_coef, target_taus)  # under no_grad

        q_values = policy.critic(z, actions)  # (2, B, 1)
        critic_loss = (q_values - target_q).pow(2).mean(dim=(1, 2)).sum()  # MSE of each network, summed
        self.optimizer_step(policy.critic_optimizer, critic_loss, self.config.max_grad_norm)
        z = z.detach()  # the memory in the states learns from the reward critic only

        taus = sample_taus(n, self.config.n_quantiles, self.device)
        current_quantiles = policy.cost_critic(z, actions, taus)
        if policy.cost_critic_type == "mean":
            cost_critic_loss = F.mse_loss(current_quantiles[:, :1], target_quantiles[:, :1])
        else:
            cost_critic_loss = quantile_huber_loss(current_quantiles, target_quantiles, cum_prob=taus.unsqueeze(-1))
        self.optimizer_step(
            policy.cost_critic_optimizer, cost_critic_loss, self.config.max_grad_norm, self.cost_critic_clip_groups
        )

        # The actor's gradients are taken for its own parameters only: the critics' weights get none
        pi_actions, log_prob = policy.actor.action_log_prob(z)
        q_pi = policy.critic(z, pi_actions).amin(dim=0)
        actor_taus = sample_taus(n, self.config.n_quantiles, self.device, risk_level=self.config.cvar_risk_level)
        cost_value = policy.cost_critic(z, pi_actions, actor_taus).mean(dim=1, keepdim=True)
        actor_loss = (ent_coef * log_prob.unsqueeze(-1) - q_pi + multiplier * cost_value).mean()
        self.optimizer_step(policy.actor_optimizer, actor_loss, self.config.actor_max_grad_norm)

        stats = {
            "critic_loss": critic_loss.detach(),
            "cost_critic_loss": cost_critic_loss.detach(),
            "actor_loss": actor_loss.detach(),
            "cost_cvar": cost_value.detach().mean(),
            "ent_coef": ent_coef.reshape(()),
        }
        if self.config.cvar_risk_level < 1.0:
            with th.no_grad():
                neutral_taus = sample_taus(n, self.config.n_quantiles, self.device)
                stats["cost_value"] = policy.cost_critic(z, pi_actions.detach(), neutral_taus).mean()
        else:
            stats["cost_value"] = stats["cost_cvar"]
        if self.config.critic_lagrange_budget is not None:
            with th.no_grad():
                raw = sgd_lagrange_step_on_device(
                    self.lagrange_raw, stats["cost_cvar"], self.config.critic_lagrange_budget, self.lagrange_learning_rate
                )
                self.lagrange_raw.copy_(raw)
        if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
            ent_coef_loss = -(self.log_ent_coef * (log_prob.detach() + self.config.target_entropy)).mean()
            self.optimizer_step(self.ent_coef_optimizer, ent_coef_loss, self.config.max_grad_norm)
            stats["ent_coef_loss"] = ent_coef_loss.detach()

        self.update_targets()
        return stats

    def update_targets(self) -> None:
        """Polyak update of both target critics, ``target += tau * (source - target)``, in one fused call."""
        with th.no_grad():
            th._foreach_lerp_(self.target_params, self.source_params, self.config.tau)

    def optimizer_step(
        self,
        optimizer: th.optim.Optimizer,
        loss: th.Tensor,
        max_grad_norm: float,
        clip_groups: tuple[slice, ...] = (slice(None),),
    ) -> None:
        """
        Gradients of ``loss`` for the optimizer's parameters only, each group of them (``clip_groups``: slices of the
        optimizer's parameter list) clipped to ``max_grad_norm`` on its own, then an Adam step.
        """
        params = optimizer.param_groups[0]["params"]
        grads = list(th.autograd.grad(loss, params, materialize_grads=True))
        for group in clip_groups:
            grads[group] = clip_grads(grads[group], max_grad_norm)
        adam_step(optimizer, grads, self.learning_rates[optimizer])
