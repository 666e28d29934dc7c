"""DS-SLAC: Distributional Safe Stochastic Latent Actor-Critic as a Stable-Baselines3 off-policy algorithm."""

import contextlib
import inspect
import math
import warnings
from collections import defaultdict, deque
from collections.abc import Callable, Iterator
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from sb3_contrib.common.utils import quantile_huber_loss
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, RolloutReturn, Schedule, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.utils import safe_mean, update_learning_rate
from stable_baselines3.common.vec_env import VecEnv
from torch.nn import functional as F
from tqdm.auto import tqdm

from sb3_dsslac.buffers import SequenceBatch, SequenceReplayBuffer
from sb3_dsslac.critics import IQNCostCritic, sample_taus
from sb3_dsslac.env_info import action_repeat_of, cost_from_info, episode_length_of
from sb3_dsslac.lagrange import LAGRANGE_RULES, LagrangeCallback, inverse_softplus, sgd_lagrange_step_on_device, softplus
from sb3_dsslac.optim import adam_step, clip_grads, init_adam_state
from sb3_dsslac.policies import LatentPolicy
from sb3_dsslac.timing import TimeAccount

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


def has_native_bf16(device: th.device) -> bool:
    """Whether ``device`` computes bfloat16 natively: a CUDA GPU that supports it, or a CPU with AVX512-BF16 or AMX."""
    if device.type == "cuda":
        return th.cuda.is_bf16_supported()
    if device.type == "cpu":
        return th.cpu._is_avx512_bf16_supported() or th.cpu._is_amx_tile_supported()
    return False


def resolve_bf16(bf16: bool | str, device: th.device) -> bool:
    """
    Whether the latent model's passes run under bfloat16 autocast: ``"auto"`` where the device computes bfloat16
    natively; ``True`` too, with a warning and float32 instead where it does not (emulated bfloat16 made the update
    7x slower on an AVX2-only CPU); ``False`` never.
    """
    if bf16 not in (True, False, "auto"):
        raise ValueError(f"bf16 must be True, False or 'auto', got {bf16!r}")
    if bf16 is False:
        return False
    native = has_native_bf16(device)
    if bf16 is True and not native:
        warnings.warn(
            f"bf16=True, but this {device.type} has no native bfloat16 (no AVX512-BF16 or AMX on a CPU), where it is "
            "several times slower than float32: the latent model stays in float32. Pass bf16='auto' to choose silently."
        )
    return native


def _has_lagrange_callback(callback: MaybeCallback) -> bool:
    if isinstance(callback, LagrangeCallback):
        return True
    if isinstance(callback, CallbackList):
        return any(_has_lagrange_callback(child) for child in callback.callbacks)
    if isinstance(callback, list):
        return any(_has_lagrange_callback(child) for child in callback)
    return False


def _reduce_burst(name: str, values: th.Tensor) -> th.Tensor:
    """A statistic over a burst (U,) -> (): the least of a ``*_min`` one, the most of a ``*_max`` one, else the mean."""
    if name.endswith("_min"):
        return values.amin()
    if name.endswith("_max"):
        return values.amax()
    return values.mean()


# Keywords of both DSSLAC and LatentPolicy, with LatentPolicy's defaults (the code behind the thesis numbers)
SHARED_POLICY_KEYWORDS: dict[str, Any] = {
    name: inspect.signature(LatentPolicy).parameters[name].default
    for name in ("image_noise", "cost_loss_weight", "cost_positive_weight", "latent_learning_rate", "cost_critic")
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
    ``info["cost"]``. Defaults are the thesis's Table 5.2 and the code behind its numbers. The keywords of
    ``SHARED_POLICY_KEYWORDS`` are also ``LatentPolicy``'s: None takes ``policy_kwargs``' value, else ``LatentPolicy``'s
    default; given both here and in ``policy_kwargs``, they must agree, else a ValueError.

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
        ``lr_decay_factor``; None: no decay. The code behind the thesis numbers halves them all once at 230_000 (its
        ``MultiStepLR`` milestone 400, stepped every 1000 simulator steps after the 60k-step warm-up: 460k simulator
        steps), which the ``thesis`` presets set
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
        self.cost_target = cost_target
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
        self.time_account = TimeAccount()  # wall seconds by activity, logged as time/<activity>_s
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
        if cost_target is not None and not 0.0 <= cost_target <= cost_limit:
            raise ValueError(f"cost_target must be in [0, cost_limit={cost_limit:g}] or None, got {cost_target}")
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
    def episode_cost_target(self) -> float:
        """The episode cost the multiplier aims at: ``cost_target``, else ``cost_limit``."""
        return self.cost_limit if self.cost_target is None else self.cost_target

    @property
    def cost_budget_per_step(self) -> float:
        """The multiplier's episode target spread over the agent steps of an episode (25 / 500 = 0.05 for the thesis)."""
        assert self.episode_length is not None
        return self.episode_cost_target / self.episode_length

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
        return softplus(float(self.lagrange_raw.numpy()))

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
        self._bf16_active = resolve_bf16(self.bf16, self.device)
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
            self.ent_coef_optimizer = th.optim.Adam([self.log_ent_coef], lr=self.lr_schedule(1), fused=True)
        else:
            self.ent_coef_tensor = th.tensor(float(self.ent_coef), device=self.device)
        self._setup_update_state()

    def _setup_update_state(self) -> None:
        """The device tensors that a burst of updates reads and writes instead of host values, and the compiled step."""
        policy = self.policy
        optimizers = [policy.latent_optimizer, policy.actor_optimizer, policy.critic_optimizer, policy.cost_critic_optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._learning_rates = {optimizer: th.zeros((), device=self.device) for optimizer in optimizers}
        self._lagrange_raw_device = th.zeros((), device=self.device)
        # float64 like the host's step sizes: the SGD rules step with exactly the same value on the host and the device
        self._lagrange_learning_rate_device = th.zeros((), dtype=th.float64, device=self.device)
        self._first_nonfinite_update = th.full((len(self._GUARDED_LOSSES),), -1, dtype=th.long, device=self.device)
        self._burst_update_index = th.zeros((), dtype=th.long, device=self.device)
        # How many steps before their own each guarded loss is computed when the updates are pipelined (_gradient_step)
        lags = [0 if name == "latent_loss" else 1 for name in self._GUARDED_LOSSES]
        self._pipelined_lags = th.tensor(lags, dtype=th.long, device=self.device)
        self._target_params = [*policy.critic_target.parameters(), *policy.cost_critic_target.parameters()]
        self._source_params = [*policy.critic.parameters(), *policy.cost_critic.parameters()]
        # The reference trains the IQN's cosine and quantile nets with two optimizers, each clipped at 40: clipped apart
        self._cost_critic_clip_groups: tuple[slice, ...] = (slice(None),)
        if isinstance(policy.cost_critic, IQNCostCritic):
            n_cosine = len(list(policy.cost_critic.cosine_net.parameters()))
            assert list(policy.cost_critic.parameters())[:n_cosine] == list(policy.cost_critic.cosine_net.parameters())
            self._cost_critic_clip_groups = (slice(0, n_cosine), slice(n_cosine, None))
        self._compiled_steps: dict[str, Callable[..., dict[str, th.Tensor]]] = {}
        self._compiled_once: set[str] = set()
        if self.compile_updates:
            if not hasattr(th._dynamo.config, "trace_autograd_ops"):
                warnings.warn(
                    f"compile_updates needs a torch whose compiler traces the backward pass (2.13 or newer), this is "
                    f"{th.__version__}: the updates run eagerly"
                )
                return
            # CUDA graphs on a GPU: the whole step is replayed as one graph. On a CPU the tensors keep the layouts that
            # eager mode found fastest: inductor's own choice, channels-last convolutions, transposed the 3-channel frames
            # and reconstructions on every step (28.5 against 25.7 updates/s at cpu_pixels32 sizes, one thread, AMD EPYC)
            if self.device.type == "cuda":
                options: dict[str, Any] = {"mode": "reduce-overhead"}
            else:
                options = {"options": {"layout_optimization": False}}
            self._compiled_steps = {
                step.__name__: th.compile(step, fullgraph=True, **options)
                for step in (self._gradient_step, self._last_actor_critic_step)
            }

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

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """
        Advance the training envs' latent filter on the last observation and act: ``tanh(N(0, 2^2))`` random actions
        during the warm-up (they advance the filter too), the stochastic actor afterwards. No action noise.
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
        if not np.isfinite(buffer_action).all():
            # Weights that overflowed in the last burst's final update, or finite weights whose filter overflows on a
            # real frame: either way no later loss would be computed before the env rejects the action
            raise RuntimeError(
                f"DS-SLAC's action became NaN or inf at timestep {self.num_timesteps} (after update {self._n_updates}): "
                "the latent filter or the actor overflowed, so the weights may hold NaN or huge values: go back to the "
                "last checkpoint. Check train/kl and train/image_loss for a spike, or lower latent_learning_rate."
            )
        return self.policy.unscale_action(buffer_action), buffer_action

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        train_freq: TrainFreq,
        replay_buffer: ReplayBuffer,
        action_noise: ActionNoise | None = None,
        learning_starts: int = 0,
        log_interval: int | None = None,
    ) -> RolloutReturn:
        """SB3's ``collect_rollouts``, its time counted as acting (callbacks that measure their own excepted)."""
        with self.time_account.measure("acting"):
            return super().collect_rollouts(
                env, callback, train_freq, replay_buffer, action_noise, learning_starts, log_interval
            )

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
        """SB3's logs, with the episode costs, the simulator steps and the time account; its time counted as logging."""
        with self.time_account.measure("logging"):
            for name, seconds in self.time_account.summary().items():
                self.logger.record(f"time/{name}_s", round(seconds, 1))
            sim_steps = self.num_timesteps * self.action_repeat
            if len(self.ep_cost_buffer) > 0:
                self.logger.record("rollout/ep_cost_mean", safe_mean(list(self.ep_cost_buffer)))
            self.logger.record("rollout/cost_rate", self.total_cost / max(sim_steps, 1))
            self.logger.record("time/sim_steps", sim_steps)
            if hasattr(super(), "dump_logs"):
                super().dump_logs()
            else:  # SB3 before 2.6 names it _dump_logs
                super()._dump_logs()

    _dump_logs = dump_logs  # the name SB3 before 2.6 calls

    # ----------------------------------------------------------------------------------------------------------------
    # Learning
    # ----------------------------------------------------------------------------------------------------------------

    # Losses checked for NaN/inf on the device during a burst, in this order (see ``_raise_if_not_finite``)
    _GUARDED_LOSSES = ("latent_loss", "critic_loss", "cost_critic_loss", "actor_loss", "ent_coef_loss")

    def _record_finite(self, losses: dict[str, th.Tensor], pipelined: bool = False) -> None:
        """
        Note on the device, without reading it, the first update of this burst in which each guarded loss of
        ``losses`` (detached scalars; the guarded ones present must be a run of ``_GUARDED_LOSSES``) is NaN or inf: one
        check for all of them. The burst reads the notes once, at its end (``_raise_if_not_finite``).

        :param pipelined: the actor-critic losses belong to the step before the current one (``_gradient_step``)
        """
        names = [name for name in self._GUARDED_LOSSES if name in losses]
        start = self._GUARDED_LOSSES.index(names[0])
        assert tuple(names) == self._GUARDED_LOSSES[start : start + len(names)], names
        first = self._first_nonfinite_update[start : start + len(names)]
        not_finite = ~th.isfinite(th.stack([losses[name] for name in names]))
        update = self._burst_update_index
        if pipelined:
            update = update - self._pipelined_lags[start : start + len(names)]
        first.copy_(th.where((first < 0) & not_finite, update, first))

    def _raise_if_not_finite(self, first_nonfinite: np.ndarray) -> None:
        """Stop training, naming the loss and the update, when a burst noted a NaN or inf loss."""
        # The earliest update, and in it the first loss computed (the others follow from it)
        bad = [(int(update), index) for index, update in enumerate(first_nonfinite) if update >= 0]
        if bad:
            update, index = min(bad)
            name = self._GUARDED_LOSSES[index]
            raise RuntimeError(
                f"DS-SLAC's {name} became NaN or inf at update {self._n_updates + update} (timestep {self.num_timesteps}); "
                "training stopped at the end of that burst of updates, so the weights may hold NaN: go back to the last "
                "checkpoint. Check the env's observations, rewards and costs for NaN/inf, or lower the learning rates."
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
        """bfloat16 autocast for the latent model's passes when bfloat16 is on (``bf16``), else nothing."""
        if self._bf16_active:
            return th.autocast(self.device.type, dtype=th.bfloat16)
        return contextlib.nullcontext()

    def _begin_burst(self) -> None:
        """
        Bring the device copies of the step sizes and the multiplier up to date and clear the NaN notes: the update reads
        no Python value that changes during training, so a compiled update never recompiles for one.
        """
        for optimizer, learning_rate in self._learning_rates.items():
            learning_rate.fill_(optimizer.param_groups[0]["lr"])
            if self._compiled_steps:
                init_adam_state(optimizer)
        self._lagrange_raw_device.copy_(self.lagrange_raw)
        self._lagrange_learning_rate_device.fill_(self.current_lagrange_learning_rate)
        self._first_nonfinite_update.fill_(-1)
        self._burst_update_index.zero_()

    def _end_burst(self, history: dict[str, list[th.Tensor]]) -> dict[str, float]:
        """
        The one host read of a burst: the mean of each logged statistic (the smallest of a ``*_min`` one, the largest of
        a ``*_max`` one), the NaN notes and, for the "critic" rule, the multiplier. Raises if a loss became NaN or inf.
        """
        means = [_reduce_burst(name, th.stack(values).float()) for name, values in history.items()]
        packed = th.cat([th.stack(means), self._first_nonfinite_update.float(), self._lagrange_raw_device.view(1).float()])
        values = packed.cpu().numpy().astype(np.float64)
        n_stats = len(means)
        self._raise_if_not_finite(values[n_stats : n_stats + len(self._GUARDED_LOSSES)])
        if self.lagrange == "critic":
            self.lagrange_raw.fill_(values[-1])
        return dict(zip(history, values[:n_stats].tolist(), strict=True))

    def _pretrain_latent(self) -> None:
        """
        The one-off latent-model pre-training of Algorithm 1 (W_t updates on the random-policy data), after fixing the
        standardisation of vector observations from that data.
        """
        self.policy.set_observation_statistics(self.replay_buffer.stored_observations())
        losses: list[th.Tensor] = []
        progress = tqdm(total=self.latent_pretrain_steps, desc="latent pre-training", disable=self.verbose < 1)
        for done in range(0, self.latent_pretrain_steps, self._PRETRAIN_BURST):
            n_updates = min(self._PRETRAIN_BURST, self.latent_pretrain_steps - done)
            indices = self.replay_buffer.sample_indices(n_updates, self.latent_batch_size)
            self._begin_burst()
            history = defaultdict(list)
            for k in range(n_updates):
                stats, _ = self._latent_update(self.replay_buffer.gather(indices[k]))
                self._record_finite(stats)
                history["latent_loss"].append(stats["latent_loss"])
                self._burst_update_index.add_(1)
            losses = [*losses, *history["latent_loss"]][-100:]
            self._end_burst(history)
            progress.update(n_updates)
        progress.close()
        self.latent_pretrained = True
        if losses:
            self.logger.record("train/pretrain_latent_loss", float(th.stack(losses[-100:]).mean()))

    def _latent_update(
        self, batch: SequenceBatch, features: th.Tensor | None = None, filter_batch: SequenceBatch | None = None
    ) -> tuple[dict[str, th.Tensor], th.Tensor | None]:
        """
        One latent-model update on a batch of sequences (``features``: their encoder features, if already computed).

        :param filter_batch: other sequences to filter, without gradient, in the same rollout (before the update)
        :return: the update's detached losses, and the posterior samples of ``filter_batch`` (B', L+1, z_dim) or None
        """
        with self._latent_autocast():
            observations = self.policy.preprocess(batch.observations)
            other = None
            if filter_batch is not None:
                other = (self.policy.preprocess(filter_batch.observations), filter_batch.actions)
            loss, parts, latents = self.policy.latent.loss_and_filter(
                observations, batch.actions, batch.rewards, batch.costs, batch.terminated, features=features, other=other
            )
        self._step(self.policy.latent_optimizer, loss, self.max_grad_norm)
        return {"latent_loss": loss.detach(), **parts}, latents

    def _step(
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
        adam_step(optimizer, grads, self._learning_rates[optimizer])

    def _gradient_step(self, batch: SequenceBatch, waiting: SequenceBatch | None) -> dict[str, th.Tensor]:
        """
        One gradient step of Algorithm 1, on the device and free of host syncs: a latent-model update, then an
        actor-critic update (``compile_updates`` compiles this whole method).

        As in the reference code, the actor-critic batch is filtered by the latent model after the latent update of its
        step. That filtering runs in the rollout of the next step's latent update, one rollout over both batches: each
        step updates the actor and critics on the previous step's batch (``waiting``) and leaves its own for the next
        step, or for ``_last_actor_critic_step`` at the end of the burst. The latent model and the actor-critic share no
        parameter, so this order computes the same updates with one rollout and first-frame pass fewer per step (the
        waiting batch is still encoded on its own, without gradient).

        :param batch: the sampled windows: ``latent_batch_size + batch_size`` of them (two independent batches, the
            actor-critic one waits), or ``max(latent_batch_size, batch_size)`` with ``share_latent_batch``
        :param waiting: the previous step's actor-critic batch, None in a burst's first step or with ``share_latent_batch``
        :return: the detached statistics of the step
        """
        latent = self.policy.latent
        n_latent, batch_size = self.latent_batch_size, self.batch_size
        latent_batch = SequenceBatch(*(field[:n_latent] for field in batch))
        if not self.share_latent_batch:
            stats, latents = self._latent_update(latent_batch, filter_batch=waiting)
            if waiting is not None:
                stats.update(self._actor_critic_update(waiting, latents.float()))
        else:
            ac_batch = SequenceBatch(*(field[:batch_size] for field in batch))
            with self._latent_autocast():
                observations = self.policy.preprocess(batch.observations)
                latent_features = latent.encode(observations[:n_latent])
                with th.no_grad():
                    features = latent_features.detach()
                    if batch_size > n_latent:
                        features = th.cat([features, latent.encode(observations[n_latent:batch_size])])
                    latents = latent.latents_from_features(features[:batch_size], ac_batch.actions)
            stats, _ = self._latent_update(latent_batch, features=latent_features)
            stats.update(self._actor_critic_update(ac_batch, latents.float()))
        self._record_finite(stats, pipelined=not self.share_latent_batch)
        self._burst_update_index.add_(1)
        return stats

    def _last_actor_critic_step(self, batch: SequenceBatch) -> dict[str, th.Tensor]:
        """
        The actor-critic update on the actor-critic batch of a burst's last gradient step (see ``_gradient_step``),
        filtered by the latent model as that step left it; its NaN notes name that step.
        """
        with th.no_grad(), self._latent_autocast():
            latents = self.policy.latent.sample_latents(self.policy.preprocess(batch.observations), batch.actions)
        stats = self._actor_critic_update(batch, latents.float())
        self._record_finite(stats, pipelined=True)
        return stats

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
        next_q = policy.critic_target(next_z, next_actions).amin(dim=0) - ent_coef * next_log_prob.unsqueeze(-1)
        target_q = batch.rewards[:, -1:] + not_terminated * self.gamma * next_q
        next_quantiles = policy.cost_critic_target(next_z, next_actions, target_taus)
        target_quantiles = batch.costs[:, -1:] + not_terminated * self.cost_gamma * next_quantiles
        return target_q, target_quantiles

    def _actor_critic_update(self, batch: SequenceBatch, latents: th.Tensor) -> dict[str, th.Tensor]:
        """
        One update of the reward critic, the cost critic, the actor and the entropy coefficient on the last transition
        of each sequence, then of the target critics.

        :param batch: the sequences (B, L+1 frames)
        :param latents: their posterior samples (B, L+1, z_dim), no gradient
        """
        policy = self.policy
        n = batch.actions.shape[0]
        z = latents[:, -2]
        actions = batch.actions[:, -1]
        ent_coef = th.exp(self.log_ent_coef.detach()) if self.ent_coef_optimizer is not None else self.ent_coef_tensor
        multiplier = F.softplus(self._lagrange_raw_device)

        target_taus = sample_taus(n, self.n_quantiles, self.device)
        target_q, target_quantiles = self._td_targets(batch, latents, ent_coef, target_taus)  # under no_grad

        q_values = policy.critic(z, actions)  # (2, B, 1)
        critic_loss = (q_values - target_q).pow(2).mean(dim=(1, 2)).sum()  # MSE of each network, summed
        self._step(policy.critic_optimizer, critic_loss, self.max_grad_norm)

        taus = sample_taus(n, self.n_quantiles, self.device)
        current_quantiles = policy.cost_critic(z, actions, taus)
        if self.cost_critic == "mean":
            cost_critic_loss = F.mse_loss(current_quantiles[:, :1], target_quantiles[:, :1])
        else:
            cost_critic_loss = quantile_huber_loss(current_quantiles, target_quantiles, cum_prob=taus.unsqueeze(-1))
        self._step(policy.cost_critic_optimizer, cost_critic_loss, self.max_grad_norm, self._cost_critic_clip_groups)

        # The actor's gradients are taken for its own parameters only: the critics' weights get none
        pi_actions, log_prob = policy.actor.action_log_prob(z)
        q_pi = policy.critic(z, pi_actions).amin(dim=0)
        actor_taus = sample_taus(n, self.n_quantiles, self.device, risk_level=self.cvar_risk_level)
        cost_value = policy.cost_critic(z, pi_actions, actor_taus).mean(dim=1, keepdim=True)
        actor_loss = (ent_coef * log_prob.unsqueeze(-1) - q_pi + multiplier * cost_value).mean()
        self._step(policy.actor_optimizer, actor_loss, self.actor_max_grad_norm)

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
            with th.no_grad():
                raw = sgd_lagrange_step_on_device(
                    self._lagrange_raw_device, stats["cost_cvar"], self.critic_cost_budget, self._lagrange_learning_rate_device
                )
                self._lagrange_raw_device.copy_(raw)
        if self.ent_coef_optimizer is not None:
            ent_coef_loss = -(self.log_ent_coef * (log_prob.detach() + self.target_entropy)).mean()
            self._step(self.ent_coef_optimizer, ent_coef_loss, self.max_grad_norm)
            stats["ent_coef_loss"] = ent_coef_loss.detach()

        self._update_targets()
        return stats

    def _update_targets(self) -> None:
        """Polyak update of both target critics, ``target += tau * (source - target)``, in one fused call."""
        with th.no_grad():
            th._foreach_lerp_(self._target_params, self._source_params, self.tau)

    def train(self, gradient_steps: int, batch_size: int) -> None:
        """
        ``gradient_steps`` updates, each one latent-model update and one actor-critic update (Algorithm 1), with one
        host read for the whole burst. The first call runs the latent pre-training once.
        """
        self.policy.set_training_mode(True)
        optimizers = [self.policy.actor_optimizer, self.policy.critic_optimizer, self.policy.cost_critic_optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)

        if not self.latent_pretrained:
            with self.time_account.measure("latent_pretraining"):
                self._pretrain_latent()

        with self.time_account.measure("updates"):
            self._train_burst(gradient_steps, batch_size)

    def _train_burst(self, gradient_steps: int, batch_size: int) -> None:
        """One burst of ``gradient_steps`` updates on freshly sampled windows, and its logs."""
        if self.share_latent_batch:
            windows_per_update = max(self.latent_batch_size, batch_size)
        else:
            windows_per_update = self.latent_batch_size + batch_size
        indices = self.replay_buffer.sample_indices(gradient_steps, windows_per_update)
        means = self._end_burst(self._burst(indices))
        self._n_updates += gradient_steps

        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/lagrange_multiplier", self.lagrange_multiplier)
        for key, value in means.items():
            self.logger.record(f"train/{key}", value)

    def _burst(self, indices: th.Tensor) -> dict[str, list[th.Tensor]]:
        """
        The gradient steps on the windows ``indices[k]`` (from ``sample_indices``), each actor-critic batch updated on in
        the step after its own (``_gradient_step``) and the last one after them; their statistics by name, in order.
        """
        self._begin_burst()
        history: dict[str, list[th.Tensor]] = defaultdict(list)
        waiting = None
        for k in range(indices.shape[0]):
            batch = self.replay_buffer.gather(indices[k])
            for key, value in self._run_step(self._gradient_step, batch, waiting).items():
                history[key].append(value)
            if not self.share_latent_batch:
                waiting = SequenceBatch(*(field[self.latent_batch_size :] for field in batch))
        if waiting is not None:
            for key, value in self._run_step(self._last_actor_critic_step, waiting).items():
                history[key].append(value)
        return history

    def _run_step(self, step: Callable[..., dict[str, th.Tensor]], *args: Any) -> dict[str, th.Tensor]:
        """
        ``step(*args)`` (``_gradient_step`` or ``_last_actor_critic_step``), compiled with ``compile_updates`` (falling
        back to eager, with a warning, if that fails).
        """
        compiled = self._compiled_steps.get(step.__name__)
        if compiled is None:
            return step(*args)
        # The first call compiles (a minute or more on a CPU): its time is the compilation's
        first_call = self.time_account.measure("compilation") if step.__name__ not in self._compiled_once else None
        try:
            with th._dynamo.config.patch(trace_autograd_ops=True), first_call or contextlib.nullcontext():
                if self.device.type != "cuda":
                    return compiled(*args)
                # A CUDA graph's replay reuses its output memory: keep copies of this step's statistics
                th.compiler.cudagraph_mark_step_begin()
                return {key: value.clone() for key, value in compiled(*args).items()}
        except Exception as error:  # the compiler's errors have no common base class
            if step.__name__ in self._compiled_once:
                raise
            warnings.warn(f"compile_updates: the update could not be compiled ({type(error).__name__}: {error}); runs eagerly")
            self._compiled_steps = {}
            return step(*args)
        finally:
            self._compiled_once.add(step.__name__)

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

    # ----------------------------------------------------------------------------------------------------------------
    # Save / load
    # ----------------------------------------------------------------------------------------------------------------

    def _excluded_save_params(self) -> list[str]:
        return [
            *super()._excluded_save_params(),
            "_last_filter_state",
            "_episode_costs",
            "ep_cost_buffer",
            # rebuilt by _setup_model
            "_bf16_active",
            "_learning_rates",
            "_lagrange_raw_device",
            "_lagrange_learning_rate_device",
            "_first_nonfinite_update",
            "_burst_update_index",
            "_pipelined_lags",
            "_target_params",
            "_source_params",
            "_cost_critic_clip_groups",
            "_compiled_steps",
            "_compiled_once",
        ]

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
