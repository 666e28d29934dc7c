"""
The latent model's convolution layers, each computed the fastest way we measured on a CPU for its shape, with the
parameters (names, shapes, initialisation) of the ``torch.nn`` layer it subclasses, so checkpoints load either way.

- A convolution whose kernel covers its whole unpadded input (the encoder's last layer, 4x4 onto 4x4) and a transposed
  convolution from a 1x1 input (the decoder's first layer) are one matrix product each: about a fifth of oneDNN's time
  for these shapes, forward and backward. In a channels-last model the products read and write the images in their
  (H, W, C) order, with the weights permuted to match: no copy to NCHW and back around them.
- A stride-2 transposed convolution runs its forward pass as a stride-1 convolution onto ``stride**2`` phase images,
  interleaved by a pixel shuffle (a sub-pixel convolution: each output pixel sums the same products in another order),
  and its backward pass through ATen's own transposed-convolution gradient: oneDNN's transposed convolution onto 3
  channels pads them to 8, and took 2.7x the time of the sub-pixel form (80 frames of 16x16 onto 32x32). It is one
  custom op, opaque to ``torch.compile``: inlined, the shuffle's index (``x // 2``, ``x % 2``) left every loop that read
  the decoder's output scalar (its activation, the image loss, their gradients: 5.2 ms of a 58 ms compiled ``cpu_pixels``
  update), while the op writes its output once, dense in the model's layout, and those loops vectorise. Channels-last,
  the phases' channels are ordered so that the shuffle copies runs of ``stride * C_out`` values, and with the replay
  buffer's frames stored channels-last too the image loss reads both images in one order.
"""

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sb3_dsslac.nn.numerics import autocast_enabled


def _is_channels_last(x: Tensor) -> bool:
    """Whether a 4-d tensor lies in memory as (N, H, W, C) and not also as (N, C, H, W)."""
    return x.is_contiguous(memory_format=torch.channels_last) and not x.is_contiguous()


class DenseConv2d(nn.Conv2d):
    """``nn.Conv2d`` on inputs of the kernel's size (one output) as one matrix product: (N, C, k, k) -> (N, C', 1, 1)."""

    def forward(self, x: Tensor) -> Tensor:
        if tuple(x.shape[-2:]) != self.kernel_size or self.padding != (0, 0):
            return super().forward(x)
        if _is_channels_last(x):  # both flattened in (H, W, C) order: x as it lies in memory
            x, weight = x.permute(0, 2, 3, 1), self.weight.permute(2, 3, 1, 0)
        else:
            weight = self.weight.permute(1, 2, 3, 0)
        # The weight as the product's right factor (k * k * C, C'), the memory F.linear would read, without its transpose
        columns, rows = weight.reshape(-1, self.out_channels), x.reshape(x.shape[0], -1)
        out = rows.mm(columns) if self.bias is None else torch.addmm(self.bias, rows, columns)
        return out.view(x.shape[0], self.out_channels, 1, 1)


class DenseConvTranspose2d(nn.ConvTranspose2d):
    """``nn.ConvTranspose2d`` from a 1x1 input with no padding: one matrix product, (N, C, 1, 1) -> (N, C', k, k)."""

    def forward(self, x: Tensor, output_size: list[int] | None = None) -> Tensor:
        if tuple(x.shape[-2:]) != (1, 1) or self.padding != (0, 0) or self.output_padding != (0, 0) or output_size:
            return super().forward(x, output_size)
        height, width = self.kernel_size
        x = x.reshape(x.shape[0], self.in_channels)
        if _is_channels_last(self.weight):  # a channels-last output, as ATen's layer would give: (N, k, k, C') in memory
            weight = self.weight.permute(0, 2, 3, 1).reshape(self.in_channels, -1)  # (C, k * k * C')
            out = x.mm(weight).view(x.shape[0], height, width, self.out_channels).permute(0, 3, 1, 2)
        else:
            weight = self.weight.reshape(self.in_channels, -1)  # (C, C' * k * k)
            out = x.mm(weight).view(x.shape[0], self.out_channels, height, width)
        return out if self.bias is None else out + self.bias.view(1, -1, 1, 1)


def subpixel_kernel(weight: Tensor, stride: int, channels_last: bool = False) -> Tensor:
    """
    The stride-1 correlation kernels of a stride-``stride`` transposed convolution, one per output phase.

    :param weight: the transposed convolution's weight (C_in, C_out, k, k)
    :param channels_last: order the phases' channels (row phase, column phase, output channel), the order in which a
        channels-last output holds them, instead of ``pixel_shuffle``'s (output channel, row phase, column phase)
    :return: (C_out * stride**2, C_in, m, m) with ``m = ceil(k / stride)``; phase r's tap t is weight tap
        ``r + stride * (m-1-t)``, zero past the kernel. Built by padding, reshaping and flipping only, so its gradient
        is as cheap
    """
    in_channels, out_channels, kernel, _ = weight.shape
    taps = -(-kernel // stride)
    padded = F.pad(weight, (0, stride * taps - kernel, 0, stride * taps - kernel))
    # Tap j = stride * u + r: (C_in, C_out, u_y, r_y, u_x, r_x), then t = m - 1 - u
    phases = padded.view(in_channels, out_channels, taps, stride, taps, stride).flip(2, 4)
    order = (3, 5, 1, 0, 2, 4) if channels_last else (1, 3, 5, 0, 2, 4)
    return phases.permute(order).reshape(out_channels * stride * stride, in_channels, taps, taps)


def _subpixel_layout(x: Tensor, weight: Tensor) -> torch.memory_format:
    """The layout of a sub-pixel convolution's output: channels-last when its input or weight is, as ATen's layer."""
    return torch.channels_last if _is_channels_last(x) or _is_channels_last(weight) else torch.contiguous_format


def _transposed_size(x: Tensor, weight: Tensor, stride: int, padding: int, output_padding: int) -> int:
    """The output height (= width) of a square transposed convolution of ``x`` (N, C_in, H, H)."""
    return (x.shape[-1] - 1) * stride - 2 * padding + weight.shape[-1] + output_padding


def subpixel_conv_transpose2d(
    x: Tensor, weight: Tensor, bias: Tensor | None, stride: int, padding: int, output_padding: int
) -> Tensor:
    """
    ``F.conv_transpose2d`` of square images and kernels as a sub-pixel convolution: (N, C_in, H, H) -> (N, C_out, O, O)
    with ``O = (H - 1) * stride - 2 * padding + k + output_padding``, channels-last when ``x`` or ``weight`` is.
    """
    height, kernel = x.shape[-1], weight.shape[-1]
    out_channels, taps = weight.shape[1], -(-kernel // stride)
    size = _transposed_size(x, weight, stride, padding, output_padding)
    # Output pixel o = stride * q + r - padding sums x[q - i] * weight[r + stride * i]: the phase images' rows q
    first, last = padding // stride, (padding + size - 1) // stride
    before, after = taps - 1 - first, last - (height - 1)
    layout = _subpixel_layout(x, weight)
    channels_last = layout == torch.channels_last
    phase_weight = subpixel_kernel(weight, stride, channels_last).contiguous(memory_format=layout)
    phase_bias = None
    if bias is not None:  # one per phase channel, in the kernel's channel order
        phase_bias = bias.repeat(stride * stride) if channels_last else bias.repeat_interleave(stride * stride)
    if before == after >= 0:  # the convolution's own zero padding: no padded copy of the input
        phases = F.conv2d(x, phase_weight, phase_bias, padding=before)
    else:
        phases = F.conv2d(F.pad(x, (before, after, before, after)), phase_weight, phase_bias)
    offset = padding - stride * first
    batch, _, rows, cols = phases.shape
    if channels_last:
        # In memory (N, q_y, q_x, r_y, r_x * C_out): swapping q_x and r_y lays the rows out as (N, O, O, C_out) in runs
        # of r_x * C_out values, 0.50 ms for 80 64x64 frames against 1.11 for the NCHW shuffle (Intel Xeon, one thread)
        runs = phases.permute(0, 2, 3, 1).reshape(batch, rows, cols, stride, stride * out_channels).transpose(2, 3)
        shuffled = runs.contiguous().view(batch, rows * stride, cols * stride, out_channels).permute(0, 3, 1, 2)
    else:
        # The pixel shuffle as a permuted view, copied once (twice where it crops): half the time of F.pixel_shuffle's
        shuffled = phases.view(batch, -1, stride, stride, rows, cols).permute(0, 1, 4, 2, 5, 3)
        shuffled = shuffled.reshape(batch, -1, rows * stride, cols * stride)
    return shuffled[:, :, offset : offset + size, offset : offset + size].contiguous(memory_format=layout)


@torch.library.custom_op("sb3_dsslac::subpixel_conv_transpose2d", mutates_args=())
def _subpixel_op(x: Tensor, weight: Tensor, bias: Tensor | None, stride: int, padding: int, output_padding: int) -> Tensor:
    """``subpixel_conv_transpose2d`` as one op: (N, C_in, H, H) -> (N, C_out, O, O), dense in ``_subpixel_layout``."""
    return subpixel_conv_transpose2d(x, weight, bias, stride, padding, output_padding)


@_subpixel_op.register_fake
def _(x: Tensor, weight: Tensor, bias: Tensor | None, stride: int, padding: int, output_padding: int) -> Tensor:
    size = _transposed_size(x, weight, stride, padding, output_padding)
    shape = (x.shape[0], weight.shape[1], size, size)
    return torch.empty(shape, dtype=x.dtype, device=x.device, memory_format=_subpixel_layout(x, weight))


def _save_for_backward(ctx, inputs: tuple, output: Tensor) -> None:
    x, weight, bias, stride, padding, output_padding = inputs
    ctx.save_for_backward(x, weight)
    ctx.geometry = (stride, padding, output_padding)
    ctx.has_bias = bias is not None


def _backward(ctx, grad: Tensor) -> tuple:
    """The transposed convolution's gradients from ATen's own kernel (the sub-pixel form's would be slower)."""
    x, weight = ctx.saved_tensors
    stride, padding, output_padding = ctx.geometry
    grad = grad.contiguous(memory_format=_subpixel_layout(x, weight))
    grad_x, grad_weight, grad_bias = torch.ops.aten.convolution_backward(
        grad,
        x,
        weight,
        [weight.shape[1]] if ctx.has_bias else None,
        [stride, stride],
        [padding, padding],
        [1, 1],
        True,
        [output_padding, output_padding],
        1,
        [ctx.needs_input_grad[0], ctx.needs_input_grad[1], ctx.has_bias and ctx.needs_input_grad[2]],
    )
    return grad_x, grad_weight, grad_bias, None, None, None


_subpixel_op.register_autograd(_backward, setup_context=_save_for_backward)


class SubpixelConvTranspose2d(nn.ConvTranspose2d):
    """
    ``nn.ConvTranspose2d`` (stride > 1) whose forward pass is a sub-pixel convolution on square inputs and geometry (no
    dilation or groups); ATen's layer otherwise.
    """

    def forward(self, x: Tensor, output_size: list[int] | None = None) -> Tensor:
        (stride, _), (padding, _), (output_padding, _) = self.stride, self.padding, self.output_padding
        plain = output_size is not None or self.groups != 1 or self.dilation != (1, 1) or x.shape[-1] != x.shape[-2]
        # Square geometry only: the output paddings of a frame whose sides differ in parity (84x83) can differ
        square = all(first == second for first, second in (self.kernel_size, self.stride, self.padding, self.output_padding))
        if plain or not square or autocast_enabled(x.device.type):  # autocast casts the inputs of ATen's own layer only
            return super().forward(x, output_size)
        return _subpixel_op(x, self.weight, self.bias, stride, padding, output_padding)
