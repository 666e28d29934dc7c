"""DS-SLAC: Distributional Safe Stochastic Latent Actor-Critic as a Stable-Baselines3 off-policy algorithm."""

import contextlib
import math
import warnings
from collections import defaultdict, deque
from collections.abc import Iterator
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import safe_mean, update_learning_rate
from torch.nn import functional as F
from tqdm.auto import tqdm

from sb3_dsslac.buffers import SequenceBatch, SequenceReplayBuffer
from sb3_dsslac.critics import IQNCostCritic, quantile_huber_loss, sample_taus
from sb3_dsslac.env_info import action_repeat_of, cost_from_info, episode_length_of
from sb3_dsslac.lagrange import (
    LAGRANGE_RULES,
    LagrangeCallback,
    inverse_softplus,
    sgd_lagrange_step,
    softplus,
)
from sb3_dsslac.policies import LatentPolicy

SelfDSSLAC = TypeVar("SelfDSSLAC", bound="DSSLAC")


@contextlib.contextmanager
def tf32_matmul(enabled: bool) -> Iterator[None]:
    """
    TF32 for CUDA float32 matrix products and cuDNN convolutions inside the block when ``enabled`` (PyTorch's switches
    are process-wide, so the previous values come back when the block ends, also on an error); nothing otherwise.
    """
    if not enabled:
        yield
        return
    previous = th.backends.cuda.matmul.allow_tf32, th.backends.cudnn.allow_tf32
    th.backends.cuda.matmul.allow_tf32 = th.backends.cudnn.allow_tf32 = True
    try:
        yield
    finally:
        th.backends.cuda.matmul.allow_tf32, th.backends.cudnn.allow_tf32 = previous


def _has_lagrange_callback(callback: MaybeCallback) -> bool:
    if isinstance(callback, LagrangeCallback):
        return True
    if isinstance(callback, CallbackList):
        return any(_has_lagrange_callback(child) for child in callback.callbacks)
    if isinstance(callback, list):
        return any(_has_lagrange_callback(child) for child in callback)
    return False


# Keywords of both DSSLAC and LatentPolicy, with their defaults (the code behind the thesis numbers)
SHARED_POLICY_KEYWORDS: dict[str, Any] = {
    "image_noise": 0.4,
    "cost_loss_weight": 30.0,
    "cost_positive_weight": 100.0,
    "latent_learning_rate": 1e-4,
    "cost_critic": "iqn",
}


def _merge_shared_keywords(policy_kwargs: dict[str, Any], **given: Any) -> dict[str, Any]:
    """
    ``policy_kwargs`` with each of ``SHARED_POLICY_KEYWORDS`` set once: the value given to DSSLAC (None: not given),
    else the one in ``policy_kwargs``, else the default. A ValueError names both when they are given and differ.
    """
    for name, default in SHARED_POLICY_KEYWORDS.items():
        value = given[name]
        if value is None:
            policy_kwargs.setdefault(name, default)
        elif name in policy_kwargs and policy_kwargs[name] != value:
            raise ValueError(
                f"{name}={value!r} and policy_kwargs={{{name!r}: {policy_kwargs[name]!r}}} disagree: give {name} once"
            )
        else:
            policy_kwargs[name] = value
    return policy_kwargs


class DSSLAC(OffPolicyAlgorithm):
    """
    Distributional Safe Stochastic Latent Actor-Critic (Miranda, 2023), built on Safe SLAC (Hogewind et al., 2023).

    A sequential latent model learned from the observations (pixels or vectors) gives a belief ``z``; a SAC actor and
    twin reward critic and an implicit-quantile cost critic act and learn on ``z``; a Lagrange multiplier, updated
    on-policy from the real costs of the training episodes, trades reward against the cost budget.

    Units: one timestep is one ``env.step`` (an agent step, ``action_repeat`` simulator steps). Costs come from
    ``info["cost"]``. Defaults are the thesis's Table 5.2 and the code behind its numbers.

    :param policy: "LatentPolicy" or the class
    :param env: the env or its registered id; must report ``info["cost"]`` every step
    :param learning_rate: Adam step size of the actor, the critics and the entropy coefficient (or a schedule)
    :param buffer_size: frames kept in the replay buffer (over all envs)
    :param learning_starts: agent steps of random actions (``tanh(N(0, 2^2))``) before learning
    :param latent_pretrain_steps: latent-model updates run once, at the first ``train()`` after the warm-up
    :param batch_size: sequences per actor-critic update
    :param latent_batch_size: sequences per latent-model update
    :param sequence_length: transitions per sampled sequence (frames: ``sequence_length + 1``)
    :param tau: Polyak factor of the target critics
    :param gamma: discount of the reward
    :param cost_gamma: discount of the cost
    :param train_freq: agent steps between training bursts; with ``n_envs`` envs it counts agent steps over all envs
        (it becomes ``train_freq / n_envs`` calls of ``env.step``), so the updates per agent step stay the same
    :param gradient_steps: updates per burst (each is one latent and one actor-critic update)
    :param latent_learning_rate: Adam step size of the latent model (None: ``policy_kwargs``' value, else 1e-4)
    :param ent_coef: entropy coefficient, "auto" (learned from 1.0) or "auto_<init>" (learned from init), or a float
    :param target_entropy: target entropy of the learned coefficient; "auto" is ``-action_dim``
    :param cost_limit: cost budget per episode (Safety-Gym: 25 per 1000 simulator steps)
    :param episode_length: agent steps per episode, to turn the budget into a per-step budget for the multiplier;
        None reads the env's time limit
    :param lagrange: the multiplier's update rule: "sgd" (the thesis's, per agent step from the real cost), "episode"
        (SGD once per finished episode), "pid" (PID Lagrangian on episode costs), "critic" (off-policy, from the cost
        critic's estimate against the discounted per-step budget, every actor-critic update; for study)
    :param lagrange_init: initial Lagrange multiplier
    :param lagrange_learning_rate: SGD step size of the multiplier's raw (pre-softplus) parameter
    :param lr_decay_milestone: agent steps (counted from the start of training, warm-up included) from which every step
        size (actor, both critics, entropy coefficient, latent model and multiplier) is multiplied by
        ``lr_decay_factor``; None: no decay. The code behind the thesis numbers halves them all once at 230_000 (its
        ``MultiStepLR`` milestone 400, stepped every 1000 simulator steps after the 60k-step warm-up: 460k simulator
        steps), which the ``thesis`` presets set
    :param lr_decay_factor: the factor applied from ``lr_decay_milestone`` on (0.5 in the reference code)
    :param pid_kp: proportional gain of the "pid" rule (multiplier per unit of episode cost over the budget)
    :param pid_ki: integral gain of the "pid" rule
    :param pid_kd: derivative gain of the "pid" rule
    :param pid_cost_ema: smoothing of the episode costs that the "pid" rule's proportional and derivative terms act on
        (an exponential moving average with this weight on the past; 0: each episode's own cost)
    :param cost_critic: "iqn" (DS-SLAC's distributional critic) or "mean" (Safe SLAC's expectation critic); None:
        ``policy_kwargs``' value, else "iqn"
    :param n_quantiles: N = N' = K, the quantile fractions sampled per update by the IQN critic and the actor
    :param cvar_risk_level: beta in (0, 1]: the actor's K fractions are drawn from U(1 - beta, 1); 1.0 is the mean
    :param max_grad_norm: gradient-norm clip of the latent model and the critics
    :param actor_max_grad_norm: gradient-norm clip of the actor (80 in the reference code)
    :param image_noise: variance of the Gaussian observation likelihood (None: ``policy_kwargs``' value, else 0.4)
    :param cost_loss_weight: weight of the Bernoulli cost likelihood in the latent loss (None: ``policy_kwargs``' value,
        else 30)
    :param cost_positive_weight: extra weight of unsafe steps in the cost likelihood (None: ``policy_kwargs``' value,
        else 100)
    :param share_latent_batch: one sampled batch and one encoder pass per update: the latent model trains on the first
        ``latent_batch_size`` sequences, and the actor-critic update uses the posterior of the first ``batch_size``
        from the same features (before the latent step). False keeps the thesis's two independent batches
    :param bf16: run the latent model's passes (the convolutions: most of the arithmetic) under bfloat16 autocast;
        the actor, critics and every optimizer stay in float32
    :param compile_updates: ``torch.compile`` the latent model's posterior rollout (a loop of small MLPs, the
        launch-bound part of the update) and the cost critic; the convolutions stay eager. Costs a one-off
        compilation (about a minute) at the first update
    :param tf32: on CUDA, float32 matrix products and convolutions use TF32 while ``learn`` runs (the process-wide
        settings come back when it returns); the reference code ran in full float32
    :param replay_buffer_kwargs: extra keywords of the ``SequenceReplayBuffer``
    :param stats_window_size: episodes averaged in the rollout logs
    :param tensorboard_log: TensorBoard log folder
    :param policy_kwargs: keywords of the policy (``z1_dim``, ``z2_dim``, ``feature_dim``, ``hidden_units``, ``n_cosines``);
        a keyword given both here and to DSSLAC (``image_noise``, ``cost_loss_weight``, ``cost_positive_weight``,
        ``latent_learning_rate``, ``cost_critic``) must have the same value in both, else a ValueError
    :param verbose: 0 silent, 1 info (with a progress bar for the latent pre-training), 2 debug
    :param seed: random seed
    :param device: "cpu", "cuda" or "auto"
    :param _init_setup_model: build the networks at construction
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {"LatentPolicy": LatentPolicy}
    policy: LatentPolicy
    replay_buffer: SequenceReplayBuffer
    _PRETRAIN_BURST = 100  # latent pre-training updates whose windows are drawn at once

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
        tau: float = 5e-3,
        gamma: float = 0.99,
        cost_gamma: float = 0.995,
        train_freq: int | tuple[int, str] = 100,
        gradient_steps: int = 100,
        latent_learning_rate: float | None = None,
        ent_coef: str | float = "auto_4e-3",
        target_entropy: str | float = "auto",
        cost_limit: float = 25.0,
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
        bf16: bool = False,
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
            replay_buffer_kwargs={"sequence_length": sequence_length, **(replay_buffer_kwargs or {})},
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
        self.cost_gamma = cost_gamma
        # A copy: the caller's dict is not ours to fill, and may be shared by several models
        self.policy_kwargs = _merge_shared_keywords(
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
        self.episode_length = episode_length
        self.lagrange = lagrange
        self.lagrange_init = lagrange_init
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
        self.total_cost = 0.0
        # Rollout state, not saved: the training envs' filter state and running episode costs
        self._last_filter_state: tuple[th.Tensor, th.Tensor] | None = None
        self._episode_costs = np.zeros(0)
        self.ep_cost_buffer: deque[float] = deque(maxlen=stats_window_size)

        if self.env is not None:
            self._check_spaces(self.observation_space, self.action_space)
            self.action_repeat = action_repeat_of(self.env)
            if self.episode_length is None:
                self.episode_length = episode_length_of(self.env)
            if self.episode_length is None:
                raise ValueError(
                    "Cannot tell how many agent steps an episode of this env has (it has no time limit): "
                    "pass episode_length=<agent steps per episode> so that cost_limit can be spread over the steps."
                )
        if not 0.0 < cvar_risk_level <= 1.0:
            raise ValueError(f"cvar_risk_level must be in (0, 1], got {cvar_risk_level}")
        if lr_decay_milestone is not None and lr_decay_milestone < 0:
            raise ValueError(f"lr_decay_milestone must be a number of agent steps >= 0 or None, got {lr_decay_milestone}")
        if lr_decay_factor <= 0.0:
            raise ValueError(f"lr_decay_factor must be > 0, got {lr_decay_factor}")
        if not 0.0 <= pid_cost_ema < 1.0:
            raise ValueError(f"pid_cost_ema must be in [0, 1), got {pid_cost_ema}")
        if lagrange not in LAGRANGE_RULES:
            raise ValueError(f"Unknown lagrange rule {lagrange!r}; choose one of {', '.join(LAGRANGE_RULES)}")
        if self.episode_length is not None:
            self.policy_kwargs.setdefault("cost_critic_initial_value", self.discounted_cost_budget)
        if _init_setup_model:
            self._setup_model()

    @staticmethod
    def _check_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> None:
        """Raise a ValueError naming the fix for spaces DS-SLAC cannot handle."""
        if not isinstance(action_space, spaces.Box):
            raise ValueError(
                f"DS-SLAC needs a continuous Box action space, got {action_space}. "
                "Discrete-action envs need a different algorithm (or a wrapper mapping a Box to the discrete actions)."
            )
        if not isinstance(observation_space, spaces.Box) or len(observation_space.shape) not in (1, 3):
            raise ValueError(
                f"DS-SLAC encodes Box images (C, H, W) or flat Box vectors, got {observation_space}. "
                "For safety_envs use obs_type='pixels' or obs_type='state'; "
                "flatten or select Dict observations with a wrapper."
            )

    @property
    def cost_budget_per_step(self) -> float:
        """The episode budget spread over the agent steps of an episode (25 / 500 = 0.05 for the thesis setting)."""
        assert self.episode_length is not None
        return self.cost_limit / self.episode_length

    @property
    def discounted_cost_budget(self) -> float:
        """The per-step budget discounted over an episode with ``cost_gamma``: 9.184 for the thesis setting."""
        assert self.episode_length is not None
        return self.cost_budget_per_step * (1.0 - self.cost_gamma**self.episode_length) / (1.0 - self.cost_gamma)

    @property
    def lr_decay_multiplier(self) -> float:
        """The factor on every step size now: ``lr_decay_factor`` from agent step ``lr_decay_milestone`` on, else 1."""
        if self.lr_decay_milestone is not None and self.num_timesteps >= self.lr_decay_milestone:
            return self.lr_decay_factor
        return 1.0

    @property
    def current_lagrange_learning_rate(self) -> float:
        """The multiplier's SGD step size now: ``lagrange_learning_rate`` times ``lr_decay_multiplier``."""
        return self.lagrange_learning_rate * self.lr_decay_multiplier

    @property
    def critic_cost_budget(self) -> float:
        """
        The budget of the "critic" rule: ``cost_budget_per_step / (1 - cost_gamma)``, 10.0 for the thesis setting, the
        value the critic's (infinite-horizon, time-limit-bootstrapped) estimate converges to at exactly the per-step
        budget. Against ``discounted_cost_budget`` (9.184, discounting stopped at the episode end) the rule would hold
        the episode cost to about 23 instead of 25.
        """
        return self.cost_budget_per_step / (1.0 - self.cost_gamma)

    @property
    def lagrange_multiplier(self) -> float:
        """The current Lagrange multiplier (softplus of its raw parameter)."""
        return softplus(float(self.lagrange_raw.item()))

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
        if self.compile_updates:
            self.policy.latent.posterior = th.compile(self.policy.latent.posterior)  # type: ignore[method-assign]
            self.policy.cost_critic.compile()
        self.lagrange_raw = th.tensor(inverse_softplus(self.lagrange_init), dtype=th.float64)
        if self.target_entropy == "auto":
            self.target_entropy = -float(np.prod(self.action_space.shape))  # type: ignore[arg-type]
        else:
            self.target_entropy = float(self.target_entropy)
        self.ent_coef_optimizer: th.optim.Adam | None = None
        if isinstance(self.ent_coef, str) and self.ent_coef.startswith("auto"):
            init_value = float(self.ent_coef.split("_")[1]) if "_" in self.ent_coef else 1.0
            if init_value <= 0.0:
                raise ValueError(f"The initial entropy coefficient must be greater than 0, got {self.ent_coef}")
            self.log_ent_coef = th.log(th.full((1,), init_value, device=self.device)).requires_grad_(True)
            self.ent_coef_optimizer = th.optim.Adam([self.log_ent_coef], lr=self.lr_schedule(1))
        else:
            self.ent_coef_tensor = th.tensor(float(self.ent_coef), device=self.device)

    # ----------------------------------------------------------------------------------------------------------------
    # Acting
    # ----------------------------------------------------------------------------------------------------------------

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        envs_reset = reset_num_timesteps or self._last_obs is None
        if reset_num_timesteps:
            self.total_cost = 0.0
            self.ep_cost_buffer = deque(maxlen=self._stats_window_size)
        result = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        assert self.env is not None
        if envs_reset or self._last_filter_state is None or len(self._episode_costs) != self.env.num_envs:
            # Fresh episodes (or a run resumed without its rollout state): every filter restarts at the next frame
            self._last_filter_state = None
            self._last_episode_starts = np.ones(self.env.num_envs, dtype=bool)
            self._episode_costs = np.zeros(self.env.num_envs)
        return result

    def _init_callback(self, callback: MaybeCallback, progress_bar: bool = False) -> BaseCallback:
        """Attach the on-policy ``LagrangeCallback`` unless the caller already passed one."""
        if not _has_lagrange_callback(callback):
            if callback is None:
                callback = [LagrangeCallback()]
            elif isinstance(callback, list):
                callback = [LagrangeCallback(), *callback]
            else:
                callback = [LagrangeCallback(), callback]
        return super()._init_callback(callback, progress_bar)

    def _sample_action(self, learning_starts: int, action_noise: Any = None, n_envs: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """
        Advance the training envs' latent filter on the last observation and act: ``tanh(N(0, 2^2))`` random actions
        during the warm-up (they advance the filter too), the stochastic actor afterwards.
        """
        assert self._last_obs is not None and isinstance(self._last_obs, np.ndarray)
        if self._last_filter_state is None:
            self._last_filter_state = self.policy.initial_state(n_envs)
        observation = th.as_tensor(self._last_obs, device=self.device)
        episode_start = th.as_tensor(self._last_episode_starts, dtype=th.bool, device=self.device)
        self.policy.set_training_mode(False)
        with th.inference_mode():
            z, z2 = self.policy.belief_step(observation, *self._last_filter_state, episode_start, deterministic=False)
            if self.num_timesteps < learning_starts:
                scaled_action = th.tanh(2.0 * th.randn(n_envs, self._action_dim, device=self.device))
            else:
                scaled_action = self.policy.actor(z)
        self._last_filter_state = (z2, scaled_action)
        buffer_action = scaled_action.cpu().numpy()
        return self.policy.unscale_action(buffer_action), buffer_action

    @property
    def _action_dim(self) -> int:
        return int(np.prod(self.action_space.shape))  # type: ignore[arg-type]

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        costs = np.array([cost_from_info(info) for info in infos])
        self._episode_costs += costs
        self.total_cost += float(costs.sum())
        for idx in np.flatnonzero(dones):
            self.ep_cost_buffer.append(float(self._episode_costs[idx]))
            self._episode_costs[idx] = 0.0
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        self._last_episode_starts = np.array(dones, dtype=bool)

    def dump_logs(self) -> None:
        sim_steps = self.num_timesteps * self.action_repeat
        if len(self.ep_cost_buffer) > 0:
            self.logger.record("rollout/ep_cost_mean", safe_mean(list(self.ep_cost_buffer)))
        self.logger.record("rollout/cost_rate", self.total_cost / max(sim_steps, 1))
        self.logger.record("time/sim_steps", sim_steps)
        super().dump_logs()

    # ----------------------------------------------------------------------------------------------------------------
    # Learning
    # ----------------------------------------------------------------------------------------------------------------

    def _check_finite(self, name: str, loss: th.Tensor) -> None:
        """Stop before an optimizer step would spread a NaN or inf into the weights."""
        if not bool(th.isfinite(loss).all()):
            raise RuntimeError(
                f"DS-SLAC's {name} became {loss.item()} at update {self._n_updates} (timestep {self.num_timesteps}); "
                "training stopped before the weights were corrupted. Check the env's observations, rewards and costs "
                "for NaN/inf, or lower the learning rates."
            )

    def _update_learning_rate(self, optimizers: list[th.optim.Optimizer] | th.optim.Optimizer) -> None:
        """
        Set the step sizes for the current timestep: ``optimizers`` (actor, critics, entropy coefficient) follow
        ``lr_schedule`` and the latent model ``latent_learning_rate``, each times ``lr_decay_multiplier``. A pure
        function of ``num_timesteps`` and the progress, so a resumed run continues with the right step sizes.
        """
        if not isinstance(optimizers, list):
            optimizers = [optimizers]
        factor = self.lr_decay_multiplier
        learning_rate = self.lr_schedule(self._current_progress_remaining) * factor
        latent_learning_rate = self.latent_learning_rate * factor
        self.logger.record("train/learning_rate", learning_rate)
        self.logger.record("train/latent_learning_rate", latent_learning_rate)
        for optimizer in optimizers:
            update_learning_rate(optimizer, learning_rate)
        update_learning_rate(self.policy.latent_optimizer, latent_learning_rate)

    def _latent_autocast(self) -> contextlib.AbstractContextManager:
        """bfloat16 autocast for the latent model's passes when ``bf16`` is set, else nothing."""
        if self.bf16:
            return th.autocast(self.device.type, dtype=th.bfloat16)
        return contextlib.nullcontext()

    def _pretrain_latent(self) -> None:
        """
        The one-off latent-model pre-training of Algorithm 1 (W_t updates on the random-policy data), after fixing the
        standardisation of vector observations from that data.
        """
        self.policy.set_observation_statistics(self.replay_buffer.stored_observations())
        losses = []
        progress = tqdm(total=self.latent_pretrain_steps, desc="latent pre-training", disable=self.verbose < 1)
        for done in range(0, self.latent_pretrain_steps, self._PRETRAIN_BURST):
            n_updates = min(self._PRETRAIN_BURST, self.latent_pretrain_steps - done)
            indices = self.replay_buffer.sample_indices(n_updates, self.latent_batch_size)
            for k in range(n_updates):
                losses.append(self._latent_update(self.replay_buffer.gather(indices[k]))["latent_loss"])
            progress.update(n_updates)
        progress.close()
        self.latent_pretrained = True
        if losses:
            self.logger.record("train/pretrain_latent_loss", float(th.stack(losses[-100:]).mean()))

    def _latent_update(self, batch: SequenceBatch, features: th.Tensor | None = None) -> dict[str, th.Tensor]:
        """
        One latent-model update on a batch of sequences (``features``: their encoder features, if already computed);
        returns its detached losses.
        """
        with self._latent_autocast():
            observations = self.policy.preprocess(batch.observations)
            loss, parts = self.policy.latent.loss(
                observations, batch.actions, batch.rewards, batch.costs, batch.terminated, features=features
            )
        self._check_finite("latent_loss", loss)
        self.policy.latent_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        th.nn.utils.clip_grad_norm_(self.policy.latent.parameters(), self.max_grad_norm)
        self.policy.latent_optimizer.step()
        return {"latent_loss": loss.detach(), **parts}

    def _update(self, indices: th.Tensor, batch_size: int) -> dict[str, th.Tensor]:
        """
        One gradient step of Algorithm 1: a latent-model update, then an actor-critic update.

        :param indices: windows from ``SequenceReplayBuffer.sample_indices``: ``latent_batch_size + batch_size`` of them
            (two independent batches), or ``max(latent_batch_size, batch_size)`` with ``share_latent_batch``
        """
        latent = self.policy.latent
        if not self.share_latent_batch:
            stats = self._latent_update(self.replay_buffer.gather(indices[: self.latent_batch_size]))
            batch = self.replay_buffer.gather(indices[self.latent_batch_size :])
            with th.no_grad(), self._latent_autocast():
                latents = latent.sample_latents(self.policy.preprocess(batch.observations), batch.actions)
            return {**stats, **self._actor_critic_update(batch, latents.float())}

        batch = self.replay_buffer.gather(indices)
        n_latent = self.latent_batch_size
        with self._latent_autocast():
            observations = self.policy.preprocess(batch.observations)
            latent_features = latent.encode(observations[:n_latent])
            with th.no_grad():
                features = latent_features.detach()
                if batch_size > n_latent:
                    features = th.cat([features, latent.encode(observations[n_latent:batch_size])])
                latents = latent.latents_from_features(features[:batch_size], batch.actions[:batch_size])
        latent_batch = SequenceBatch(*(field[:n_latent] for field in batch))
        stats = self._latent_update(latent_batch, features=latent_features)
        ac_batch = SequenceBatch(*(field[:batch_size] for field in batch))
        return {**stats, **self._actor_critic_update(ac_batch, latents.float())}

    @th.no_grad()
    def _td_targets(
        self, batch: SequenceBatch, latents: th.Tensor, ent_coef: th.Tensor, target_taus: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor]:
        """
        TD targets of both critics for the last transition of each sequence, ``z = latents[:, -2]`` to
        ``z' = latents[:, -1]``, with ``a' ~ pi(z')`` from the current actor; terminations stop the bootstrap, time
        limits (truncations) do not.

        :param batch: the sequences (B, L+1 frames)
        :param latents: their posterior samples (B, L+1, z_dim)
        :param ent_coef: the entropy coefficient (scalar or (1,))
        :param target_taus: the target quantile fractions (B, N')
        :return: ``r + gamma * (1 - terminated) * (min(Q1', Q2')(z', a') - alpha * log pi(a' | z'))`` (B, 1) and
            ``c + gamma_c * (1 - terminated) * Z'_tau'(z', a')`` (B, N')
        """
        policy = self.policy
        next_z = latents[:, -1]
        not_terminated = 1.0 - batch.terminated[:, -1:]
        next_actions, next_log_prob = policy.actor.action_log_prob(next_z)
        next_q = th.min(*policy.critic_target(next_z, next_actions)) - ent_coef * next_log_prob.unsqueeze(-1)
        target_q = batch.rewards[:, -1:] + not_terminated * self.gamma * next_q
        next_quantiles = policy.cost_critic_target(next_z, next_actions, target_taus)
        target_quantiles = batch.costs[:, -1:] + not_terminated * self.cost_gamma * next_quantiles
        return target_q, target_quantiles

    def _actor_critic_update(self, batch: SequenceBatch, latents: th.Tensor) -> dict[str, th.Tensor]:
        """
        One update of the reward critic, the cost critic, the actor and the entropy coefficient on the last transition
        of each sequence.

        :param batch: the sequences (B, L+1 frames)
        :param latents: their posterior samples (B, L+1, z_dim), no gradient
        """
        policy = self.policy
        n = batch.actions.shape[0]
        z = latents[:, -2]
        actions = batch.actions[:, -1]
        ent_coef = th.exp(self.log_ent_coef.detach()) if self.ent_coef_optimizer is not None else self.ent_coef_tensor
        multiplier = self.lagrange_multiplier

        target_taus = sample_taus(n, self.n_quantiles, self.device)
        target_q, target_quantiles = self._td_targets(batch, latents, ent_coef, target_taus)

        q1, q2 = policy.critic(z, actions)
        critic_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        self._check_finite("critic_loss", critic_loss)
        policy.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        th.nn.utils.clip_grad_norm_(policy.critic.parameters(), self.max_grad_norm)
        policy.critic_optimizer.step()

        taus = sample_taus(n, self.n_quantiles, self.device)
        current_quantiles = policy.cost_critic(z, actions, taus)
        if self.cost_critic == "mean":
            cost_critic_loss = F.mse_loss(current_quantiles[:, :1], target_quantiles[:, :1])
        else:
            cost_critic_loss = quantile_huber_loss(current_quantiles, target_quantiles, taus)
        self._check_finite("cost_critic_loss", cost_critic_loss)
        policy.cost_critic_optimizer.zero_grad(set_to_none=True)
        cost_critic_loss.backward()
        self._clip_cost_critic_gradients()
        policy.cost_critic_optimizer.step()

        # The actor's loss must not fill the critics' gradients
        policy.critic.requires_grad_(False)
        policy.cost_critic.requires_grad_(False)
        pi_actions, log_prob = policy.actor.action_log_prob(z)
        q_pi = th.min(*policy.critic(z, pi_actions))
        actor_taus = sample_taus(n, self.n_quantiles, self.device, risk_level=self.cvar_risk_level)
        cost_value = policy.cost_critic(z, pi_actions, actor_taus).mean(dim=1, keepdim=True)
        actor_loss = (ent_coef * log_prob.unsqueeze(-1) - q_pi + multiplier * cost_value).mean()
        policy.critic.requires_grad_(True)
        policy.cost_critic.requires_grad_(True)
        self._check_finite("actor_loss", actor_loss)
        policy.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()
        th.nn.utils.clip_grad_norm_(policy.actor.parameters(), self.actor_max_grad_norm)
        policy.actor_optimizer.step()

        stats = {
            "critic_loss": critic_loss.detach(),
            "cost_critic_loss": cost_critic_loss.detach(),
            "actor_loss": actor_loss.detach(),
            "cost_cvar": cost_value.detach().mean(),
            "ent_coef": ent_coef.detach().reshape(()),
        }
        if self.cvar_risk_level < 1.0:
            with th.no_grad():
                neutral_taus = sample_taus(n, self.n_quantiles, self.device)
                stats["cost_value"] = policy.cost_critic(z, pi_actions.detach(), neutral_taus).mean()
        else:
            stats["cost_value"] = stats["cost_cvar"]
        if self.lagrange == "critic":
            raw = sgd_lagrange_step(
                float(self.lagrange_raw.item()),
                float(stats["cost_cvar"]),
                self.critic_cost_budget,
                self.current_lagrange_learning_rate,
            )
            self.lagrange_raw.fill_(raw)
        if self.ent_coef_optimizer is not None:
            ent_coef_loss = -(self.log_ent_coef * (log_prob.detach() + self.target_entropy)).mean()
            self._check_finite("ent_coef_loss", ent_coef_loss)
            self.ent_coef_optimizer.zero_grad(set_to_none=True)
            ent_coef_loss.backward()
            th.nn.utils.clip_grad_norm_([self.log_ent_coef], self.max_grad_norm)
            self.ent_coef_optimizer.step()
            stats["ent_coef_loss"] = ent_coef_loss.detach()

        self._update_targets()
        return stats

    def _clip_cost_critic_gradients(self) -> None:
        """
        Clip the cost critic's gradient norm at ``max_grad_norm``: the IQN's cosine and quantile nets each on its own
        (the reference trains them with two optimizers, each clipped at 40), the mean critic as a whole.
        """
        cost_critic = self.policy.cost_critic
        if isinstance(cost_critic, IQNCostCritic):
            groups = [cost_critic.cosine_net.parameters(), cost_critic.quantile_net.parameters()]
        else:
            groups = [cost_critic.parameters()]
        for parameters in groups:
            th.nn.utils.clip_grad_norm_(parameters, self.max_grad_norm)

    def _update_targets(self) -> None:
        """Polyak update of both target critics, ``target += tau * (source - target)``, in one fused call."""
        policy = self.policy
        targets = [*policy.critic_target.parameters(), *policy.cost_critic_target.parameters()]
        sources = [*policy.critic.parameters(), *policy.cost_critic.parameters()]
        th._foreach_lerp_(targets, sources, self.tau)

    def train(self, gradient_steps: int, batch_size: int) -> None:
        """
        ``gradient_steps`` updates, each one latent-model update and one actor-critic update (Algorithm 1).
        The first call runs the latent pre-training once.
        """
        self.policy.set_training_mode(True)
        optimizers = [self.policy.actor_optimizer, self.policy.critic_optimizer, self.policy.cost_critic_optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)

        if not self.latent_pretrained:
            self._pretrain_latent()

        history: dict[str, list[th.Tensor]] = defaultdict(list)
        if self.share_latent_batch:
            windows_per_update = max(self.latent_batch_size, batch_size)
        else:
            windows_per_update = self.latent_batch_size + batch_size
        indices = self.replay_buffer.sample_indices(gradient_steps, windows_per_update)
        for k in range(gradient_steps):
            for key, value in self._update(indices[k], batch_size).items():
                history[key].append(value)
        self._n_updates += gradient_steps

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/lagrange_multiplier", self.lagrange_multiplier)
        for key, values in history.items():
            self.logger.record(f"train/{key}", float(th.stack(values).mean()))

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
        with tf32_matmul(self.tf32 and self.device.type == "cuda"):
            return super().learn(
                total_timesteps=total_timesteps,
                callback=callback,
                log_interval=log_interval,
                tb_log_name=tb_log_name,
                reset_num_timesteps=reset_num_timesteps,
                progress_bar=progress_bar,
            )

    # ----------------------------------------------------------------------------------------------------------------
    # Save / load
    # ----------------------------------------------------------------------------------------------------------------

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_last_filter_state", "_episode_costs", "ep_cost_buffer"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        state_dicts = [
            "policy",
            "policy.latent_optimizer",
            "policy.actor_optimizer",
            "policy.critic_optimizer",
            "policy.cost_critic_optimizer",
        ]
        if self.ent_coef_optimizer is not None:
            state_dicts.append("ent_coef_optimizer")
            return state_dicts, ["log_ent_coef", "lagrange_raw"]
        return state_dicts, ["ent_coef_tensor", "lagrange_raw"]
