"""LatentPolicy: the latent model, actor, twin reward critic and IQN cost critic of DS-SLAC behind SB3's policy API."""

import inspect
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule

from sb3_dsslac.common.env_info import check_observations_finite
from sb3_dsslac.nn.actor import LatentActor
from sb3_dsslac.nn.critics import IQNCostCritic, MeanCostCritic, TwinQCritic
from sb3_dsslac.nn.latent import STD_EPS, THESIS_IMAGE_CHANNELS, LatentModel
from sb3_dsslac.nn.memory import BeliefMemory
from sb3_dsslac.nn.optim import fast_adam_kwargs
from sb3_dsslac.nn.recurrent_latent import RecurrentLatentModel

# Filter state carried through ``predict``: (z2 (n_envs, z2_dim), previous action scaled to [-1, 1] (n_envs, action_dim),
# the actor-critic memory (n_envs, actor_critic_memory), 0 wide without one). A state of the first two alone is taken
# for a policy without a memory
FilterState = tuple[np.ndarray, ...]


# The latent model of each ``latent_recurrence``
LATENT_MODELS: dict[str, type[LatentModel]] = {"gaussian": LatentModel, "gru": RecurrentLatentModel}


class LatentPolicy(BasePolicy):
    """
    The DS-SLAC policy: a sequential latent model filters the observations into a belief ``z = [z1, z2]``, on which
    a tanh-Gaussian actor, a twin reward critic and an implicit-quantile cost critic operate.

    ``predict(obs, state, episode_start)`` runs one step of the latent filter and returns its new state, as
    ``RecurrentPPO`` does, so ``evaluate_policy`` and ``EvalCallback`` work unchanged.

    :param observation_space: Box of uint8 images (C, H, W), both sides at least 32 pixels (any with an encoder and a
        decoder of the user's), or a 1-D float Box
    :param action_space: Box action space
    :param lr_schedule: learning rate schedule of the actor and critics
    :param z1_dim: size of the stochastic latent z1
    :param z2_dim: size of the deterministic-path latent z2
    :param feature_dim: size of the encoder's per-frame feature
    :param hidden_units: hidden layers of every MLP (latent distributions, actor, reward critic)
    :param n_cosines: cosine features of the IQN tau embedding
    :param cost_critic: "iqn" (DS-SLAC's implicit-quantile critic) or "mean" (Safe SLAC's expectation critic)
    :param cost_critic_hidden_dim: hidden width of the IQN head
    :param cost_critic_initial_value: initial output of the "mean" critic (Safe SLAC: the discounted budget)
    :param image_noise: variance of the Gaussian observation likelihood (0.4 in the thesis code: std 0.632)
    :param reward_loss_weight: weight of the Gaussian reward likelihood in the latent loss (1 in the thesis). Its one
        scalar per step is otherwise outweighed by the 12,288 pixel terms of a 64x64x3 frame
    :param cost_loss_weight: weight of the Bernoulli cost likelihood in the latent loss
    :param cost_positive_weight: extra weight of unsafe (cost > 0) steps in the cost likelihood
    :param image_channels: output channels of the conv encoder's four stride-2 layers, mirrored by the decoder; the
        thesis's (32, 64, 128, 256) by default. Narrower convolutions are most of what makes a pixel update cheap.
        Frames of up to 56 pixels use the first three, of over 112 pixels repeat the last (``LatentModel``)
    :param encoder_class: an encoder of the user's in place of the built-in one, as SB3's ``features_extractor_class``:
        ``encoder_class(observation_shape, feature_dim, **encoder_kwargs)``, a module mapping preprocessed observations
        (N, *observation_shape) (images channels first, in [0, 1]) to (N, feature_dim) or (N, feature_dim, 1, 1)
    :param encoder_kwargs: further keywords of ``encoder_class``
    :param decoder_class: a decoder of the user's in place of the built-in one: ``decoder_class(z_dim,
        observation_shape, **decoder_kwargs)``, a module mapping latents (N, z_dim) (``z_dim = z1_dim + z2_dim``) to the
        mean (N, *observation_shape) of the observation Gaussian
    :param decoder_kwargs: further keywords of ``decoder_class``
    :param latent_min_std: the floor on the std of the latent Gaussians (1e-5 in the thesis code)
    :param latent_max_std: the ceiling on their std (None, the thesis code's: none)
    :param latent_mean_bound: the bound on their means' absolute value (None, the thesis code's: none). With a ceiling
        and a bound the latents cannot run away (see ``GaussianBounds``)
    :param latent_kl_balance: None (the thesis's) or the share of the KL's gradient that trains the prior
        (``LatentModel``'s ``kl_balance``; 0.8 in LAMBDA)
    :param latent_overshooting: the longest open-loop roll of z1's prior in the latent loss (``LatentModel``'s
        ``overshooting_depth``): 1, the thesis's, the one-step KL alone; up to ``sequence_length``
    :param latent_reward_overshooting: the weight of the reward likelihood on the overshooting's open-loop rolls
        (``LatentModel``'s ``reward_overshooting_weight``): 0, the thesis's, none; positive needs ``latent_overshooting
        >= 2``. The reward of each rolled step depends on where the goal is, seen or not
    :param latent_overshooting_stride: roll from every start of a window (1) or from every s-th only
        (``LatentModel``'s ``overshooting_stride``): as deep, at about 1/s of the rows
    :param latent_recurrence: how z2 follows from the previous step: "gaussian" (the thesis's: a Gaussian MLP of
        ``[z1_{t+1}, z2_t, a_t]``, noise at every step) or "gru" (a deterministic GRU state, as in an RSSM:
        ``RecurrentLatentModel``), which can hold what left the view
    :param latent_learning_rate: Adam step size of the latent model
    :param previous_action_input: the actor and both critics take the previous action beside the belief, ``[z_t,
        a_{t-1}]`` (zero at an episode's first step), instead of ``z_t`` alone (the thesis's). The belief holds what the
        last few frames show; when they show nothing to steer by, the previous action says which way the agent turned
    :param actor_critic_memory: size of a recurrent memory over the beliefs (``BeliefMemory``) that the actor and both
        critics take beside them, trained by the reward critic's TD error; 0 (the thesis's): none. In the update it
        runs over each window from zero, so the learned transitions should leave it a few frames of the window before
        them (``DSSLAC``'s ``actor_critic_transitions`` below ``sequence_length``)
    :param normalize_images: divide uint8 images by 255
    :param normalize_vectors: standardise vector observations with the mean and std of the warm-up data (set once by
        ``set_observation_statistics``; saved with the policy). Without it, the fixed-variance likelihood lets large
        dimensions (an accelerometer's 9.81) drown small informative ones (lidar in [0, 1])
    :param optimizer_class: optimizer of every network
    :param optimizer_kwargs: extra optimizer keywords (Adam and AdamW get ``fused=True`` unless ``fused`` or ``foreach``
        is given)
    """

    latent: LatentModel
    memory: BeliefMemory | None
    actor: LatentActor
    critic: TwinQCritic
    critic_target: TwinQCritic
    cost_critic: IQNCostCritic | MeanCostCritic
    cost_critic_target: IQNCostCritic | MeanCostCritic

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        z1_dim: int = 32,
        z2_dim: int = 200,
        feature_dim: int = 200,
        hidden_units: tuple[int, ...] = (256, 256),
        n_cosines: int = 64,
        cost_critic: str = "iqn",
        cost_critic_hidden_dim: int = 512,
        cost_critic_initial_value: float = 0.0,
        image_noise: float = 0.4,
        reward_loss_weight: float = 1.0,
        cost_loss_weight: float = 30.0,
        cost_positive_weight: float = 100.0,
        image_channels: tuple[int, ...] = THESIS_IMAGE_CHANNELS,
        encoder_class: type[th.nn.Module] | None = None,
        encoder_kwargs: dict[str, Any] | None = None,
        decoder_class: type[th.nn.Module] | None = None,
        decoder_kwargs: dict[str, Any] | None = None,
        latent_min_std: float = STD_EPS,
        latent_max_std: float | None = None,
        latent_mean_bound: float | None = None,
        latent_kl_balance: float | None = None,
        latent_overshooting: int = 1,
        latent_reward_overshooting: float = 0.0,
        latent_overshooting_stride: int = 1,
        latent_recurrence: str = "gaussian",
        latent_learning_rate: float = 1e-4,
        previous_action_input: bool = False,
        actor_critic_memory: int = 0,
        normalize_images: bool = True,
        normalize_vectors: bool = True,
        optimizer_class: type[th.optim.Optimizer] = th.optim.Adam,
        optimizer_kwargs: dict[str, Any] | None = None,
    ):
        super().__init__(
            observation_space,
            action_space,
            optimizer_class=optimizer_class,
            optimizer_kwargs=optimizer_kwargs,
            normalize_images=normalize_images,
            squash_output=True,
        )
        self.action_dim = int(np.prod(action_space.shape))  # actions are flat vectors (n, action_dim) inside the policy
        self.z1_dim = z1_dim
        self.z2_dim = z2_dim
        self.feature_dim = feature_dim
        self.hidden_units = tuple(hidden_units)
        self.n_cosines = n_cosines
        if cost_critic not in ("iqn", "mean"):
            raise ValueError(f"cost_critic must be 'iqn' (DS-SLAC) or 'mean' (Safe SLAC), got {cost_critic!r}")
        self.cost_critic_type = cost_critic
        self.cost_critic_hidden_dim = cost_critic_hidden_dim
        self.cost_critic_initial_value = cost_critic_initial_value
        self.image_noise = image_noise
        self.reward_loss_weight = reward_loss_weight
        self.cost_loss_weight = cost_loss_weight
        self.cost_positive_weight = cost_positive_weight
        self.image_channels = tuple(image_channels)
        self.encoder_class, self.encoder_kwargs = encoder_class, encoder_kwargs
        self.decoder_class, self.decoder_kwargs = decoder_class, decoder_kwargs
        self.latent_min_std = latent_min_std
        self.latent_max_std = latent_max_std
        self.latent_mean_bound = latent_mean_bound
        self.latent_kl_balance = latent_kl_balance
        self.latent_overshooting = latent_overshooting
        self.latent_reward_overshooting = latent_reward_overshooting
        self.latent_overshooting_stride = latent_overshooting_stride
        if latent_recurrence not in LATENT_MODELS:
            raise ValueError(f"latent_recurrence must be one of {sorted(LATENT_MODELS)}, got {latent_recurrence!r}")
        self.latent_recurrence = latent_recurrence
        self.latent_learning_rate = latent_learning_rate
        self.previous_action_input = previous_action_input
        if actor_critic_memory < 0:
            raise ValueError(f"actor_critic_memory must be >= 0 (the memory's size; 0: none), got {actor_critic_memory}")
        self.actor_critic_memory = actor_critic_memory
        self.normalize_vectors = normalize_vectors
        self._scale_images = normalize_images and is_image_space(observation_space)
        vector_shape = self.observation_space.shape if len(self.observation_space.shape) == 1 else (0,)  # type: ignore[arg-type]
        self.register_buffer("observation_mean", th.zeros(vector_shape))
        self.register_buffer("observation_std", th.ones(vector_shape))
        self._build(lr_schedule)

    def _build(self, lr_schedule: Schedule) -> None:
        assert self.observation_space.shape is not None
        self.latent = LATENT_MODELS[self.latent_recurrence](
            tuple(self.observation_space.shape),
            self.action_dim,
            feature_dim=self.feature_dim,
            z1_dim=self.z1_dim,
            z2_dim=self.z2_dim,
            hidden_units=self.hidden_units,
            image_noise=self.image_noise,
            reward_loss_weight=self.reward_loss_weight,
            cost_loss_weight=self.cost_loss_weight,
            cost_positive_weight=self.cost_positive_weight,
            image_channels=self.image_channels,
            encoder_class=self.encoder_class,
            encoder_kwargs=self.encoder_kwargs,
            decoder_class=self.decoder_class,
            decoder_kwargs=self.decoder_kwargs,
            min_std=self.latent_min_std,
            max_std=self.latent_max_std,
            mean_bound=self.latent_mean_bound,
            kl_balance=self.latent_kl_balance,
            overshooting_depth=self.latent_overshooting,
            reward_overshooting_weight=self.latent_reward_overshooting,
            overshooting_stride=self.latent_overshooting_stride,
        )
        state_dim = self.latent.z_dim + (self.action_dim if self.previous_action_input else 0) + self.actor_critic_memory
        self.memory = None
        if self.actor_critic_memory > 0:
            self.memory = BeliefMemory(self.latent.z_dim, self.action_dim, self.actor_critic_memory)
        self.actor = LatentActor(state_dim, self.action_dim, self.hidden_units)
        self.critic = TwinQCritic(state_dim, self.action_dim, self.hidden_units)
        self.critic_target = TwinQCritic(state_dim, self.action_dim, self.hidden_units)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.cost_critic, self.cost_critic_target = (self._make_cost_critic(state_dim, self.action_dim) for _ in range(2))
        self.cost_critic_target.load_state_dict(self.cost_critic.state_dict())
        for target in (self.critic_target, self.cost_critic_target):
            target.requires_grad_(False)
            target.train(False)

        optimizer_kwargs = fast_adam_kwargs(self.optimizer_class, self.optimizer_kwargs)
        latent_lr = self.latent_learning_rate
        self.latent_optimizer = self.optimizer_class(self.latent.parameters(), lr=latent_lr, **optimizer_kwargs)
        self.actor_optimizer = self.optimizer_class(self.actor.parameters(), lr=lr_schedule(1), **optimizer_kwargs)
        # The memory learns from the reward critic's TD error, with its optimizer
        critic_params = [*self.critic.parameters(), *(self.memory.parameters() if self.memory is not None else ())]
        self.critic_optimizer = self.optimizer_class(critic_params, lr=lr_schedule(1), **optimizer_kwargs)
        self.cost_critic_optimizer = self.optimizer_class(self.cost_critic.parameters(), lr=lr_schedule(1), **optimizer_kwargs)

    def _make_cost_critic(self, z_dim: int, action_dim: int) -> IQNCostCritic | MeanCostCritic:
        if self.cost_critic_type == "mean":
            return MeanCostCritic(z_dim, action_dim, self.hidden_units, self.cost_critic_initial_value)
        return IQNCostCritic(z_dim, action_dim, self.n_cosines, self.cost_critic_hidden_dim)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(
            dict(
                z1_dim=self.z1_dim,
                z2_dim=self.z2_dim,
                feature_dim=self.feature_dim,
                hidden_units=self.hidden_units,
                n_cosines=self.n_cosines,
                cost_critic=self.cost_critic_type,
                cost_critic_hidden_dim=self.cost_critic_hidden_dim,
                cost_critic_initial_value=self.cost_critic_initial_value,
                image_noise=self.image_noise,
                reward_loss_weight=self.reward_loss_weight,
                cost_loss_weight=self.cost_loss_weight,
                cost_positive_weight=self.cost_positive_weight,
                image_channels=self.image_channels,
                encoder_class=self.encoder_class,
                encoder_kwargs=self.encoder_kwargs,
                decoder_class=self.decoder_class,
                decoder_kwargs=self.decoder_kwargs,
                latent_min_std=self.latent_min_std,
                latent_max_std=self.latent_max_std,
                latent_mean_bound=self.latent_mean_bound,
                latent_kl_balance=self.latent_kl_balance,
                latent_overshooting=self.latent_overshooting,
                latent_reward_overshooting=self.latent_reward_overshooting,
                latent_overshooting_stride=self.latent_overshooting_stride,
                latent_recurrence=self.latent_recurrence,
                latent_learning_rate=self.latent_learning_rate,
                previous_action_input=self.previous_action_input,
                actor_critic_memory=self.actor_critic_memory,
                normalize_vectors=self.normalize_vectors,
                optimizer_class=self.optimizer_class,
                optimizer_kwargs=self.optimizer_kwargs,
                lr_schedule=self._dummy_schedule,
            )
        )
        return data

    def preprocess(self, observations: th.Tensor) -> th.Tensor:
        """
        Raw observations (any leading dims, as stored) to floats: uint8 images scaled to [0, 1], vectors standardised
        (identity until ``set_observation_statistics``). Decided at construction, so that it compiles without branches.
        """
        if self._scale_images:
            return observations.float() / 255.0
        if self.observation_mean.numel() > 0:
            return (observations.float() - self.observation_mean) / self.observation_std
        return observations.float()

    def set_observation_statistics(self, observations: np.ndarray, min_std: float = 1e-2) -> None:
        """
        Standardise vector observations from now on with the mean and std (floored at ``min_std``) of ``observations``
        (n, obs_dim). Does nothing for images or when ``normalize_vectors`` is off.
        """
        if self.observation_mean.numel() == 0 or not self.normalize_vectors:
            return
        values = th.as_tensor(observations, dtype=th.float32, device=self.device)
        self.observation_mean.copy_(values.mean(dim=0))
        self.observation_std.copy_(values.std(dim=0).clamp(min=min_std))

    def initial_state(self, n_envs: int) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """Zero filter state (z2, previous action, actor-critic memory) for ``n_envs`` envs, on the policy's device."""
        sizes = (self.z2_dim, self.action_dim, self.actor_critic_memory)
        z2, action_prev, memory = (th.zeros(n_envs, size, device=self.device) for size in sizes)
        return z2, action_prev, memory

    def belief_step(
        self, observation: th.Tensor, z2_prev: th.Tensor, action_prev: th.Tensor, episode_start: th.Tensor, deterministic: bool
    ) -> tuple[th.Tensor, th.Tensor]:
        """
        One step of the latent filter.

        :param observation: raw observations (n_envs, *obs_shape)
        :param z2_prev: z2 of the previous step (n_envs, z2_dim)
        :param action_prev: previous action scaled to [-1, 1] (n_envs, action_dim)
        :param episode_start: (n_envs,) bool, True where ``observation`` is the first of an episode
        :param deterministic: use the filter's means instead of samples
        :return: the belief z = [z1, z2] (n_envs, z_dim) and the new z2 (n_envs, z2_dim)
        """
        feature = self.latent.encode(self.preprocess(observation).unsqueeze(1)).squeeze(1)
        z1, z2 = self.latent.filter_step(feature, z2_prev, action_prev, episode_start, deterministic)
        return th.cat([z1, z2], dim=-1), z2

    def actor_critic_input(
        self, z: th.Tensor, action_prev: th.Tensor, episode_start: th.Tensor | None = None, memory: th.Tensor | None = None
    ) -> th.Tensor:
        """
        What the actor and the critics take: the belief, with ``previous_action_input`` the previous action, and with
        an ``actor_critic_memory`` the memory after the belief.

        :param z: beliefs (..., z_dim)
        :param action_prev: the action taken before each belief's frame, scaled to [-1, 1] (..., action_dim)
        :param episode_start: (n,) bool, True where the belief is an episode's first (its previous action counts as zero)
        :param memory: the memory after each belief (..., actor_critic_memory); needed with a memory only
        :return: ``[z, a_prev, h]`` (..., state size), each part there if the policy takes it
        """
        parts = [z]
        if self.previous_action_input:
            if episode_start is not None:
                action_prev = action_prev.masked_fill(episode_start.reshape(-1, 1), 0.0)
            parts.append(action_prev)
        if self.memory is not None:
            assert memory is not None, "a policy with an actor-critic memory takes the memory after the belief"
            parts.append(memory)
        return parts[0] if len(parts) == 1 else th.cat(parts, dim=-1)

    def acting_input(
        self, z: th.Tensor, action_prev: th.Tensor, memory_prev: th.Tensor, episode_start: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor]:
        """
        What the actor takes when it acts on belief ``z``, and the actor-critic memory after it (``memory_prev``
        unchanged without one).

        :param z: the beliefs of one step (n, z_dim)
        :param action_prev: the action taken before each belief's frame (n, action_dim)
        :param memory_prev: the memory before the belief (n, actor_critic_memory); where an episode starts, zero is
        :param episode_start: (n,) bool, True where the belief is an episode's first
        :return: the actor's input (n, state size) and the new memory (n, actor_critic_memory)
        """
        memory = memory_prev
        if self.memory is not None:
            starts = episode_start.reshape(-1, 1)
            memory = self.memory(z, action_prev.masked_fill(starts, 0.0), memory_prev.masked_fill(starts, 0.0))
        return self.actor_critic_input(z, action_prev, episode_start, memory), memory

    def window_states(self, latents: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """
        What the actor and the critics take at frames 1..L of windows, with ``previous_action_input`` or a memory
        (which runs from zero before frame 1): frame 0 has no previous action in the window.

        :param latents: the beliefs of the windows' frames (B, L+1, z_dim)
        :param actions: the windows' actions (B, L, action_dim); action ``t`` leads to frame ``t + 1``
        :return: (B, L, state size)
        """
        memory = None if self.memory is None else self.memory.unroll(latents[:, 1:], actions)
        return self.actor_critic_input(latents[:, 1:], actions, memory=memory)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        """Act from a single frame, as at the first step of an episode (no history). Prefer ``predict`` with state."""
        assert isinstance(observation, th.Tensor)
        n_envs = observation.shape[0]
        z2_prev, action_prev, memory_prev = self.initial_state(n_envs)
        episode_start = th.ones(n_envs, dtype=th.bool, device=self.device)
        z, _ = self.belief_step(observation, z2_prev, action_prev, episode_start, deterministic)
        state, _ = self.acting_input(z, action_prev, memory_prev, episode_start)
        return self.actor(state, deterministic=deterministic)

    def forward(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self._predict(observation, deterministic=deterministic)

    def predict(  # type: ignore[override]
        self,
        observation: np.ndarray,
        state: FilterState | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, FilterState]:
        """
        Filter one observation per env into the latent belief and act on it.

        :param observation: (n_envs, *obs_shape) or a single observation
        :param state: the filter state returned by the previous call; None starts every env afresh
        :param episode_start: (n_envs,) True where an episode starts (resets that env's filter)
        :param deterministic: use the filter's means and the actor's mean action
        :return: actions in the action space's bounds, and the new filter state
        """
        self.set_training_mode(False)
        if isinstance(observation, tuple) and len(observation) == 2 and isinstance(observation[1], dict):
            raise ValueError(
                "predict() got an (observation, info) tuple: pass only the observation "
                "(Gymnasium's `obs, info = env.reset()` vs SB3's `obs = vec_env.reset()`)."
            )
        obs_tensor, vectorized_env = self.obs_to_tensor(observation)
        assert isinstance(obs_tensor, th.Tensor)
        n_envs = obs_tensor.shape[0]
        if obs_tensor.is_floating_point() and not bool(th.isfinite(obs_tensor).all()):  # before the filter, not after
            check_observations_finite(
                obs_tensor.cpu().numpy(), lambda row: f"predict()'s observation of env {row} of {n_envs}"
            )
        if state is None:
            z2_prev, action_prev, memory_prev = self.initial_state(n_envs)
            starts = th.ones(n_envs, dtype=th.bool, device=self.device)
        else:
            if not (len(state) == 3 or (len(state) == 2 and self.memory is None)):
                raise ValueError(
                    f"predict()'s state is the (z2, previous action, memory) that its last call returned, got {len(state)} "
                    "arrays"
                )
            z2_prev = th.as_tensor(state[0], dtype=th.float32, device=self.device).reshape(n_envs, self.z2_dim)
            action_prev = th.as_tensor(state[1], dtype=th.float32, device=self.device).reshape(n_envs, -1)
            memory = state[2] if len(state) == 3 else np.zeros((n_envs, 0), dtype=np.float32)
            memory_prev = th.as_tensor(memory, dtype=th.float32, device=self.device).reshape(n_envs, self.actor_critic_memory)
            flags = np.zeros(n_envs, dtype=bool) if episode_start is None else np.asarray(episode_start, dtype=bool)
            starts = th.as_tensor(flags.reshape(n_envs), device=self.device)
        with th.inference_mode():
            z, z2 = self.belief_step(obs_tensor, z2_prev, action_prev, starts, deterministic)
            actor_input, memory = self.acting_input(z, action_prev, memory_prev, starts)
            scaled_actions = self.actor(actor_input, deterministic=deterministic)
        scaled = scaled_actions.cpu().numpy()
        actions = self.unscale_action(scaled).reshape((-1, *self.action_space.shape))  # type: ignore[misc]
        new_state = (z2.cpu().numpy(), scaled, memory.cpu().numpy())
        if not vectorized_env:
            actions = actions.squeeze(axis=0)
        return actions, new_state

    def set_training_mode(self, mode: bool) -> None:
        """Train or eval mode for the trained networks; the target networks always stay in eval mode."""
        for module in (self.latent, self.actor, self.critic, self.cost_critic, self.memory):
            if module is not None:
                module.train(mode)
        self.training = mode


# Keywords of both DSSLAC and LatentPolicy, with LatentPolicy's defaults (the code behind the thesis numbers)
SHARED_POLICY_KEYWORDS: dict[str, Any] = {
    name: inspect.signature(LatentPolicy).parameters[name].default
    for name in ("image_noise", "cost_loss_weight", "cost_positive_weight", "latent_learning_rate", "cost_critic")
}


def merge_shared_keywords(policy_kwargs: dict[str, Any], **given: Any) -> dict[str, Any]:
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
