"""Frames of any size from 32x32 up, encoders and decoders of the user's, and observations that hold NaN or inf."""

import itertools
import re
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from torch import nn

import sb3_dsslac.nn.latent as latent_module
from sb3_dsslac import DSSLAC
from sb3_dsslac.nn.convolutions import DenseConv2d, DenseConvTranspose2d, SubpixelConvTranspose2d
from sb3_dsslac.nn.image_nets import image_decoder, image_encoder, image_map_sizes
from sb3_dsslac.nn.latent import THESIS_IMAGE_CHANNELS, LatentModel, init_weights
from sb3_dsslac.presets import preset_hyperparams
from tests.synthetic_envs import HazardPointEnv

CPU_WIDTHS = (8, 16, 32, 64)


def _encoder_before_issue_61(channels: int, size: int, feature_dim: int, widths: tuple[int, ...]) -> nn.Sequential:
    """The encoder as built before frames of any size (64x64 and 32x32 only), for the comparison below."""
    specs = tuple(zip(widths, (5, 3, 3, 3), (2, 1, 1, 1), strict=True))[: 4 if size == 64 else 3]
    layers: list[nn.Module] = []
    in_ch = channels
    for out_ch, kernel, pad in specs:
        layers += [nn.Conv2d(in_ch, out_ch, kernel, stride=2, padding=pad), nn.ELU()]
        in_ch = out_ch
    layers += [DenseConv2d(in_ch, feature_dim, 4, stride=1, padding=0), nn.ELU()]
    return nn.Sequential(*layers)


def _decoder_before_issue_61(z_dim: int, channels: int, size: int, widths: tuple[int, ...]) -> nn.Sequential:
    """The decoder as built before frames of any size (64x64 and 32x32 only)."""
    mirrored = tuple(reversed(widths[: 4 if size == 64 else 3]))
    layers: list[nn.Module] = [DenseConvTranspose2d(z_dim, mirrored[0], 4, stride=1, padding=0), nn.LeakyReLU(0.2)]
    for in_ch, out_ch in itertools.pairwise(mirrored):
        layers += [nn.ConvTranspose2d(in_ch, out_ch, 3, stride=2, padding=1, output_padding=1), nn.LeakyReLU(0.2)]
    output = SubpixelConvTranspose2d(mirrored[-1], channels, 5, stride=2, padding=2, output_padding=1)
    layers += [output, nn.LeakyReLU(0.2)]
    return nn.Sequential(*layers)


def _small_latent(shape: tuple[int, ...], **keywords: Any) -> LatentModel:
    return LatentModel(shape, 2, feature_dim=16, z1_dim=4, z2_dim=8, hidden_units=(16,), **keywords)


@pytest.mark.parametrize("size", [64, 32])
@pytest.mark.parametrize("widths", [THESIS_IMAGE_CHANNELS, CPU_WIDTHS])
def test_64x64_and_32x32_keep_the_layers_names_and_draws_of_the_published_networks(size, widths, monkeypatch):
    """The same modules, parameter names and shapes, and (same seed) the same numbers as before, in the model too."""
    torch.manual_seed(0)
    old = (_encoder_before_issue_61(3, size, 200, widths), _decoder_before_issue_61(232, 3, size, widths))
    torch.manual_seed(0)
    new = (image_encoder(3, size, size, 200, widths), image_decoder(232, 3, size, size, widths))
    for before, after in zip(old, new, strict=True):
        assert repr(after) == repr(before)
        assert before.state_dict().keys() == after.state_dict().keys()
        for key, value in before.state_dict().items():
            assert torch.equal(after.state_dict()[key], value), key

    torch.manual_seed(1)
    model = _small_latent((3, size, size), image_channels=widths)
    monkeypatch.setattr(latent_module, "image_encoder", lambda c, h, w, f, ws: _encoder_before_issue_61(c, h, f, ws))
    monkeypatch.setattr(latent_module, "image_decoder", lambda z, c, h, w, ws: _decoder_before_issue_61(z, c, h, ws))
    torch.manual_seed(1)
    reference = _small_latent((3, size, size), image_channels=widths)
    assert model.state_dict().keys() == reference.state_dict().keys()
    for key, value in reference.state_dict().items():
        assert torch.equal(model.state_dict()[key], value), key


def test_the_model_initialises_its_networks_in_the_order_of_one_pass_over_it(monkeypatch):
    """``init_weights`` per network (the user's left out) draws what one ``init_weights(model)`` drew before."""
    torch.manual_seed(2)
    model = _small_latent((3, 64, 64))
    monkeypatch.setattr(latent_module, "init_weights", lambda module: None)
    torch.manual_seed(2)
    reference = _small_latent((3, 64, 64)).to(memory_format=torch.contiguous_format)  # as built, before its layout
    init_weights(reference)
    for key, value in reference.state_dict().items():
        assert torch.equal(model.state_dict()[key], value), key


@pytest.mark.parametrize(
    "height, width, maps",
    [
        (48, 48, [(24, 24), (12, 12), (6, 6)]),
        (84, 84, [(42, 42), (21, 21), (11, 11), (6, 6)]),
        (96, 96, [(48, 48), (24, 24), (12, 12), (6, 6)]),
        (128, 128, [(64, 64), (32, 32), (16, 16), (8, 8), (4, 4)]),
        (48, 64, [(24, 32), (12, 16), (6, 8), (3, 4)]),
        (83, 84, [(42, 42), (21, 21), (11, 11), (6, 6)]),
        (256, 256, [(128, 128), (64, 64), (32, 32), (16, 16), (8, 8), (4, 4)]),
    ],
)
def test_frames_of_other_sizes_halve_to_a_small_map_and_decode_to_their_own_size(height, width, maps):
    assert image_map_sizes(height, width) == [(height, width), *maps]
    model = _small_latent((3, height, width), image_channels=CPU_WIDTHS)
    stages = [layer.out_channels for layer in model.encoder if type(layer) is nn.Conv2d]
    assert stages == [*CPU_WIDTHS[: len(maps)], *[CPU_WIDTHS[-1]] * (len(maps) - 4)]
    assert model.encoder[-2].kernel_size == maps[-1]  # the last convolution covers the last map
    observations = torch.rand(2, 3, 3, height, width)
    features = model.encoder(observations.flatten(0, 1))
    assert features.shape == (6, 16, 1, 1)
    torch.manual_seed(0)
    actions, rewards = torch.rand(2, 2, 2) * 2 - 1, torch.randn(2, 2)
    loss, _ = model.loss(observations, actions, rewards, torch.zeros(2, 2), torch.zeros(2, 2))
    assert torch.isfinite(loss) and model.decode(torch.randn(2, 3, 12)).shape == observations.shape
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


@pytest.mark.parametrize("shape", [(3, 16, 16), (3, 31, 64), (3, 32, 160), (1, 200, 40)])
def test_frames_it_cannot_take_get_one_error_naming_the_shape_and_the_smallest_size(shape):
    with pytest.raises(ValueError, match=rf"Unsupported image shape {re.escape(str(shape))}.*at least 32x32 pixels"):
        _small_latent(shape)


class FlatEncoder(nn.Module):
    """A user's encoder: one linear layer over the flattened frame, (N, C, H, W) -> (N, feature_dim)."""

    def __init__(self, observation_shape: tuple[int, ...], feature_dim: int, hidden: int = 32) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Flatten(), nn.Linear(int(np.prod(observation_shape)), hidden), nn.ReLU())
        self.out = nn.Linear(hidden, feature_dim)
        nn.init.constant_(self.out.weight, 0.01)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.net(x))


class FlatDecoder(nn.Module):
    """A user's decoder: latents (N, z_dim) -> sigmoid images (N, C, H, W)."""

    def __init__(self, z_dim: int, observation_shape: tuple[int, ...], hidden: int = 32) -> None:
        super().__init__()
        self.observation_shape = observation_shape
        self.net = nn.Sequential(nn.Linear(z_dim, hidden), nn.ReLU(), nn.Linear(hidden, int(np.prod(observation_shape))))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(z)).view(-1, *self.observation_shape)


def test_a_users_encoder_and_decoder_replace_the_built_in_ones_and_keep_their_initialisation():
    model = _small_latent((3, 20, 24), encoder_class=FlatEncoder, encoder_kwargs={"hidden": 12}, decoder_class=FlatDecoder)
    assert isinstance(model.encoder, FlatEncoder) and model.encoder.net[1].out_features == 12
    assert isinstance(model.decoder, FlatDecoder)
    assert torch.equal(model.encoder.out.weight, torch.full_like(model.encoder.out.weight, 0.01))
    assert not model.channels_last
    observations = torch.rand(2, 3, 3, 20, 24)
    loss, _ = model.loss(observations, torch.zeros(2, 2, 2), torch.zeros(2, 2), torch.zeros(2, 2), torch.zeros(2, 2))
    loss.backward()
    assert model.encoder.out.weight.grad is not None and model.decoder.net[0].weight.grad is not None


class WrongFeatures(FlatEncoder):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x)[:, :-1]


class WrongImage(FlatDecoder):
    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return super().forward(z).transpose(-1, -2)


class Fails(FlatDecoder):
    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.net(z.view(len(z), 1, -1, 1))


class NotAModule:
    def __init__(self, *arguments: Any) -> None:
        pass


@pytest.mark.parametrize(
    "keywords, error, message",
    [
        (
            {"encoder_class": WrongFeatures},
            ValueError,
            r"encoder_class WrongFeatures must map .* \(N, feature_dim=16\).*\(2, 15\)",
        ),
        (
            {"decoder_class": WrongImage},
            ValueError,
            r"decoder_class WrongImage must map latents \(N, z_dim=12\).*\(2, 3, 40, 32\)",
        ),
        ({"decoder_class": Fails}, ValueError, r"decoder_class Fails failed on latents \(2, 12\)"),
        ({"encoder_class": NotAModule}, TypeError, r"encoder_class must build a torch.nn.Module, it built a NotAModule"),
    ],
)
def test_a_users_network_of_the_wrong_shape_is_refused_as_it_is_built(keywords, error, message):
    with pytest.raises(error, match=message):
        _small_latent((3, 32, 40), **keywords)


class Cropped(gym.ObservationWrapper):
    """The top ``height`` rows of a square frame: 64x48 frames (48 rows of 64) from a 64x64 env."""

    def __init__(self, env: gym.Env, height: int) -> None:
        super().__init__(env)
        _, width, channels = env.observation_space.shape
        self.height = height
        self.observation_space = gym.spaces.Box(0, 255, (height, width, channels), np.uint8)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return observation[: self.height]


def _cpu_preset(**policy_kwargs: Any) -> dict[str, Any]:
    """The ``cpu`` preset with a short warm-up: trains from step 150 to 300, updates every 50 steps."""
    overrides = {"learning_starts": 150, "latent_pretrain_steps": 5, "train_freq": 50, "gradient_steps": 2}
    return preset_hyperparams("cpu", {**overrides, "policy_kwargs": policy_kwargs})


def _trains_saves_and_loads(env: gym.Env, tmp_path: Path, **policy_kwargs: Any) -> DSSLAC:
    model = DSSLAC("LatentPolicy", env, seed=0, device="cpu", **_cpu_preset(**policy_kwargs))
    model.learn(300)
    assert model.num_timesteps == 300 and model._n_updates > 0
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip", env=env, device="cpu")
    observations = np.stack([env.reset(seed=seed)[0] for seed in range(2)])
    expected, _ = model.predict(observations, deterministic=True)
    actual, _ = loaded.predict(observations, deterministic=True)
    np.testing.assert_array_equal(actual, expected)
    assert np.isfinite(actual).all()
    return loaded


@pytest.mark.parametrize("size", [48, 84, 96, 128])
def test_the_cpu_preset_trains_saves_and_loads_on_square_frames_of_other_sizes(size, tmp_path):
    loaded = _trains_saves_and_loads(HazardPointEnv(obs_type="pixels", size=size), tmp_path)
    assert loaded.policy.latent.observation_shape == (3, size, size)


def test_the_cpu_preset_trains_saves_and_loads_on_64x48_frames(tmp_path):
    loaded = _trains_saves_and_loads(Cropped(HazardPointEnv(obs_type="pixels", size=64), height=48), tmp_path)
    assert loaded.policy.latent.observation_shape == (3, 48, 64)


def test_a_users_encoder_and_decoder_train_and_are_saved_and_loaded_with_the_model(tmp_path):
    env = HazardPointEnv(obs_type="pixels", size=24)  # below the built-in networks' 32x32: the user's take any size
    loaded = _trains_saves_and_loads(
        env, tmp_path, encoder_class=FlatEncoder, encoder_kwargs={"hidden": 24}, decoder_class=FlatDecoder
    )
    assert isinstance(loaded.policy.latent.encoder, FlatEncoder) and loaded.policy.latent.encoder.net[1].out_features == 24
    assert isinstance(loaded.policy.latent.decoder, FlatDecoder)
    assert loaded.policy_kwargs["encoder_class"] is FlatEncoder


class NaNAt(gym.Wrapper):
    """Puts NaN (or inf) into the observation of agent step ``step`` of the first episode."""

    def __init__(self, env: gym.Env, step: int, value: float = np.nan) -> None:
        super().__init__(env)
        self.step_with_nan, self.value, self.steps = step, value, 0

    def step(self, action: np.ndarray) -> tuple[Any, ...]:
        observation, *rest = self.env.step(action)
        self.steps += 1
        if self.steps == self.step_with_nan:
            observation = observation.copy()
            observation[1] = self.value
        return (observation, *rest)


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_an_observation_with_nan_or_inf_stops_training_naming_the_env_the_step_and_the_observation(value):
    model = DSSLAC("LatentPolicy", NaNAt(HazardPointEnv(), step=7, value=value), **_cpu_preset())
    with pytest.raises(
        ValueError, match=r"Training env 0 \(<Monitor<NaNAt<HazardPointEnv.*>\) at timestep 7 gave an observation "
    ):
        model.learn(20)
    with pytest.raises(ValueError, match=r"NaN or inf in 1 of its 4 values \(first at \[\(1,\)\]\): \[.*(nan|inf)"):
        DSSLAC("LatentPolicy", NaNAt(HazardPointEnv(), step=3, value=value), **_cpu_preset()).learn(20)


def test_an_episodes_last_observation_with_nan_stops_training_though_the_filter_never_sees_it():
    model = DSSLAC("LatentPolicy", NaNAt(HazardPointEnv(max_episode_steps=30), step=30), **_cpu_preset())
    with pytest.raises(ValueError, match=r"Training env 0 .* at timestep 30 gave an observation with NaN"):
        model.learn(40)


def test_predict_refuses_an_observation_with_nan_before_the_filter():
    model = DSSLAC("LatentPolicy", HazardPointEnv(), **_cpu_preset())
    observations = np.zeros((3, 4), np.float32)
    observations[2, 0] = np.nan
    with pytest.raises(ValueError, match=r"predict\(\)'s observation of env 2 of 3 gave an observation with NaN"):
        model.predict(observations)
    model.predict(observations[:2])  # finite rows act
