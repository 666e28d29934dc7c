"""
The latent model's convolutional encoder and decoder for frames of any size from 32x32 up, and the checks of the
encoder and decoder a user passes in their place.

The layers follow from the frame's size: stride-2 convolutions halve the map (rounding up) until its longer side is
below 8, then one convolution whose kernel covers the remaining map gives the feature; the decoder mirrors them. On the
thesis's 64x64 frames that is its four stride-2 layers and a 4x4 convolution, on 32x32 frames the same with three:
the layers, parameter names and initialisation of both are the published networks'. Frames of 84x84 and 96x96 end on
6x6 maps after four stages, 128x128 after five on 4x4 (the fifth as wide as the fourth), 64x48 after four on 4x3.
"""

import itertools
import torch
from torch import nn

from sb3_dsslac.nn.convolutions import DenseConv2d, DenseConvTranspose2d, SubpixelConvTranspose2d

# The smallest side of a frame the conv encoder takes, in pixels, and the largest ratio of its longer side to its shorter
MIN_IMAGE_SIDE = 32
MAX_ASPECT_RATIO = 4
# The stride-2 stages stop once the map's longer side is below this: 64x64 frames end on 4x4 maps, as in the thesis
_STOP_BELOW = 8
# Kernel and padding of each stride-2 stage: the first 5x5, the others 3x3 (the thesis's); both halve a side, rounding up
_FIRST_STAGE = (5, 2)
_LATER_STAGES = (3, 1)


def check_image_shape(observation_shape: tuple[int, ...]) -> None:
    """
    Raise a ValueError naming the shape and the sizes accepted when the conv encoder cannot take (C, H, W) frames.

    :param observation_shape: (C, H, W), channels first
    """
    _, height, width = observation_shape
    if min(height, width) < MIN_IMAGE_SIDE or max(height, width) > MAX_ASPECT_RATIO * min(height, width):
        raise ValueError(
            f"Unsupported image shape {tuple(observation_shape)} (C, H, W): the conv encoder takes frames of at least "
            f"{MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE} pixels whose longer side is at most {MAX_ASPECT_RATIO} times the shorter. "
            f"Resize the observations (e.g. width=64, height=64 in safety_envs), or pass an encoder_class and a "
            "decoder_class of your own in policy_kwargs."
        )


def image_map_sizes(height: int, width: int) -> list[tuple[int, int]]:
    """
    The map's (height, width) in pixels at the input and after each stride-2 stage of the encoder (each halves both
    sides, rounding up), until the longer side is below 8: [(64, 64), (32, 32), (16, 16), (8, 8), (4, 4)] for 64x64.
    """
    sizes = [(height, width)]
    while max(sizes[-1]) >= _STOP_BELOW:
        sizes.append(tuple(-(-side // 2) for side in sizes[-1]))  # type: ignore[arg-type]
    return sizes


def stage_widths(widths: tuple[int, ...], stages: int) -> tuple[int, ...]:
    """The output channels of ``stages`` stride-2 stages: the first of ``widths``, then the last one repeated."""
    return tuple(widths[:stages]) + (widths[-1],) * max(0, stages - len(widths))


def image_encoder(channels: int, height: int, width: int, feature_dim: int, widths: tuple[int, ...]) -> nn.Sequential:
    """
    Conv encoder (N, C, H, W) -> (N, feature_dim, 1, 1), ELU after every layer (output included): the stride-2 stages
    of ``image_map_sizes`` with ``stage_widths`` output channels (kernels 5, then 3), then a convolution whose kernel
    covers the last map (4x4 on 64x64 and 32x32 frames).
    """
    sizes = image_map_sizes(height, width)
    stages = stage_widths(widths, len(sizes) - 1)
    layers: list[nn.Module] = []
    in_ch = channels
    for index, out_ch in enumerate(stages):
        kernel, pad = _FIRST_STAGE if index == 0 else _LATER_STAGES
        layers += [nn.Conv2d(in_ch, out_ch, kernel, stride=2, padding=pad), nn.ELU()]
        in_ch = out_ch
    layers += [DenseConv2d(in_ch, feature_dim, sizes[-1], stride=1, padding=0), nn.ELU()]
    return nn.Sequential(*layers)


def _output_padding(size: tuple[int, int]) -> tuple[int, int]:
    """The output padding that makes a stride-2 transposed convolution (kernel 3 pad 1, or 5 pad 2) end on ``size``."""
    return (1 - size[0] % 2, 1 - size[1] % 2)


def image_decoder(z_dim: int, channels: int, height: int, width: int, widths: tuple[int, ...]) -> nn.Sequential:
    """
    ConvTranspose decoder (N, z_dim, 1, 1) -> (N, C, H, W), LeakyReLU(0.2) after every layer (output included): the
    encoder's layers mirrored, from a transposed convolution onto its last map up through its stages' sizes.
    """
    sizes = image_map_sizes(height, width)
    mirrored = tuple(reversed(stage_widths(widths, len(sizes) - 1)))
    layers: list[nn.Module] = [DenseConvTranspose2d(z_dim, mirrored[0], sizes[-1], stride=1, padding=0), nn.LeakyReLU(0.2)]
    kernel, pad = _LATER_STAGES
    for (in_ch, out_ch), size in zip(itertools.pairwise(mirrored), reversed(sizes[1:-1]), strict=True):
        padding = _output_padding(size)
        layers += [nn.ConvTranspose2d(in_ch, out_ch, kernel, stride=2, padding=pad, output_padding=padding), nn.LeakyReLU(0.2)]
    kernel, pad = _FIRST_STAGE
    output = SubpixelConvTranspose2d(
        mirrored[-1], channels, kernel, stride=2, padding=pad, output_padding=_output_padding(sizes[0])
    )
    layers += [output, nn.LeakyReLU(0.2)]
    return nn.Sequential(*layers)


def _trial_output(network: nn.Module, x: torch.Tensor, role: str, takes: str) -> torch.Tensor:
    """
    ``network``'s output on ``x`` without gradient in eval mode (its mode restored): a TypeError if it is no module, a
    ValueError if it fails.
    """
    if not isinstance(network, nn.Module):
        raise TypeError(f"{role} must build a torch.nn.Module, it built a {type(network).__name__}")
    was_training = network.training
    network.eval()
    try:
        with torch.no_grad():
            return network(x)
    except Exception as error:
        raise ValueError(f"{role} {type(network).__name__} failed on {takes} {tuple(x.shape)}: {error}") from error
    finally:
        network.train(was_training)


def _shape_of_floats(out: object) -> tuple[int, ...] | None:
    """The shape of a floating-point tensor, None for anything else."""
    return tuple(out.shape) if isinstance(out, torch.Tensor) and out.is_floating_point() else None


def _describe(out: object) -> str:
    """A tensor's dtype and shape, or another value's type."""
    return f"{out.dtype} {tuple(out.shape)}" if isinstance(out, torch.Tensor) else f"a {type(out).__name__}"


def check_encoder(encoder: nn.Module, observation_shape: tuple[int, ...], feature_dim: int) -> None:
    """
    Raise a ValueError unless ``encoder`` maps (N, *observation_shape) floats to (N, feature_dim) or
    (N, feature_dim, 1, 1) floats (tried on two zero observations, on the CPU).
    """
    out = _trial_output(encoder, torch.zeros(2, *observation_shape), "encoder_class", "observations")
    if _shape_of_floats(out) not in ((2, feature_dim), (2, feature_dim, 1, 1)):
        raise ValueError(
            f"encoder_class {type(encoder).__name__} must map observations (N, *{tuple(observation_shape)}) to floats "
            f"(N, feature_dim={feature_dim}) or (N, {feature_dim}, 1, 1); for N=2 it gave {_describe(out)}"
        )


def check_decoder(decoder: nn.Module, z_dim: int, observation_shape: tuple[int, ...]) -> None:
    """
    Raise a ValueError unless ``decoder`` maps latents (N, z_dim) to (N, *observation_shape) floats (tried on two zero
    latents, on the CPU).
    """
    out = _trial_output(decoder, torch.zeros(2, z_dim), "decoder_class", "latents")
    if _shape_of_floats(out) != (2, *observation_shape):
        raise ValueError(
            f"decoder_class {type(decoder).__name__} must map latents (N, z_dim={z_dim}) to floats "
            f"(N, *{tuple(observation_shape)}), the observations' shape; for N=2 it gave {_describe(out)}"
        )
