"""The latent model's fast convolution layers compute what the torch.nn layers they replace compute."""

import pytest
import torch
from torch import nn

from sb3_dsslac.nn.convolutions import (
    DenseConv2d,
    DenseConvTranspose2d,
    SubpixelConvTranspose2d,
)
from sb3_dsslac.nn.latent import LatentModel


def _same_outputs_and_gradients(
    reference: nn.Module, fast: nn.Module, input_shape: tuple[int, ...], layout: torch.memory_format = torch.contiguous_format
) -> torch.Tensor:
    """Asserts the same outputs and gradients in float64, ``fast``'s weights and input in ``layout``; returns its output."""
    fast.load_state_dict(reference.state_dict())
    x = torch.randn(input_shape, dtype=torch.float64)
    reference.double(), fast.double().to(memory_format=layout)
    expected, got = reference(x.requires_grad_()), fast(x.contiguous(memory_format=layout))
    assert got.shape == expected.shape
    torch.testing.assert_close(got, expected)
    grad_out = torch.randn_like(expected)
    expected_grads = torch.autograd.grad(expected, [x, *reference.parameters()], grad_out)
    got_grads = torch.autograd.grad(got, [x, *fast.parameters()], grad_out)
    for want, have in zip(expected_grads, got_grads, strict=True):
        torch.testing.assert_close(have, want)
    return got


def test_dense_conv2d_is_the_convolution_of_a_kernel_sized_input():
    _same_outputs_and_gradients(nn.Conv2d(32, 64, 4), DenseConv2d(32, 64, 4), (5, 32, 4, 4))


def test_dense_conv2d_falls_back_on_larger_inputs():
    _same_outputs_and_gradients(nn.Conv2d(3, 4, 4), DenseConv2d(3, 4, 4), (2, 3, 7, 7))


def test_dense_conv_transpose2d_is_the_transposed_convolution_of_one_pixel():
    _same_outputs_and_gradients(nn.ConvTranspose2d(80, 32, 4), DenseConvTranspose2d(80, 32, 4), (5, 80, 1, 1))


def test_dense_layers_keep_a_channels_last_model_channels_last():
    """Channels-last images in, channels-last images out, with no copy to NCHW between: the same numbers."""
    layout = torch.channels_last
    _same_outputs_and_gradients(nn.Conv2d(32, 64, 4), DenseConv2d(32, 64, 4), (5, 32, 4, 4), layout)
    out = _same_outputs_and_gradients(nn.ConvTranspose2d(80, 32, 4), DenseConvTranspose2d(80, 32, 4), (5, 80, 1, 1), layout)
    assert out.is_contiguous(memory_format=layout) and not out.is_contiguous()


@pytest.mark.parametrize(
    "channels, kernel, stride, padding, output_padding, size",
    [
        ((8, 3), 5, 2, 2, 1, 16),  # the decoder's output layer at 32x32
        ((8, 3), 5, 2, 2, 1, 32),  # and at 64x64
        ((32, 16), 3, 2, 1, 1, 4),
        ((4, 2), 4, 2, 1, 0, 5),
        ((3, 5), 3, 3, 0, 2, 6),
        ((16, 8), 3, 2, 1, 0, 11),  # 84x84 frames' decoder: 11x11 onto 21x21
        ((8, 3), 5, 2, 2, 1, 42),  # and its output layer
    ],
)
@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last])
def test_subpixel_conv_transpose2d_is_the_transposed_convolution(
    channels, kernel, stride, padding, output_padding, size, layout
):
    layers = [
        cls(*channels, kernel, stride=stride, padding=padding, output_padding=output_padding)
        for cls in (nn.ConvTranspose2d, SubpixelConvTranspose2d)
    ]
    out = _same_outputs_and_gradients(*layers, (3, channels[0], size, size), layout)
    assert out.is_contiguous(memory_format=layout)  # the layout of the model's other layers: no copy to or from it


def test_subpixel_conv_transpose2d_compiles_to_the_same_numbers():
    # About 10 s: torch.compile of the layer's forward and backward
    reference = nn.ConvTranspose2d(8, 3, 5, stride=2, padding=2, output_padding=1)
    fast = SubpixelConvTranspose2d(8, 3, 5, stride=2, padding=2, output_padding=1)
    fast.load_state_dict(reference.state_dict())
    x = torch.randn(2, 8, 16, 16)
    torch.testing.assert_close(torch.compile(fast, fullgraph=True)(x), reference(x), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("height, width", [(32, 32), (64, 64), (84, 84), (48, 64), (84, 83)])
def test_latent_model_loads_the_state_dict_of_plain_convolutions(height, width):
    """Checkpoints of models built from nn.Conv2d / nn.ConvTranspose2d layers load, and give the same images."""
    model = LatentModel(
        (3, height, width), 2, feature_dim=16, z1_dim=4, z2_dim=8, hidden_units=(16,), image_channels=(4, 4, 8, 8)
    )
    plain = {}
    for name, module in model.named_modules():
        if isinstance(module, nn.ConvTranspose2d):
            plain[name] = nn.ConvTranspose2d(
                module.in_channels,
                module.out_channels,
                module.kernel_size,
                module.stride,
                module.padding,
                module.output_padding,
            )
        elif isinstance(module, nn.Conv2d):
            plain[name] = nn.Conv2d(module.in_channels, module.out_channels, module.kernel_size, module.stride, module.padding)
    assert {type(model.get_submodule(name)) for name in plain} >= {DenseConv2d, DenseConvTranspose2d, SubpixelConvTranspose2d}
    state = {f"{name}.{key}": value for name, layer in plain.items() for key, value in layer.state_dict().items()}
    model.load_state_dict({**model.state_dict(), **state})
    observations = torch.rand(2, 3, 3, height, width)
    features = model.encode(observations)
    x = observations.reshape(6, 3, height, width)
    for index, layer in enumerate(model.encoder):
        x = plain[f"encoder.{index}"](x) if f"encoder.{index}" in plain else layer(x)
    torch.testing.assert_close(features, x.view(2, 3, -1), atol=1e-5, rtol=1e-5)
    z = torch.randn(2, 3, model.z_dim)
    y = z.reshape(6, model.z_dim, 1, 1)
    for index, layer in enumerate(model.decoder):
        y = plain[f"decoder.{index}"](y) if f"decoder.{index}" in plain else layer(y)
    torch.testing.assert_close(model.decode(z), y.view(2, 3, 3, height, width), atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last])
def test_subpixel_conv_transpose2d_gradients_compile_to_the_same_numbers(layout):
    """The update compiles its backward pass too (``trace_autograd_ops``): the layer's gradients inside the graph."""
    reference = nn.ConvTranspose2d(8, 3, 5, stride=2, padding=2, output_padding=1)
    fast = SubpixelConvTranspose2d(8, 3, 5, stride=2, padding=2, output_padding=1).to(memory_format=layout)
    fast.load_state_dict(reference.state_dict())
    x = torch.randn(2, 8, 16, 16).contiguous(memory_format=layout).requires_grad_()

    def gradients(layer: nn.Module) -> tuple[torch.Tensor, ...]:
        return torch.autograd.grad(layer(x).square().sum(), [x, *layer.parameters()])

    with torch._dynamo.config.patch(trace_autograd_ops=True):
        compiled = torch.compile(gradients, fullgraph=True)(fast)
    for got, want in zip(compiled, gradients(reference), strict=True):
        torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("bias", [False, True])
def test_subpixel_op_passes_torch_library_checks(channels_last: bool, bias: bool):
    """The custom op's fake tensor (shapes and strides), autograd registration and schema agree with what it computes."""
    layer = SubpixelConvTranspose2d(8, 3, 5, stride=2, padding=2, output_padding=1, bias=bias)
    x = torch.randn(2, 8, 6, 6, requires_grad=True)
    layout = torch.channels_last if channels_last else torch.contiguous_format
    x = x.detach().contiguous(memory_format=layout).requires_grad_()
    out = layer(x)
    assert out.shape == (2, 3, 12, 12) and out.is_contiguous(memory_format=layout)
    torch.library.opcheck(torch.ops.sb3_dsslac.subpixel_conv_transpose2d, (x, layer.weight, layer.bias, 2, 2, 1))
