"""DS-SLAC: Distributional Safe Stochastic Latent Actor-Critic as a Stable-Baselines3 off-policy algorithm."""

import io
import math
import pathlib
import warnings
from dataclasses import replace
from typing import Any, ClassVar, TypeVar

import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.save_util import recursive_getattr
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import update_learning_rate

from sb3_dsslac.common.buffers import SequenceReplayBuffer
from sb3_dsslac.common.env_info import action_repeat_of, episode_length_of
from sb3_dsslac.common.filtered_rollouts import FilteredRollouts
from sb3_dsslac.common.lagrange import CostBudget, inverse_softplus, with_lagrange_callback
from sb3_dsslac.common.policies import LatentPolicy, merge_shared_keywords
from sb3_dsslac.common.timing import TimeAccount
from sb3_dsslac.common.validation import check_arguments, check_related_arguments, check_spaces
from sb3_dsslac.engine.allocator import keep_freed_memory
from sb3_dsslac.engine.bursts import UpdateBursts, record_burst
from sb3_dsslac.engine.gradient_step import GradientStep, UpdateConfig
from sb3_dsslac.nn.numerics import resolve_bf16, tf32_matmul

SelfDSSLAC = TypeVar("SelfDSSLAC", bound="DSSLAC")


class DSSLAC(CostBudget, FilteredRollouts):
    """
    Distributional Safe Stochastic Latent Actor-Critic (Miranda, 2023), built on Safe SLAC (Hogewind et al., 2023).

    A sequential latent model learned from the observations (pixels or vectors) gives a belief ``z``; a SAC actor and
    twin reward critic and an implicit-quantile cost critic act and learn on ``z``; a Lagrange multiplier, updated
    on-policy from the real costs of the training episodes, trades reward against the cost budget.

    Units: one timestep is one ``env.step`` (an agent step, ``action_repeat`` simulator steps). Costs come from
    ``info["cost"]``. Defaults are the thesis's Table 5.2 and the code behind its numbers. The keywords of
    ``SHARED_POLICY_KEYWORDS`` (``common/policies.py``) are also ``LatentPolicy``'s: None takes ``policy_kwargs``' value,
    else ``LatentPolicy``'s default; given both here and in ``policy_kwargs``, they must agree, else a ValueError.

    :param policy: "LatentPolicy" or the class
    :param env: the env or its registered id; must report ``info["cost"]`` every step
    :param learning_rate: Adam step size of the actor, the critics and the entropy coefficient (or a schedule)
    :param buffer_size: frames kept in the replay buffer (over all envs)
    :param learning_starts: agent steps of random actions (``tanh(N(0, 2^2))``) before learning
    :param latent_pretrain_steps: latent-model updates run once, at the first ``train()`` after the warm-up
    :param batch_size: sequences per actor-critic update
    :param latent_batch_size: sequences per latent-model update
    :param sequence_length: transitions per sampled sequence (frames: ``sequence_length + 1``)
    :param burn_in: frames before each sampled sequence that the latent model filters first, without gradient and as
        the acting filter does (R2D2's burn-in), so that the sequences' beliefs, the latent model's loss and the actor
        and critics learn from carry ``burn_in + sequence_length`` frames of history, as the acting filter's beliefs
        do, and not the sequence's alone. 0: none (the thesis's: each sequence opens its own belief)
    :param stored_beliefs: with a burn-in, start it from the belief the acting filter reached at the frame before it,
        stored with that frame in the replay buffer (R2D2's stored state), so that a short burn-in gives the sequences
        beliefs of the whole episode so far; False: the burn-in opens its own belief at its first frame. The burn-in's
        encoder passes are what it costs: at ``cpu_pixels32_gru``'s sizes 4 frames from stored beliefs ran at 0.90x
        ``cpu_pixels32_pid``'s updates/s, 16 frames from the window's own at 0.37x (benchmarks/results/burn_in_speed.md)
    :param belief_refresh_interval: with ``stored_beliefs``, agent steps between two re-filterings of every stored
        episode by the current latent model (``SequenceReplayBuffer.refresh_beliefs``), the first right after the latent
        pre-training: a stored belief is the acting filter's of its time, and a buffer's oldest were written by a much
        younger model (the warm-up's by an untrained one). 0: never, beliefs stay as stored
    :param actor_critic_transitions: transitions of each sampled sequence, its last ones, that the actor and critics
        learn from: 1 (the thesis's, the last) to ``sequence_length`` (all: that many times the samples per update). The
        IQN cost critic then runs on ``batch_size * actor_critic_transitions * n_quantiles`` rows: with 4 transitions,
        ``n_quantiles`` / 4 keeps the update's cost (at ``cpu_pixels32_bounded``'s sizes, 4 transitions ran at 0.74x the
        updates/s of 1, and 4 with 8 quantiles at 1.01x; ``benchmarks/tools/compare_trees.py``, one thread, AMD EPYC)
    :param tau: Polyak factor of the target critics
    :param gamma: discount of the reward
    :param cost_gamma: discount of the cost
    :param train_freq: agent steps between training bursts; with ``n_envs`` envs it counts agent steps over all envs
        (it becomes ``train_freq / n_envs`` calls of ``env.step``), so the updates per agent step stay the same
    :param gradient_steps: updates per burst (each is one latent and one actor-critic update)
    :param latent_learning_rate: Adam step size of the latent model
    :param ent_coef: entropy coefficient, "auto" (learned from 1.0) or "auto_<init>" (learned from init), or a float
    :param target_entropy: target entropy of the learned coefficient; "auto" is ``-action_dim``
    :param cost_limit: cost budget per episode (Safety-Gym: 25 per 1000 simulator steps); evaluations are judged by it
    :param cost_target: the episode cost the multiplier holds the training episodes to; None: ``cost_limit``. Below
        ``cost_limit`` it leaves a margin for the noise of an evaluation (10 episodes' mean cost has a standard error of
        about 10 on PointGoal1), which is still judged against ``cost_limit``
    :param episode_length: agent steps per episode, to turn the budget into a per-step budget for the multiplier;
        None reads the env's time limit
    :param lagrange: the multiplier's update rule: "sgd" (the thesis's, per agent step from the real cost), "episode"
        (SGD once per finished episode), "pid" (PID Lagrangian on episode costs), "critic" (off-policy, from the cost
        critic's estimate against the discounted per-step budget, every actor-critic update; for study)
    :param lagrange_init: initial Lagrange multiplier
    :param lagrange_learning_rate: SGD step size of the multiplier's raw (pre-softplus) parameter
    :param lr_decay_milestone: agent steps (counted from the start of training, warm-up included) from which every step
        size (actor, both critics, entropy coefficient, latent model and multiplier) is multiplied by
        ``lr_decay_factor``; None: no decay. The ``thesis`` presets set the reference code's 230_000 (see
        ``presets.THESIS_LR_DECAY_MILESTONE``)
    :param lr_decay_factor: the factor applied from ``lr_decay_milestone`` on (0.5 in the reference code)
    :param pid_kp: proportional gain of the "pid" rule (multiplier per unit of episode cost over the budget)
    :param pid_ki: integral gain of the "pid" rule
    :param pid_kd: derivative gain of the "pid" rule
    :param pid_cost_ema: smoothing of the episode costs that the "pid" rule's proportional and derivative terms act on
        (an exponential moving average with this weight on the past; 0: each episode's own cost)
    :param cost_critic: "iqn" (DS-SLAC's distributional critic) or "mean" (Safe SLAC's expectation critic)
    :param n_quantiles: N = N' = K, the quantile fractions sampled per update by the IQN critic and the actor
    :param cvar_risk_level: beta in (0, 1]: the actor's K fractions are drawn from U(1 - beta, 1); 1.0 is the mean
    :param max_grad_norm: gradient-norm clip of the latent model and the critics
    :param actor_max_grad_norm: gradient-norm clip of the actor (80 in the reference code)
    :param image_noise: variance of the Gaussian observation likelihood
    :param cost_loss_weight: weight of the Bernoulli cost likelihood in the latent loss
    :param cost_positive_weight: extra weight of unsafe steps in the cost likelihood
    :param share_latent_batch: one sampled batch and one encoder pass per update: the latent model trains on the first
        ``latent_batch_size`` sequences, and the actor-critic update uses the posterior of the first ``batch_size``
        from the same features (before the latent step). False keeps the thesis's two independent batches
    :param bf16: run the latent model's passes (the convolutions: most of the arithmetic) under bfloat16 autocast;
        the actor, critics and every optimizer stay in float32. ``"auto"``: only where the device computes bfloat16
        natively (a recent GPU, a CPU with AVX512-BF16 or AMX); ``True`` on a device without it warns and keeps float32
    :param compile_updates: ``torch.compile`` the whole gradient step (latent update, actor-critic update, Adam steps,
        Polyak) as one graph with ``fullgraph=True``; on CUDA it is replayed as CUDA graphs (``mode="reduce-overhead"``).
        Costs a one-off compilation (a minute or more) at the first update; falls back to eager with a warning where
        compilation fails
    :param tf32: on CUDA, float32 matrix products and convolutions use TF32 while ``learn`` runs (the process-wide
        settings come back when it returns); the reference code ran in full float32
    :param replay_buffer_kwargs: extra keywords of the ``SequenceReplayBuffer``
    :param stats_window_size: episodes averaged in the rollout logs
    :param tensorboard_log: TensorBoard log folder
    :param policy_kwargs: keywords of the policy (``z1_dim``, ``z2_dim``, ``feature_dim``, ``hidden_units``, ``n_cosines``)
    :param verbose: 0 silent, 1 info (with a progress bar for the latent pre-training), 2 debug
    :param seed: random seed
    :param device: "cpu", "cuda" or "auto"
    :param _init_setup_model: build the networks at construction
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"LatentPolicy": LatentPolicy}
    policy: LatentPolicy
    replay_buffer: SequenceReplayBuffer

    def __init__(
        self,
        policy: str | type[LatentPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 2e-4,
        buffer_size: int = 200_000,
        learning_starts: int = 30_000,
        latent_pretrain_steps: int = 30_000,
        batch_size: int = 64,
        latent_batch_size: int = 32,
        sequence_length: int = 10,
        burn_in: int = 0,
        stored_beliefs: bool = False,
        belief_refresh_interval: int = 0,
        actor_critic_transitions: int = 1,
        tau: float = 5e-3,
        gamma: float = 0.99,
        cost_gamma: float = 0.995,
        train_freq: int | tuple[int, str] = 100,
        gradient_steps: int = 100,
        latent_learning_rate: float | None = None,
        ent_coef: str | float = "auto_4e-3",
        target_entropy: str | float = "auto",
        cost_limit: float = 25.0,
        cost_target: float | None = None,
        episode_length: int | None = None,
        lagrange: str = "sgd",
        lagrange_init: float = 0.02,
        lagrange_learning_rate: float = 2e-4,
        lr_decay_milestone: int | None = None,
        lr_decay_factor: float = 0.5,
        pid_kp: float = 0.05,
        pid_ki: float = 0.005,
        pid_kd: float = 0.02,
        pid_cost_ema: float = 0.9,
        cost_critic: str | None = None,
        n_quantiles: int = 64,
        cvar_risk_level: float = 1.0,
        max_grad_norm: float = 40.0,
        actor_max_grad_norm: float = 80.0,
        image_noise: float | None = None,
        cost_loss_weight: float | None = None,
        cost_positive_weight: float | None = None,
        share_latent_batch: bool = False,
        bf16: bool | str = False,
        compile_updates: bool = False,
        tf32: bool = True,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        check_arguments(DSSLAC.__init__, locals())  # types and ranges that SB3 would leave to the first update
        check_related_arguments(locals())
        super().__init__(
            policy,
            env,
            learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            replay_buffer_class=SequenceReplayBuffer,
            replay_buffer_kwargs={"sequence_length": sequence_length, "burn_in": burn_in, **(replay_buffer_kwargs or {})},
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            seed=seed,
            support_multi_env=True,
            sde_support=False,
        )
        self.latent_pretrain_steps = latent_pretrain_steps
        self.latent_batch_size = latent_batch_size
        self.sequence_length = sequence_length
        self.burn_in = burn_in
        self.stored_beliefs = stored_beliefs
        self.belief_refresh_interval = belief_refresh_interval
        self.beliefs_refreshed_at: int | None = None  # num_timesteps of the last refresh of the stored beliefs
        self.actor_critic_transitions = actor_critic_transitions
        self.cost_gamma = cost_gamma
        # A copy: the caller's dict is not ours to fill, and may be shared by several models
        self.policy_kwargs = merge_shared_keywords(
            dict(self.policy_kwargs),
            image_noise=image_noise,
            cost_loss_weight=cost_loss_weight,
            cost_positive_weight=cost_positive_weight,
            latent_learning_rate=latent_learning_rate,
            cost_critic=cost_critic,
        )
        self.latent_learning_rate = float(self.policy_kwargs["latent_learning_rate"])
        self.ent_coef = ent_coef
        self.target_entropy = target_entropy
        self.cost_limit = cost_limit
        self.cost_target = cost_target
        self.episode_length = episode_length
        self.lagrange = lagrange
        self.lagrange_init = lagrange_init
        # On the host whatever the device, read once per burst; saved with the attributes, so any load device finds it
        self.lagrange_raw = th.tensor(inverse_softplus(lagrange_init), dtype=th.float64)
        self.lagrange_learning_rate = lagrange_learning_rate
        self.lr_decay_milestone = lr_decay_milestone
        self.lr_decay_factor = lr_decay_factor
        self.pid_gains = (pid_kp, pid_ki, pid_kd)
        self.pid_cost_ema = pid_cost_ema
        self.cost_critic = str(self.policy_kwargs["cost_critic"])
        self.n_quantiles = n_quantiles
        self.cvar_risk_level = cvar_risk_level
        self.max_grad_norm = max_grad_norm
        self.actor_max_grad_norm = actor_max_grad_norm
        self.share_latent_batch = share_latent_batch
        self.bf16 = bf16
        self.compile_updates = compile_updates
        self.tf32 = tf32
        # Run state that is saved with the model (so that resuming never repeats the pre-training)
        self.latent_pretrained = False
        self.pid_state: list[float | None] = [0.0, None]  # integral, smoothed episode cost (None before the first)
        self.action_repeat = 1
        self.time_account = TimeAccount()  # wall seconds by activity, logged as time/<activity>_s
        self._init_rollout_state()
        if self.env is not None:
            check_spaces(self.observation_space, self.action_space)
            self.action_repeat = action_repeat_of(self.env)
            self.episode_length = episode_length or episode_length_of(self.env, required=True)
        if self.episode_length is not None:
            self.policy_kwargs.setdefault("cost_critic_initial_value", self.discounted_cost_budget)
        if _init_setup_model:
            self._setup_model()

    def _convert_train_freq(self) -> None:
        """SB3's conversion, then a step frequency counted in agent steps over all envs becomes ``env.step`` calls."""
        converting = not isinstance(self.train_freq, TrainFreq)
        super()._convert_train_freq()
        assert isinstance(self.train_freq, TrainFreq)
        if converting and self.n_envs > 1 and self.train_freq.unit == TrainFrequencyUnit.STEP:
            frequency = self.train_freq.frequency
            if frequency % self.n_envs != 0:
                warnings.warn(
                    f"train_freq={frequency} agent steps is not a multiple of n_envs={self.n_envs}: bursts come every "
                    f"{math.ceil(frequency / self.n_envs) * self.n_envs} agent steps, so there are fewer updates per step"
                )
            self.train_freq = TrainFreq(math.ceil(frequency / self.n_envs), TrainFrequencyUnit.STEP)

    def _setup_model(self) -> None:
        super()._setup_model()
        self.policy.latent.set_layout_for(self.device)
        self._fit_replay_buffer()
        if self.device.type == "cpu":  # the updates' freed tensors stay mapped for the next update (allocator.py)
            keep_freed_memory()
        self.target_entropy = -float(self.policy.action_dim) if self.target_entropy == "auto" else float(self.target_entropy)
        self.ent_coef_optimizer: th.optim.Adam | None = None
        log_ent_coef = ent_coef_tensor = None
        if isinstance(self.ent_coef, str) and self.ent_coef.startswith("auto"):
            init_value = float(self.ent_coef.split("_")[1]) if "_" in self.ent_coef else 1.0
            if init_value <= 0.0:
                raise ValueError(f"The initial entropy coefficient must be greater than 0, got {self.ent_coef}")
            self.log_ent_coef = log_ent_coef = th.log(th.full((1,), init_value, device=self.device)).requires_grad_(True)
            self.ent_coef_optimizer = th.optim.Adam([self.log_ent_coef], lr=self.lr_schedule(1), fused=True)
        else:
            self.ent_coef_tensor = ent_coef_tensor = th.tensor(float(self.ent_coef), device=self.device)
        optimizers = [recursive_getattr(self, name) for name in self._optimizer_names()]
        config = self.update_config(self.batch_size)
        step = GradientStep(
            self.policy, optimizers, log_ent_coef, self.ent_coef_optimizer, ent_coef_tensor, config, self.device
        )
        # The update engine: rebuilt here, never saved
        self.updates = UpdateBursts(step, self.lagrange_raw, self.compile_updates, self.time_account)

    def update_config(self, batch_size: int) -> UpdateConfig:
        """What the gradient step reads of this model's hyperparameters, now (``batch_size``: sequences per update)."""
        assert isinstance(self.target_entropy, float)
        return UpdateConfig(
            target_entropy=self.target_entropy,
            gamma=self.gamma,
            cost_gamma=self.cost_gamma,
            tau=self.tau,
            batch_size=batch_size,
            latent_batch_size=self.latent_batch_size,
            actor_critic_transitions=self.actor_critic_transitions,
            share_latent_batch=self.share_latent_batch,
            n_quantiles=self.n_quantiles,
            cvar_risk_level=self.cvar_risk_level,
            max_grad_norm=self.max_grad_norm,
            actor_max_grad_norm=self.actor_max_grad_norm,
            critic_lagrange_budget=self.critic_cost_budget if self.lagrange == "critic" else None,
            bf16=resolve_bf16(self.bf16, self.device),
            burn_in=self.burn_in,
        )

    def _optimizer_names(self) -> list[str]:
        """Every optimizer, by the attribute path it is saved under: the policy's four, then the entropy coefficient's."""
        names = [f"policy.{network}_optimizer" for network in ("latent", "actor", "critic", "cost_critic")]
        return [*names, "ent_coef_optimizer"] if self.ent_coef_optimizer is not None else names

    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        """Attach the on-policy ``LagrangeCallback`` unless the caller already passed one."""
        return super()._init_callback(with_lagrange_callback(callback), progress_bar)

    def _update_learning_rate(self, optimizers: list[th.optim.Optimizer] | th.optim.Optimizer) -> None:
        """
        Set the step sizes for the current timestep: the latent model's ``latent_learning_rate``, the others' (actor,
        critics, entropy coefficient) ``lr_schedule``, each times ``lr_decay_multiplier``. A pure function of
        ``num_timesteps`` and the progress, so a resumed run continues with the right step sizes.
        """
        factor = self.lr_decay_multiplier
        learning_rate = self.lr_schedule(self._current_progress_remaining) * factor
        latent_learning_rate = self.latent_learning_rate * factor
        self.logger.record("train/learning_rate", learning_rate)
        self.logger.record("train/latent_learning_rate", latent_learning_rate)
        rates = {self.policy.latent_optimizer: latent_learning_rate}
        for optimizer in optimizers if isinstance(optimizers, list) else [optimizers]:
            update_learning_rate(optimizer, rates.get(optimizer, learning_rate))

    def train(self, gradient_steps: int, batch_size: int) -> None:
        """
        ``gradient_steps`` updates, each one latent-model update and one actor-critic update (Algorithm 1), with one
        host read for the whole burst. The first call runs the latent pre-training once.
        """
        self.policy.set_training_mode(True)
        self._update_learning_rate(self.updates.step.optimizers)
        # Read at every burst, as SAC reads them at every update: a changed model.gamma or model.tau takes effect
        # (a compiled update recompiles once for the new values; the same values keep the same config and graphs).
        # The rest of the config (bf16 resolved against the device among it) is fixed when the model is set up
        step_config = self.updates.step.config
        config = replace(
            step_config,
            gamma=self.gamma,
            cost_gamma=self.cost_gamma,
            tau=self.tau,
            batch_size=batch_size,
            latent_batch_size=self.latent_batch_size,
        )
        if config != step_config:
            self.updates.step.config = config
        if not self.latent_pretrained:
            with self.time_account.measure("latent_pretraining"):
                self._pretrain_latent()
        with self.time_account.measure("updates"):
            if self._beliefs_due_for_refresh():
                self._refresh_beliefs()
            means = self.updates.train(
                self.replay_buffer,
                gradient_steps,
                batch_size,
                self.current_lagrange_learning_rate,
                self._n_updates,
                self.num_timesteps,
            )
            self._n_updates += gradient_steps
            self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
            self.logger.record("train/lagrange_multiplier", self.lagrange_multiplier)
            record_burst(self.logger, means)

    def _pretrain_latent(self) -> None:
        """The one-off latent pre-training of Algorithm 1 (W_t updates), after standardising vectors by the warm-up data."""
        self.policy.set_observation_statistics(self.replay_buffer.stored_observations())
        loss = self.updates.pretrain_latent(
            self.replay_buffer,
            self.latent_pretrain_steps,
            self.current_lagrange_learning_rate,
            self._n_updates,
            self.num_timesteps,
            progress_bar=self.verbose >= 1,
        )
        self.latent_pretrained = True
        if loss is not None:
            self.logger.record("train/pretrain_latent_loss", loss)

    def _beliefs_due_for_refresh(self) -> bool:
        """Whether ``belief_refresh_interval`` asks for a refresh now (the first one at the first burst)."""
        if self.belief_refresh_interval == 0:
            return False
        last = self.beliefs_refreshed_at
        return last is None or self.num_timesteps - last >= self.belief_refresh_interval

    def _refresh_beliefs(self) -> None:
        """Re-filter the replay buffer's stored beliefs with the current latent model, as the acting filter steps."""
        self.policy.set_training_mode(False)
        with th.no_grad():
            refreshed = self.replay_buffer.refresh_beliefs(
                lambda frames, z2_prev, action_prev, opens: self.policy.belief_step(
                    frames, z2_prev, action_prev, opens, deterministic=False
                )[1]
            )
        self.policy.set_training_mode(True)
        self.beliefs_refreshed_at = self.num_timesteps
        self.logger.record("train/beliefs_refreshed", refreshed)

    def learn(
        self: SelfDSSLAC,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "DSSLAC",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfDSSLAC:
        """SB3's ``learn``; with ``tf32`` on CUDA, float32 matrix products and convolutions use TF32 until it returns."""
        with tf32_matmul(self.tf32 and self.device.type == "cuda"), self.time_account.running():
            return super().learn(
                total_timesteps=total_timesteps,
                callback=callback,
                log_interval=log_interval,
                tb_log_name=tb_log_name,
                reset_num_timesteps=reset_num_timesteps,
                progress_bar=progress_bar,
            )

    @classmethod
    def load(
        cls: type[SelfDSSLAC],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        **kwargs: Any,
    ) -> SelfDSSLAC:
        """
        SB3's ``load``, with the multiplier's raw parameter on the host whatever ``device``: files saved before it moved
        into the saved attributes hold it as a torch variable, which SB3 loads onto ``device``.
        """
        model = super().load(path, env, device, custom_objects, print_system_info, force_reset, **kwargs)
        model.lagrange_raw.data = model.lagrange_raw.data.cpu()
        return model

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """SB3's ``load_replay_buffer``, the buffer then fitted to this model (``_fit_replay_buffer``)."""
        super().load_replay_buffer(path, truncate_last_traj)
        self._fit_replay_buffer()

    def _fit_replay_buffer(self) -> None:
        """Store the buffer's frames in the layout of this model's convolutions, and its beliefs with ``stored_beliefs``."""
        self.replay_buffer.set_channels_last_frames(self.policy.latent.channels_last)
        if self.stored_beliefs:
            self.replay_buffer.store_beliefs(self.policy.latent.z2_dim)

    def _excluded_save_params(self) -> list[str]:
        # The training envs' rollout state, and the update engine that _setup_model rebuilds
        return [*super()._excluded_save_params(), "_last_filter_state", "_episode_costs", "ep_cost_buffer", "updates"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        ent_coef = "log_ent_coef" if self.ent_coef_optimizer is not None else "ent_coef_tensor"
        return ["policy", *self._optimizer_names()], [ent_coef]
