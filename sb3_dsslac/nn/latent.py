"""Sequential latent variable model of (DS-)SLAC: encoder, decoder, latent dynamics, reward and cost decoders."""

import contextlib
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sb3_dsslac.nn.fused_rollout import posterior_steps
from sb3_dsslac.nn.gaussian import STD_EPS, GaussianBounds, gaussian_kl
from sb3_dsslac.nn.image_nets import check_decoder, check_encoder, check_image_shape, image_decoder, image_encoder
from sb3_dsslac.nn.numerics import autocast_enabled
from sb3_dsslac.nn.overshooting import overshooting_roll

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)
_LOG_COST_EPS = math.log(1e-6)


def init_weights(module: nn.Module) -> None:
    """Xavier-uniform (gain 1) weights and zero biases for every linear and (transposed) convolution layer."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear | nn.Conv2d | nn.ConvTranspose2d):
            nn.init.xavier_uniform_(layer.weight, gain=1.0)
            if layer.bias is not None:
                nn.init.zeros_(layer.bias)


def build_mlp(
    input_dim: int,
    output_dim: int,
    hidden_units: tuple[int, ...],
    activation: Callable[[], nn.Module],
    output_activation: Callable[[], nn.Module] | None = None,
) -> nn.Sequential:
    """
    Multi-layer perceptron ``input_dim -> *hidden_units -> output_dim``.

    :param activation: factory of the hidden activation module
    :param output_activation: factory of the activation applied to the output, or None for a linear output
    """
    layers: list[nn.Module] = []
    in_dim = input_dim
    for units in hidden_units:
        layers += [nn.Linear(in_dim, units), activation()]
        in_dim = units
    layers.append(nn.Linear(in_dim, output_dim))
    if output_activation is not None:
        layers.append(output_activation())
    return nn.Sequential(*layers)


def gaussian_nll(x: Tensor, mean: Tensor, std: Tensor) -> Tensor:
    """Elementwise ``-log N(x | mean, std^2)``."""
    return 0.5 * ((x - mean) / std).pow(2) + torch.log(std) + _HALF_LOG_2PI


def fixed_std_gaussian_nll(x: Tensor, mean: Tensor, std: float) -> Tensor:
    """
    ``-log N(x | mean, std^2)`` of (B, ...) tensors summed over all but the first dim, mean over it: a scalar, from one
    squared-error sum (three ops forward and two backward, where the elementwise form takes seven and about as many).
    """
    values_per_row = math.prod(x.shape[1:])
    squared_error = F.mse_loss(mean.float(), x, reduction="sum")
    return squared_error.mul(0.5 / (std**2 * x.shape[0])).add(values_per_row * (math.log(std) + _HALF_LOG_2PI))


class GaussianMLP(nn.Module):
    """
    Diagonal Gaussian whose mean and std are an ELU MLP of the concatenated inputs: the MLP's ``[mean_raw, raw]`` made
    a mean and a std by ``bounds`` (by default ``std = softplus(raw) + 1e-5``, the reference code's).

    :param bounds: the std's floor and ceiling and the mean's bound (None: the reference code's)
    """

    def __init__(
        self, input_dim: int, output_dim: int, hidden_units: tuple[int, ...], bounds: GaussianBounds | None = None
    ) -> None:
        super().__init__()
        self.bounds = GaussianBounds() if bounds is None else bounds
        self.net = build_mlp(input_dim, 2 * output_dim, hidden_units, nn.ELU)

    def forward(self, *inputs: Tensor) -> tuple[Tensor, Tensor]:
        """Inputs (..., d_k) concatenated on the last dim -> (mean, std), each (..., output_dim)."""
        x = torch.cat(inputs, dim=-1) if len(inputs) > 1 else inputs[0]
        if x.dim() > 2:  # rows through the layers: a linear layer on more dims adds two views each way
            out = self.net(x.reshape(-1, x.shape[-1])).view(*x.shape[:-1], -1)
        else:
            out = self.net(x)
        mean_raw, raw_std = out.chunk(2, dim=-1)
        return self.bounds(mean_raw, raw_std)


class LatentRollout(NamedTuple):
    """Posterior rollout over a sequence; every field is (B, T+1, dim)."""

    z1_mean: Tensor
    z1_std: Tensor
    z1: Tensor
    z2: Tensor


class LatentStart(NamedTuple):
    """
    Where a posterior rollout starts when a burn-in filtered the frames before it (``LatentModel.burn_in``): the belief
    before the rollout's first frame and the action that led to that frame, each row restarting instead where the
    first frame is its episode's first.

    :param z2: (B, z2_dim) z2 before the first frame
    :param action: (B, A) the action from that state to the first frame
    :param episode_start: (B,) bool, True where the first frame is its episode's first
    """

    z2: Tensor
    action: Tensor
    episode_start: Tensor

    def rows(self, part: slice) -> "LatentStart":
        """The rows ``part`` of every field."""
        return LatentStart(*(field[part] for field in self))

    @staticmethod
    def cat(starts: "list[LatentStart]") -> "LatentStart":
        """The starts of several batches, their rows in order."""
        return LatentStart(*(torch.cat(fields) for fields in zip(*starts, strict=True)))


# Output channels of the encoder's stride-2 convolutions in the published networks (the decoder mirrors them)
THESIS_IMAGE_CHANNELS = (32, 64, 128, 256)


def channels_last_is_faster(widths: tuple[int, ...], device: torch.device) -> bool:
    """
    Whether the convolutions of these encoder ``widths`` run channels-last (NHWC) on ``device``, the layout measured
    faster for them (the replay buffer then stores the frames channels-last too); the arithmetic is the same.

    - The thesis's widths (32 channels up): NHWC on CPUs (oneDNN) and GPUs (tensor cores) alike.
    - Narrower widths on an x86 CPU (AVX2 or AVX512): in NCHW, oneDNN reorders every activation to its blocked layout
      and back, where its NHWC kernels need none: 7.4 of 27 ms of oneDNN work in a compiled ``cpu_pixels`` update on an
      Intel Xeon's AVX512, 7.7 of 36 ms with ATen, inductor, oneDNN and MKL held to AVX2 on it
      (docs/performance.md). With the frames stored channels-last, NHWC ran 1.05x (AVX512) and 1.09x (held to AVX2) the
      NCHW updates/s on 32x32 frames too. On an AVX2 CPU itself (a 2-core AMD EPYC), compiled, one run each:
      1.09x (``cpu_pixels32_pid``, 32x32) and 1.11x (``cpu_pixels``, 64x64), every round faster.
    - NCHW elsewhere, GPUs included: narrow widths were not measured there, and the reasons above are oneDNN's.
    """
    if widths[0] >= 32:
        return True
    return device.type == "cpu" and torch.backends.cpu.get_cpu_capability().startswith("AVX")


class LatentModel(nn.Module):
    """
    Stochastic latent variable model of Safe SLAC / DS-SLAC with latent ``z = [z1, z2]``.

    Images (C, H, W) use conv encoders/decoders chosen from the frame's size (``image_nets``; on 64x64 frames the
    published ones, on 32x32 the same with one stride-2 layer less on each side), 1-D observations (D,) MLPs, unless
    the caller gives an encoder and a decoder of its own. Observations are floats (images scaled to [0, 1]).

    :param observation_shape: (C, H, W) with both sides at least 32 (``check_image_shape``), or (D,)
    :param action_dim: number of action dimensions (actions in [-1, 1])
    :param feature_dim: encoder output size per frame
    :param z1_dim: size of the stochastic z1 (the only part with a KL term)
    :param z2_dim: size of z2
    :param hidden_units: hidden layers of every Gaussian / Bernoulli MLP (and of the vector encoder/decoder)
    :param image_noise: variance of the Gaussian observation likelihood (std = sqrt(image_noise))
    :param reward_loss_weight: scale of the Gaussian reward loss (1 in the thesis)
    :param cost_loss_weight: scale of the Bernoulli cost loss
    :param cost_positive_weight: extra weight of the positive (cost > 0) samples in the cost loss
    :param image_channels: output channels of the encoder's first four stride-2 convolutions, mirrored by the decoder
        (images only; frames whose longer side is at most 56 pixels use the first three, over 112 pixels repeat the
        last for their fifth and later stages: ``image_nets.stage_widths``)
    :param min_std: the floor on the std of the latent Gaussians (z1's prior and posterior, z2's): 1e-5 in the reference
        code, where a prior std at the floor lets one latent excursion make a KL of 1e10 or more
    :param max_std: the ceiling on their std (None in the reference code: ``softplus(raw) + min_std``, unbounded)
    :param mean_bound: the bound on their means' absolute value (None in the reference code). With both bounds every
        latent stays within ``mean_bound + max_std * |noise|`` (``GaussianBounds``)
    :param kl_balance: None (the thesis's) trains prior and posterior on the KL alike; a share ``alpha`` in [0, 1]
        splits its gradient, ``alpha * KL(sg(q) || p) + (1 - alpha) * KL(q || sg(p))`` (DreamerV2's KL balancing, 0.8
        in LAMBDA): the same value, the prior pulled toward the posterior more than the posterior toward the prior,
        so that what a frame shows is kept in the belief against the KL (0.5 halves the plain KL's gradient)
    :param overshooting_depth: 1 (the thesis's): z1's KL is to its one-step prior; ``D >= 2`` adds the mean over
        ``d = 2 .. D`` of the KL to its prior rolled ``d`` steps open-loop (``overshooting_roll``, PlaNet's latent
        overshooting), so that the belief must hold what the next D frames will show; D is at most a window's
        transitions
    :param reward_overshooting_weight: 0 (the thesis's) or the weight of the reward's Gaussian likelihood on the
        transitions rolled open-loop ``d = 1 .. D`` steps by the overshooting (mean over d of each depth's sum over the
        window's starts, mean over the batch), so that the belief must hold what the rewards of the next D steps
        depend on, such as where the goal went (``overshooting_roll``); needs ``overshooting_depth >= 2``
    :param overshooting_stride: 1 rolls from every start of a window; ``s`` from every s-th start only (t = 0, s, ..),
        as deep at about 1/s of the rows (``overshooting_roll``)
    :param encoder_class: the encoder in place of the built-in one (None): ``encoder_class(observation_shape,
        feature_dim, **encoder_kwargs)`` must map observations (N, *observation_shape) to (N, feature_dim) or
        (N, feature_dim, 1, 1), checked on two zero observations here. It keeps its own initialisation
    :param encoder_kwargs: further keywords of ``encoder_class``
    :param decoder_class: the decoder in place of the built-in one (None): ``decoder_class(z_dim, observation_shape,
        **decoder_kwargs)`` must map latents (N, z_dim) to the mean (N, *observation_shape) of the observation
        Gaussian, checked on two zero latents here. It keeps its own initialisation
    :param decoder_kwargs: further keywords of ``decoder_class``
    """

    # Whether eager rollouts take ``posterior_steps`` (written for z1's and z2's Gaussian MLPs) over step-by-step autograd
    uses_fused_rollout = True

    def __init__(
        self,
        observation_shape: tuple[int, ...],
        action_dim: int,
        feature_dim: int = 200,
        z1_dim: int = 32,
        z2_dim: int = 200,
        hidden_units: tuple[int, ...] = (256, 256),
        image_noise: float = 0.4,
        reward_loss_weight: float = 1.0,
        cost_loss_weight: float = 30.0,
        cost_positive_weight: float = 100.0,
        image_channels: tuple[int, ...] = THESIS_IMAGE_CHANNELS,
        min_std: float = STD_EPS,
        max_std: float | None = None,
        mean_bound: float | None = None,
        kl_balance: float | None = None,
        overshooting_depth: int = 1,
        reward_overshooting_weight: float = 0.0,
        overshooting_stride: int = 1,
        encoder_class: type[nn.Module] | None = None,
        encoder_kwargs: dict[str, Any] | None = None,
        decoder_class: type[nn.Module] | None = None,
        decoder_kwargs: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        if kl_balance is not None and not 0.0 <= kl_balance <= 1.0:
            raise ValueError(f"kl_balance must be None or a share in [0, 1], got {kl_balance}")
        self.kl_balance = kl_balance
        if overshooting_depth < 1:
            raise ValueError(f"overshooting_depth must be at least 1 (1: the one-step KL alone), got {overshooting_depth}")
        self.overshooting_depth = overshooting_depth
        if reward_overshooting_weight < 0 or (reward_overshooting_weight > 0 and overshooting_depth < 2):
            raise ValueError(
                f"reward_overshooting_weight must be 0, or positive with overshooting_depth >= 2 (the rolled transitions it "
                f"weighs), got {reward_overshooting_weight} with overshooting_depth={overshooting_depth}"
            )
        self.reward_overshooting_weight = reward_overshooting_weight
        if overshooting_stride < 1:
            raise ValueError(f"overshooting_stride must be at least 1 (1: a roll from every start), got {overshooting_stride}")
        self.overshooting_stride = overshooting_stride
        self.hidden_units = tuple(hidden_units)
        self.image_channels = tuple(int(width) for width in image_channels)
        if len(self.image_channels) != 4 or min(self.image_channels) < 1:
            raise ValueError(
                f"image_channels must be 4 positive channel counts of the encoder's stride-2 convolutions (the decoder "
                f"mirrors them), got {tuple(image_channels)}; the thesis's are {THESIS_IMAGE_CHANNELS}"
            )
        self.observation_shape = tuple(observation_shape)
        self.action_dim = action_dim
        self.feature_dim = feature_dim
        self.z1_dim = z1_dim
        self.z2_dim = z2_dim
        self.z_dim = z1_dim + z2_dim
        self.image_std = math.sqrt(image_noise)
        self.reward_loss_weight = reward_loss_weight
        self.cost_loss_weight = cost_loss_weight
        self.cost_positive_weight = cost_positive_weight
        bounds = GaussianBounds(min_std, max_std, mean_bound)

        if len(self.observation_shape) not in (1, 3):
            raise ValueError(f"observation_shape must be (C, H, W) or (D,), got {self.observation_shape}")
        is_image = len(self.observation_shape) == 3
        if is_image and (encoder_class is None or decoder_class is None):
            check_image_shape(self.observation_shape)
        if encoder_class is not None:
            self.encoder = encoder_class(self.observation_shape, feature_dim, **(encoder_kwargs or {}))
            check_encoder(self.encoder, self.observation_shape, feature_dim)
        elif is_image:
            self.encoder = image_encoder(*self.observation_shape, feature_dim, self.image_channels)
        else:
            self.encoder = build_mlp(self.observation_shape[0], feature_dim, hidden_units, nn.ELU, nn.ELU)
        if decoder_class is not None:
            self.decoder = decoder_class(self.z_dim, self.observation_shape, **(decoder_kwargs or {}))
            check_decoder(self.decoder, self.z_dim, self.observation_shape)
        elif is_image:
            self.decoder = image_decoder(self.z_dim, *self.observation_shape, self.image_channels)
        else:
            self.decoder = build_mlp(self.z_dim, self.observation_shape[0], hidden_units, nn.ELU)
        # The user's networks keep their initialisation; the built-in ones take ``init_weights`` (and the decoder's
        # input is a 1x1 map of the latents); the layout measured faster is for the built-in convolutions
        user_networks = [net for net, given in ((self.encoder, encoder_class), (self.decoder, decoder_class)) if given]
        self.built_in_networks = not user_networks
        self._latent_map_input = is_image and decoder_class is None

        # p(z2_0 | z1_0) = q(z2_0 | z1_0)
        self.z2_init = GaussianMLP(z1_dim, z2_dim, hidden_units, bounds)
        # p(z1_{t+1} | z2_t, a_t)
        self.z1_prior = GaussianMLP(z2_dim + action_dim, z1_dim, hidden_units, bounds)
        # p(z2_{t+1} | z1_{t+1}, z2_t, a_t) = q(z2_{t+1} | ...)
        self.z2_transition = GaussianMLP(z1_dim + z2_dim + action_dim, z2_dim, hidden_units, bounds)
        # q(z1_0 | f_0)
        self.z1_posterior_init = GaussianMLP(feature_dim, z1_dim, hidden_units, bounds)
        # q(z1_{t+1} | f_{t+1}, z2_t, a_t)
        self.z1_posterior = GaussianMLP(feature_dim + z2_dim + action_dim, z1_dim, hidden_units, bounds)

        transition_dim = 2 * self.z_dim + action_dim
        # p(r_t | z_t, a_t, z_{t+1})
        self.reward_decoder = GaussianMLP(transition_dim, 1, hidden_units)
        # p(c_t > 0 | z_t, a_t, z_{t+1}) as one logit
        self.cost_decoder = build_mlp(transition_dim, 1, hidden_units, nn.ELU)

        for child in self.children():  # in the order of ``init_weights(self)``: the same draws
            if all(child is not user for user in user_networks):
                init_weights(child)
        self.set_layout_for(torch.device("cpu"))  # where modules are built; DSSLAC sets its own device's

    def set_layout_for(self, device: torch.device) -> None:
        """
        Lay the convolutions' weights out in the layout measured faster for them on ``device``
        (``channels_last_is_faster``), noted in ``channels_last``: the replay buffer stores the frames in it
        (``SequenceReplayBuffer.set_channels_last_frames``). Only the layout changes, not the values or the parameters.
        """
        convolutions = len(self.observation_shape) == 3 and self.built_in_networks
        self.channels_last = convolutions and channels_last_is_faster(self.image_channels, device)
        self.to(memory_format=torch.channels_last if self.channels_last else torch.contiguous_format)

    def encode(self, observations: Tensor) -> Tensor:
        """Observations (B, T, *observation_shape) -> features (B, T, feature_dim)."""
        batch, steps = observations.shape[:2]
        features = self.encoder(observations.reshape(batch * steps, *self.observation_shape))
        return features.view(batch, steps, self.feature_dim)

    def decode(self, z: Tensor) -> Tensor:
        """Latents (B, T, z_dim) -> mean of the observation Gaussian (B, T, *observation_shape)."""
        batch, steps = z.shape[:2]
        flat = z.reshape(batch * steps, self.z_dim)
        if self._latent_map_input:
            flat = flat.view(batch * steps, self.z_dim, 1, 1)
        return self.decoder(flat).view(batch, steps, *self.observation_shape)

    def posterior(
        self,
        features: Tensor,
        actions: Tensor,
        noise: tuple[Tensor, Tensor] | None = None,
        start: LatentStart | None = None,
    ) -> LatentRollout:
        """
        Reparameterised posterior rollout: features (B, T+1, F), actions (B, T, A) -> fields (B, T+1, dim).

        :param noise: the standard normal noise of the z1 and z2 samples, (T+1, B, Z1) and (T+1, B, Z2); drawn if None
        :param start: the belief before the first frame (a burn-in's), None: the first frame opens the rollout, as an
            episode's first frame does
        """
        mixed_precision = autocast_enabled(features.device.type)
        if mixed_precision:  # the rollout's small matrix products run in float32 below; bfloat16 is for the convolutions
            features = features.float()
        batch, frames = features.shape[:2]
        if noise is None:
            z1_noise = torch.randn(frames, batch, self.z1_dim, device=features.device, dtype=features.dtype)
            z2_noise = torch.randn(frames, batch, self.z2_dim, device=features.device, dtype=features.dtype)
        else:
            z1_noise, z2_noise = noise
        if start is None:
            z1_mean, z1_std = self.z1_posterior_init(features[:, 0])
            z1 = torch.addcmul(z1_mean, z1_std, z1_noise[0])
            z2_mean, z2_std = self.z2_init(z1)
            z2 = torch.addcmul(z2_mean, z2_std, z2_noise[0])
            first = (z1_mean, z1_std, z1, z2)
        else:
            first = self._continued_first_step(features[:, 0], start, z1_noise[0], z2_noise[0])
        if frames == 1:
            return LatentRollout(*(value.unsqueeze(1) for value in first))
        if mixed_precision:
            first = tuple(value.float() for value in first)
        with torch.autocast(features.device.type, enabled=False) if mixed_precision else contextlib.nullcontext():
            # the compiler differentiates (and fuses) the steps itself; the fused rollout needs Gaussian MLPs
            if torch.compiler.is_compiling() or not self.uses_fused_rollout:
                return self._posterior_steps(features[:, 1:], actions, first, z1_noise[1:], z2_noise[1:])
            steps = posterior_steps(
                features[:, 1:], actions, first, z1_noise[1:], z2_noise[1:], self.z1_posterior, self.z2_transition
            )
        return LatentRollout(*steps)

    def _continued_first_step(
        self, feature: Tensor, start: LatentStart, z1_eps: Tensor, z2_eps: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The first frame's z1 mean, std and sample and z2 sample after ``start`` (the filter's step, as ``filter_step``)."""
        opens = start.episode_start.view(-1, 1)
        z1_mean, z1_std = self._z1_opening_or_next(feature, start.z2, start.action, opens)
        z1 = torch.addcmul(z1_mean, z1_std, z1_eps)
        z2 = torch.addcmul(*self._z2_opening_or_next(z1, start.z2, start.action, opens), z2_eps)
        return z1_mean, z1_std, z1, z2

    def _z1_opening_or_next(
        self, feature: Tensor, z2_prev: Tensor, action_prev: Tensor, opens: Tensor
    ) -> tuple[Tensor, Tensor]:
        """z1's posterior (mean, std), each (N, Z1): ``q(z1_0 | f)`` where ``opens`` (N, 1), else ``q(z1 | f, z2, a)``."""
        init_mean, init_std = self.z1_posterior_init(feature)
        step_mean, step_std = self.z1_posterior(feature, z2_prev, action_prev)
        return torch.where(opens, init_mean, step_mean), torch.where(opens, init_std, step_std)

    def _z2_opening_or_next(self, z1: Tensor, z2_prev: Tensor, action_prev: Tensor, opens: Tensor) -> tuple[Tensor, Tensor]:
        """z2's (mean, std), each (N, Z2): ``z2_init(z1)`` where ``opens`` (N, 1) is True, else ``z2_transition``'s."""
        init_mean, init_std = self.z2_init(z1)
        step_mean, step_std = self.z2_transition(z1, z2_prev, action_prev)
        return torch.where(opens, init_mean, step_mean), torch.where(opens, init_std, step_std)

    def burn_in(
        self,
        features: Tensor,
        actions: Tensor,
        episode_start_index: Tensor,
        stored: tuple[Tensor, Tensor] | None = None,
    ) -> LatentStart:
        """
        Filter the burn-in frames before a batch of windows, as the acting filter does (posterior samples, restarting
        at each row's episode start), without gradient: R2D2's burn-in, so that the windows' beliefs carry as much
        history as the acting filter's.

        :param features: (B, K, F) encoder features of the K burn-in frames
        :param actions: (B, K, A) the actions leaving them (the last one leads to the window's first frame)
        :param episode_start_index: (B,) int64 index of each row's episode's first frame, in [-1, K] (K: the window's
            first frame; -1: before the burn-in; the frames before it are another episode's:
            ``SequenceBatch.episode_start_index``)
        :param stored: the belief z2 (B, Z2) after the frame before the burn-in and the action (B, A) that left it,
            which the burn-in continues from where that frame is of the episode (index -1): R2D2's stored state. None:
            every row's burn-in opens at its first frame
        :return: the start of the windows' rollout
        """
        with torch.no_grad():
            if stored is None:
                z2, action_prev = features.new_zeros(features.shape[0], self.z2_dim), torch.zeros_like(actions[:, 0])
            else:
                z2, action_prev = stored
            for index in range(features.shape[1]):
                restart = episode_start_index == index
                if index == 0 and stored is None:
                    restart = torch.ones_like(restart)
                _, z2 = self.filter_step(features[:, index], z2, action_prev, restart)
                action_prev = actions[:, index]
            return LatentStart(z2, action_prev, episode_start_index == features.shape[1])

    def _posterior_steps(
        self, features: Tensor, actions: Tensor, first: tuple[Tensor, ...], z1_noise: Tensor, z2_noise: Tensor
    ) -> LatentRollout:
        """``posterior_steps`` step by step, recorded by autograd."""
        means, stds, z1s, z2s = ([value] for value in first)
        z2 = first[3]
        for feature, action, z1_eps, z2_eps in zip(
            features.unbind(1), actions.unbind(1), z1_noise.unbind(0), z2_noise.unbind(0), strict=True
        ):
            z1_mean, z1_std = self.z1_posterior(feature, z2, action)
            z1 = torch.addcmul(z1_mean, z1_std, z1_eps)
            z2_mean, z2_std = self.z2_transition(z1, z2, action)
            z2 = torch.addcmul(z2_mean, z2_std, z2_eps)
            means.append(z1_mean)
            stds.append(z1_std)
            z1s.append(z1)
            z2s.append(z2)
        return LatentRollout(*(torch.stack(values, dim=1) for values in (means, stds, z1s, z2s)))

    def _check_sequence(self, observations: Tensor, actions: Tensor) -> None:
        if tuple(observations.shape[2:]) != self.observation_shape:
            raise ValueError(f"observations must be (B, T+1, *{self.observation_shape}), got {tuple(observations.shape)}")
        batch, frames = observations.shape[:2]
        if tuple(actions.shape) != (batch, frames - 1, self.action_dim):
            raise ValueError(
                f"actions must be (B, T, A) = ({batch}, {frames - 1}, {self.action_dim}), got {tuple(actions.shape)}"
            )

    def _kl(self, mean_q: Tensor, std_q: Tensor, mean_p: Tensor, std_p: Tensor) -> Tensor:
        """KL(q || p) of (B, T+1, Z1) Gaussians summed over time and z1, mean over the batch; balanced by ``kl_balance``."""
        if self.kl_balance is None:
            return gaussian_kl(mean_q, std_q, mean_p, std_p).sum(dim=(1, 2)).mean()
        to_prior = gaussian_kl(mean_q.detach(), std_q.detach(), mean_p, std_p)
        to_posterior = gaussian_kl(mean_q, std_q, mean_p.detach(), std_p.detach())
        return (self.kl_balance * to_prior + (1.0 - self.kl_balance) * to_posterior).sum(dim=(1, 2)).mean()

    def loss(
        self,
        observations: Tensor,
        actions: Tensor,
        rewards: Tensor,
        costs: Tensor,
        terminated: Tensor,
        features: Tensor | None = None,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """
        Negative ELBO plus reward and cost likelihoods on a batch of sequences (``loss_and_filter`` without other
        sequences; the arguments are its own).

        :return: total scalar loss and the detached terms ``kl``, ``image_loss``, ``reward_loss``, ``cost_loss``
            (each summed over time (and pixels), mean over the batch), with the diagnostics of ``loss_and_filter``
        """
        total, info, _ = self.loss_and_filter(observations, actions, rewards, costs, terminated, features=features)
        return total, info

    def loss_and_filter(
        self,
        observations: Tensor,
        actions: Tensor,
        rewards: Tensor,
        costs: Tensor,
        terminated: Tensor,
        features: Tensor | None = None,
        other: tuple[Tensor, Tensor] | None = None,
        noise: tuple[Tensor, Tensor] | None = None,
        start: LatentStart | None = None,
    ) -> tuple[Tensor, dict[str, Tensor], Tensor | None]:
        """
        ``loss``, and the posterior samples of ``other`` sequences without gradient, from one rollout over both batches
        (the rows of a rollout never meet): a few hundred ops fewer than a second rollout, and the same numbers.

        :param observations: (B, T+1, *observation_shape) floats (images in [0, 1])
        :param actions: (B, T, A) in [-1, 1]
        :param rewards: (B, T) reward of transition t -> t+1
        :param costs: (B, T) cost of transition t -> t+1 (binarised as cost > 0)
        :param terminated: (B, T) 1.0 where transition t ended the episode by termination (masks the reward term)
        :param features: ``encode(observations)`` (B, T+1, feature_dim) if the caller already computed it
        :param other: observations (B', T+1, *observation_shape) and actions (B', T, A) of the other sequences
        :param noise: the rollout's noise (T+1, B + B', Z1) and (T+1, B + B', Z2), the loss's batch first; drawn if None
        :param start: the belief before the first frames (``burn_in``), B + B' rows, the loss's batch first; None: the
            first frames open their episodes. With it the first frame's KL is to the prior after the start
        :return: the total loss, its detached terms (as ``loss``) with the batch's extremes that name the cause of a
            spike (``prior_std_min``, ``posterior_std_min``: the smallest std of z1's prior and posterior;
            ``z_abs_max``, ``reconstruction_abs_max``: the largest |z| and |decoder output|), and the other sequences'
            ``z = [z1, z2]`` (B', T+1, z_dim), or None without ``other``
        """
        self._check_sequence(observations, actions)
        if rewards.shape != actions.shape[:2] or costs.shape != rewards.shape or terminated.shape != rewards.shape:
            raise ValueError(f"rewards, costs and terminated must be (B, T) = {tuple(actions.shape[:2])}")

        features = self.encode(observations) if features is None else features
        rollout_actions = actions
        if other is not None:
            other_observations, other_actions = other
            self._check_sequence(other_observations, other_actions)
            with torch.no_grad():
                other_features = self.encode(other_observations)
            features = torch.cat([features, other_features])
            rollout_actions = torch.cat([actions, other_actions])
        rollout = self.posterior(features, rollout_actions, noise, start)
        z = torch.cat([rollout.z1, rollout.z2], dim=-1)
        z1_mean, z1_std, z2_prev = rollout.z1_mean, rollout.z1_std, rollout.z2[:, :-1]
        other_z = None
        if other is not None:
            n_own = observations.shape[0]
            z, other_z = z.split([n_own, z.shape[0] - n_own])
            other_z = other_z.detach()
            z1_mean, z1_std, z2_prev = z1_mean[:n_own], z1_std[:n_own], z2_prev[:n_own]

        # KL(q(z1_t | .) || p(z1_t | .)): N(0, I) at t = 0, teacher-forced p(z1_t | z2_{t-1}, a_{t-1}) after.
        prior_mean, prior_std = self.z1_prior(z2_prev, actions)
        if start is None:  # N(0, 1) at t = 0, padded in front: one op each, where a cat with a filled slice takes three
            prior_mean = F.pad(prior_mean, (0, 0, 1, 0))
            prior_std = F.pad(prior_std, (0, 0, 1, 0), value=1.0)
        else:  # after a burn-in, p(z1_0 | z2_-1, a_-1) except where the first frame opens its episode
            own = start.rows(slice(0, observations.shape[0]))
            first_mean, first_std = self.z1_prior(own.z2, own.action)
            opens = own.episode_start.view(-1, 1)
            first_mean = torch.where(opens, torch.zeros_like(first_mean), first_mean)
            first_std = torch.where(opens, torch.ones_like(first_std), first_std)
            prior_mean = torch.cat([first_mean.unsqueeze(1), prior_mean], dim=1)
            prior_std = torch.cat([first_std.unsqueeze(1), prior_std], dim=1)
        kl = self._kl(z1_mean, z1_std, prior_mean, prior_std)
        terms = {"kl": kl}
        rolled_transitions: list[Tensor] = []
        if self.overshooting_depth > 1:
            z1 = z[..., : self.z1_dim] if self.reward_overshooting_weight > 0 else None
            terms["overshooting_kl"], rolled_transitions = overshooting_roll(
                self.z1_prior,
                self.z2_transition,
                z[..., self.z1_dim :],
                actions,
                z1_mean,
                z1_std,
                self.overshooting_depth,
                z1,
                self.overshooting_stride,
            )

        reconstruction = self.decode(z)
        image_loss = fixed_std_gaussian_nll(observations, reconstruction, self.image_std)

        # One row per transition (B * T, .): a linear layer on (B, T, .) adds two views each way
        transitions = torch.cat([z[:, :-1], actions, z[:, 1:]], dim=-1).flatten(0, 1)
        reward_mean, reward_std = self.reward_decoder(transitions)
        reward_nll = gaussian_nll(rewards, reward_mean.view_as(rewards), reward_std.view_as(rewards))
        reward_loss = self.reward_loss_weight * (reward_nll * (1.0 - terminated)).sum(dim=1).mean()
        if rolled_transitions:
            terms["overshooting_reward_loss"] = self.reward_overshooting_weight * self._rolled_reward_nll(
                rolled_transitions, rewards, terminated
            )

        # log(p + 1e-6) and log(1 - p + 1e-6) from the logit without cancellation: logaddexp(log p, log 1e-6).
        logits = self.cost_decoder(transitions).view_as(costs)
        log_eps = logits.new_full((), _LOG_COST_EPS)
        log_p = torch.logaddexp(F.logsigmoid(logits), log_eps)
        log_not_p = torch.logaddexp(F.logsigmoid(-logits), log_eps)
        cost_ll = torch.where(costs > 0, self.cost_positive_weight * log_p, log_not_p)
        cost_loss = -self.cost_loss_weight * cost_ll.sum(dim=1).mean()

        total = kl + image_loss + reward_loss + cost_loss
        if self.overshooting_depth > 1:
            total = total + terms["overshooting_kl"]
        if rolled_transitions:
            total = total + terms["overshooting_reward_loss"]
        terms.update(image_loss=image_loss, reward_loss=reward_loss, cost_loss=cost_loss)
        with torch.no_grad():  # computed without gradient, nothing to detach
            extremes = {
                "prior_std_min": prior_std[:, 1:].amin(),
                "posterior_std_min": z1_std.amin(),
                "z_abs_max": z.abs().amax(),
                "reconstruction_abs_max": reconstruction.abs().amax(),
            }
        return total, {**{key: value.detach() for key, value in terms.items()}, **extremes}, other_z

    def _rolled_reward_nll(self, rolled_transitions: list[Tensor], rewards: Tensor, terminated: Tensor) -> Tensor:
        """
        Mean over the depths of the reward decoder's NLL of the rewards, summed over the starts (terminal transitions
        masked), mean over the batch.

        :param rolled_transitions: per depth d = 1 .. D, (B, starts, transition_dim) rolled from the starts t = 0, s, ..
            <= T-d (``overshooting_stride`` s)
        :param rewards: (B, T) reward of transition t -> t+1; the roll's depth-d transition from t is t+d-1 -> t+d
        :param terminated: (B, T)
        """
        # One decoder pass over every depth's transitions, side by side along the starts: at depth 16 (cpu_pixels32's
        # sizes, windows of 20) the eager loss and its backward dispatch 4,329 ops instead of 5,433 with a pass per depth
        starts = [transitions.shape[1] for transitions in rolled_transitions]
        stride = self.overshooting_stride
        targets = [slice(rolled, rolled + stride * count, stride) for rolled, count in enumerate(starts)]
        mean, std = self.reward_decoder(torch.cat(rolled_transitions, dim=1))
        nll = gaussian_nll(torch.cat([rewards[:, target] for target in targets], dim=1), mean.squeeze(-1), std.squeeze(-1))
        masked = nll * (1.0 - torch.cat([terminated[:, target] for target in targets], dim=1))
        return torch.stack([part.sum(dim=1).mean() for part in masked.split(starts, dim=1)]).mean()

    def sample_latents(self, observations: Tensor, actions: Tensor, start: LatentStart | None = None) -> Tensor:
        """
        Posterior samples ``z = [z1, z2]`` (B, T+1, z_dim) of observations (B, T+1, *obs_shape), actions (B, T, A), after
        ``start`` (a burn-in's, or None).
        """
        self._check_sequence(observations, actions)
        return self.latents_from_features(self.encode(observations), actions, start)

    def cost_probability(self, z: Tensor, actions: Tensor, next_z: Tensor) -> Tensor:
        """The cost decoder's p(c > 0) of transitions z (N, z_dim), actions (N, A) -> next_z (N, z_dim), shape (N,)."""
        return torch.sigmoid(self.cost_decoder(torch.cat([z, actions, next_z], dim=-1))).squeeze(-1)

    def latents_from_features(self, features: Tensor, actions: Tensor, start: LatentStart | None = None) -> Tensor:
        """
        Posterior samples ``z = [z1, z2]`` (B, T+1, z_dim) of encoder features (B, T+1, F) and actions (B, T, A), after
        ``start`` (a burn-in's, or None).
        """
        rollout = self.posterior(features, actions, start=start)
        return torch.cat([rollout.z1, rollout.z2], dim=-1)

    def filter_step(
        self, feature: Tensor, z2_prev: Tensor, action_prev: Tensor, episode_start: Tensor, deterministic: bool = False
    ) -> tuple[Tensor, Tensor]:
        """
        One step of the online belief filter used when acting, batched over N environments.

        :param feature: (N, feature_dim) encoder feature of the current frame
        :param z2_prev: (N, z2_dim) previous z2 (ignored where ``episode_start``)
        :param action_prev: (N, A) previous action (ignored where ``episode_start``)
        :param episode_start: (N,) bool, True where the frame is the first of an episode
        :param deterministic: use the distribution means instead of samples
        :return: z1 (N, z1_dim) and z2 (N, z2_dim)
        """
        start = episode_start.to(torch.bool).view(-1, 1)
        z1, z1_std = self._z1_opening_or_next(feature, z2_prev, action_prev, start)
        if not deterministic:
            z1 = z1 + z1_std * torch.randn_like(z1)
        z2, z2_std = self._z2_opening_or_next(z1, z2_prev, action_prev, start)
        if not deterministic:
            z2 = z2 + z2_std * torch.randn_like(z2)
        return z1, z2
