"""
Where one DS-SLAC update's time goes on the CPU: the FLOPs, forward and backward time of each part of the update
(encoder, decoder, latent filter, latent heads, critics, actor, optimizer steps), and the ops that take the most time.

    python benchmarks/tools/update_profile.py                 # cpu_pixels32 (32x32 frames), eager: under a minute on 2 cores
    python benchmarks/tools/update_profile.py --size 64       # the cpu_pixels shapes (64x64 frames)
    python benchmarks/tools/update_profile.py --compile       # compile_updates: the op table shows the compiled kernels
    python benchmarks/tools/update_profile.py --compile --free-convolutions   # the floor with the convolutions' time measured

The model's buffer holds ``--fill`` random agent steps of SafetyGym/PointGoal1-v0 pixels; 10 updates warm it up
(and compile them with ``--compile``). Printed: the core's single-thread sgemm speed (the reference for the GFLOP/s
below), the updates/s (median of 3 timed bursts of ``--updates`` updates), then two tables:

- by part, per update: the FLOPs (``FlopCounterMode`` over one eager update: matrix products and convolutions, not
  the elementwise ops), and the forward, backward and total milliseconds under ``torch.profiler`` over
  ``--profile-updates`` eager updates. Forward hooks on each part's modules, and wrappers of the methods by which the
  update calls the latent model and the actor, open a profiler range named by the part; a part's forward time is the
  self time of the ops (and of the Python between them) in its ranges, the innermost range winning (the filter's
  holds the encoder's). A backward node is the part's in whose range the forward op that created it ran (matched by
  the autograd sequence number). "other" is the rest of the profiled update: sampling the windows, preprocessing the
  frames, the critics' and the actor's losses, the entropy coefficient's step, the Polyak update, the NaN checks;
  its backward: the nodes of those losses and the capture of the parameters' gradients;
- by op: the ``--top`` ops by self CPU time, in a profile without the ranges (with ``--compile``, of the compiled
  update; its by-part table is of the eager update, the only one with modules and autograd nodes to attribute to);
- the floor: the timed update less its convolutions and matrix products (their share of the by-op profile's self
  time, the dispatching ops around them included), plus their FLOPs at the sgemm's rate: what the update would take
  if every counted FLOP ran as fast as a large matrix product on this core and everything else (elementwise ops,
  copies, the optimizer, Python) stayed as it is. With ``--free-convolutions`` the convolutions' time is measured
  without the profiler: a second model whose convolution layers are free stand-ins of the same shapes
  (``FreeConvolution``: the same parameters and output layouts, next to no arithmetic) is timed the same way, and the
  convolutions take the difference.

The profiler slows the many small ops of an eager update down: the by-part shares are of the profiled update, and
its last row is the update timed without the profiler.
"""

import argparse
import contextlib
import math
import statistics
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

# Run from a checkout: the benchmarks' shared modules (machine.py)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gymnasium as gym
import torch as th
from machine import cpu_model
from torch import nn
from torch.autograd.profiler_util import FunctionEvent
from torch.profiler import ProfilerActivity, profile, record_function
from torch.utils.flop_counter import FlopCounterMode
from torch.utils.hooks import RemovableHandle

import safety_envs  # noqa: F401  (registers the SafetyGym/* ids)
import sb3_dsslac.engine.gradient_step as gradient_step_module
from pathlib import Path

# Run from a checkout: the benchmarks' shared modules (machine.py)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from sb3_dsslac import DSSLAC
from sb3_dsslac.nn.convolutions import DenseConv2d, DenseConvTranspose2d
from sb3_dsslac.presets import preset_env_kwargs, preset_hyperparams

ENV_ID = "SafetyGym/PointGoal1-v0"

# The parts of an update: label -> the policy's modules (paths below it) whose forward and backward passes are the
# part's. A part holds its modules less those of the other parts inside them: the filter is the latent model less
# its encoder, decoder and heads, i.e. the posterior rollout (one custom autograd Function), the first frame's z1 and
# z2 networks and the latent loss's terms
PARTS: dict[str, tuple[str, ...]] = {
    "encoder": ("latent.encoder",),
    "decoder": ("latent.decoder",),
    "filter": ("latent",),
    "latent heads (z1 prior, reward, cost)": ("latent.z1_prior", "latent.reward_decoder", "latent.cost_decoder"),
    "reward critics (twin Q, target)": ("critic", "critic_target"),
    "cost critic (IQN, target)": ("cost_critic", "cost_critic_target"),
    "actor": ("actor",),
}
OPTIMIZER = "optimizer (clip + Adam)"
OTHER = "other (sampling, preprocessing, glue)"
# The methods by which the update calls these modules instead of their forward pass (wrapped in the part's range)
ENTRY_POINTS: dict[str, tuple[str, ...]] = {
    "latent": ("loss_and_filter", "sample_latents", "encode", "latents_from_features"),
    "actor": ("action_log_prob",),
}
_BACKWARD_NODE = "autograd::engine::evaluate_function: "
# The profiler's names of the ops that do the counted arithmetic (FlopCounterMode's ops), by kind
MATRIX_PRODUCT_OPS = frozenset({"aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm"})
ARITHMETIC_KINDS = ("convolutions", "matrix products")


def arithmetic_kind(op_name: str) -> str | None:
    """``ARITHMETIC_KINDS``' entry of an op (profiler ``aten::mm`` or FLOP counter ``aten.mm`` names), None for the rest."""
    name = op_name.replace(".", "::", 1)
    if "convolution" in name:
        return "convolutions"
    return "matrix products" if name in MATRIX_PRODUCT_OPS else None


class FreeConvolution(nn.Module):
    """
    A stand-in for a convolution layer at next to no arithmetic: the layer's output shape and memory layout, written
    out from one input element times each output channel's weight sum, plus the bias. It holds the layer's own
    parameters, so the optimizer steps the same tensors and gradients still reach them and the layer's input.
    """

    def __init__(self, layer: nn.Conv2d | nn.ConvTranspose2d) -> None:
        super().__init__()
        self.weight, self.bias = layer.weight, layer.bias
        self.transposed = isinstance(layer, nn.ConvTranspose2d)
        output_padding = layer.output_padding[0] if self.transposed else 0
        self.geometry = (layer.kernel_size[0], layer.stride[0], int(layer.padding[0]), output_padding)  # type: ignore[arg-type]

    def forward(self, x: th.Tensor) -> th.Tensor:
        """(N, C, H, H) -> (N, C', O, O), O as the layer computes it."""
        kernel, stride, padding, output_padding = self.geometry
        size = x.shape[-1]
        if self.transposed:
            out_size = (size - 1) * stride - 2 * padding + kernel + output_padding
            per_channel = self.weight.sum(dim=(0, 2, 3))
        else:
            out_size = (size + 2 * padding - kernel) // stride + 1
            per_channel = self.weight.sum(dim=(1, 2, 3))
        value = x[:1, :1, :1, :1].reshape(1) * per_channel
        if self.bias is not None:
            value = value + self.bias
        layout = th.channels_last if x.is_contiguous(memory_format=th.channels_last) else th.contiguous_format
        out = value.view(1, -1, 1, 1).expand(x.shape[0], -1, out_size, out_size)
        return out.contiguous(memory_format=layout)


def free_convolutions(model: DSSLAC) -> None:
    """
    Replace the latent model's convolution layers by ``FreeConvolution``: every ``nn.Conv2d`` and ``nn.ConvTranspose2d``
    of its encoder and decoder but the two that run as one matrix product (``DenseConv2d`` on its kernel-sized input,
    ``DenseConvTranspose2d`` from 1x1), i.e. the layers whose ops ``arithmetic_kind`` calls convolutions.
    """
    latent = model.policy.latent
    for network in (latent.encoder, latent.decoder):
        for index, layer in enumerate(network):
            convolution = isinstance(layer, nn.Conv2d | nn.ConvTranspose2d)
            if convolution and not isinstance(layer, DenseConv2d | DenseConvTranspose2d):
                network[index] = FreeConvolution(layer)


def build_model(preset: str, env_kwargs: dict[str, Any], fill: int, compile_updates: bool, free: bool = False) -> DSSLAC:
    """
    A ``preset`` model on PointGoal1 pixels whose buffer holds ``fill`` random agent steps, after one update (the
    setup of compare_trees.py's timing: one rollout of ``fill + 1`` steps, then one gradient step); with ``free``, its
    convolutions replaced by ``FreeConvolution`` before that update (and its compilation).
    """
    env = gym.make(ENV_ID, obs_type="pixels", **env_kwargs)
    overrides = {
        "learning_starts": fill,
        "latent_pretrain_steps": 0,
        "train_freq": fill + 1,
        "gradient_steps": 1,
        "buffer_size": max(fill, 2000),
        "compile_updates": compile_updates,
    }
    model = DSSLAC("LatentPolicy", env, seed=0, **preset_hyperparams(preset, overrides))
    if free:
        free_convolutions(model)
    model.learn(fill + 1)
    return model


def sgemm_gflops(size: int = 1024, repeats: int = 7) -> float:
    """One core's float32 matrix-product speed in GFLOP/s: the median of ``repeats`` (size, size) @ (size, size)."""
    threads = th.get_num_threads()
    th.set_num_threads(1)
    a, b = th.randn(size, size), th.randn(size, size)
    th.mm(a, b)
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        th.mm(a, b)
        seconds.append(time.perf_counter() - start)
    th.set_num_threads(threads)
    return 2 * size**3 / statistics.median(seconds) / 1e9


def update_seconds(model: DSSLAC, n_updates: int, rounds: int = 3) -> float:
    """Seconds per update: the median over ``rounds`` timed bursts of ``n_updates`` updates."""
    seconds = []
    for _ in range(rounds):
        start = time.perf_counter()
        model.train(gradient_steps=n_updates, batch_size=model.batch_size)
        seconds.append((time.perf_counter() - start) / n_updates)
    return statistics.median(seconds)


@contextlib.contextmanager
def eager_updates(model: DSSLAC) -> Iterator[None]:
    """The uncompiled update inside the block, also with ``compile_updates`` (its compiled steps come back after)."""
    compiled, model.updates.compiled_steps = model.updates.compiled_steps, {}
    try:
        yield
    finally:
        model.updates.compiled_steps = compiled


@contextlib.contextmanager
def part_ranges(policy: nn.Module, enter: Callable[[str], None], leave: Callable[[], None]) -> Iterator[None]:
    """
    Inside the block, ``enter(label)`` and ``leave()`` around the forward pass of each part's modules (forward hooks),
    around each call of the methods of ``ENTRY_POINTS``, and ``enter(OPTIMIZER)``, ``leave()`` around every gradient
    clipping and Adam step (``engine.gradient_step``'s ``clip_grads`` and ``adam_step``, wrapped); all gone after it.
    """
    handles: list[RemovableHandle] = []
    for label, paths in PARTS.items():
        for path in paths:
            module = policy.get_submodule(path)
            handles += [
                module.register_forward_pre_hook(lambda *_, label=label: enter(label)),
                module.register_forward_hook(lambda *_: leave(), always_call=True),
            ]
    wrapped: list[tuple[Any, str, str]] = [(gradient_step_module, name, OPTIMIZER) for name in ("clip_grads", "adam_step")]
    for path, methods in ENTRY_POINTS.items():
        label = next(label for label, paths in PARTS.items() if path in paths)
        wrapped += [(policy.get_submodule(path), name, label) for name in methods]
    originals = [getattr(owner, name) for owner, name, _ in wrapped]
    for (owner, name, label), function in zip(wrapped, originals, strict=True):
        setattr(owner, name, _between(enter, leave, label, function))
    try:
        yield
    finally:
        for (owner, name, _), function in zip(wrapped, originals, strict=True):
            if isinstance(owner, nn.Module):
                delattr(owner, name)  # the instance attribute: the class's method shows again
            else:
                setattr(owner, name, function)
        for handle in handles:
            handle.remove()


def _between(
    enter: Callable[[str], None], leave: Callable[[], None], label: str, function: Callable[..., Any]
) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        enter(label)
        try:
            return function(*args, **kwargs)
        finally:
            leave()

    return call


class PartTracker:
    """
    Stands in for ``FlopCounterMode``'s module tracker so that each op's FLOPs count for one part only (and "Global"):
    in a forward pass for the innermost part whose range (``part_ranges``) is open, in a backward pass for the part
    in whose range the autograd node being run was created (by its sequence number); ``OTHER`` outside the ranges.

    FlopCounterMode's own tracker counts an op for every module whose forward or backward pass is under way, and the
    backward passes of modules that share an input are under way together: in torch 2.13 it counted the reward
    decoder's backward for the cost decoder too, and the reward critics' for the cost critic; nor did it see the
    backward pass of a module whose output is the loss a backward pass starts from (the latent model's).
    """

    def __init__(self) -> None:
        self.open: list[tuple[str, int, int]] = []  # label, first sequence number, opening order
        self.closed: list[tuple[int, int, int, str]] = []  # first and end sequence numbers, opening order, label
        self.opened = 0

    @property
    def parents(self) -> set[str]:
        """The names the op now running counts for."""
        node = th._C._current_autograd_node()
        if node is None:
            return {"Global", self.open[-1][0] if self.open else OTHER}
        sequence_nr = node._sequence_nr()
        inside = [(first, order, label) for first, end, order, label in self.closed if first <= sequence_nr < end]
        return {"Global", max(inside)[2] if inside else OTHER}  # the innermost: the last opened of the ranges around it

    def enter(self, label: str) -> None:
        self.open.append((label, th._C._autograd._get_sequence_nr(), self.opened))
        self.opened += 1

    def leave(self) -> None:
        label, first, order = self.open.pop()
        self.closed.append((first, th._C._autograd._get_sequence_nr(), order, label))

    def __enter__(self) -> "PartTracker":
        return self

    def __exit__(self, *_: Any) -> None:
        pass


def count_flops(model: DSSLAC) -> tuple[dict[str, float], dict[str, float]]:
    """
    FLOPs of one eager update (one latent and one actor-critic update) by part of ``PARTS``, ``OPTIMIZER``, ``OTHER``
    (outside them) and "update" (all), and by ``ARITHMETIC_KINDS``; ``FlopCounterMode`` counts matrix products and
    convolutions, forward and backward.
    """
    tracker = PartTracker()
    counter = FlopCounterMode(display=False)
    counter.mod_tracker = tracker  # type: ignore[assignment]
    with eager_updates(model), part_ranges(model.policy, tracker.enter, tracker.leave), counter:
        model.train(gradient_steps=1, batch_size=model.batch_size)
    counts = {name: sum(ops.values()) for name, ops in counter.get_flop_counts().items()}
    flops: dict[str, float] = {label: counts.get(label, 0) for label in (*PARTS, OPTIMIZER, OTHER)}
    if sum(flops.values()) != counts["Global"]:
        raise RuntimeError(f"the FLOPs by part do not add up to the update's: {counts}")
    by_kind = dict.fromkeys(ARITHMETIC_KINDS, 0.0)
    for op, count in counter.get_flop_counts()["Global"].items():
        kind = arithmetic_kind(str(op))
        if kind is None:
            raise RuntimeError(f"FlopCounterMode counted {op}, neither a convolution nor a matrix product")
        by_kind[kind] += count
    return {**flops, "update": counts["Global"]}, by_kind


def _enclosing(event: FunctionEvent, labels: set[str]) -> tuple[str | None, bool]:
    """The innermost range of ``labels`` around ``event`` (None if none), and whether a backward node encloses it."""
    label, backward = None, False
    parent = event.cpu_parent
    while parent is not None:
        if label is None and parent.name in labels:
            label = parent.name
        backward = backward or parent.name.startswith(_BACKWARD_NODE)
        parent = parent.cpu_parent
    return label, backward


def time_by_label(events: list[FunctionEvent], labels: set[str]) -> tuple[dict[str | None, float], dict[str | None, float]]:
    """
    Forward and backward CPU microseconds by label (None: outside every range) of a profile's events.

    Forward: the self time of every event outside the backward pass, to its innermost range (a range's own self time,
    the Python between its ops, included). Backward: the time of each outermost backward node (its children included),
    to the range of the forward op that created it, matched by the autograd sequence number. An op records the number
    the next node will get whether it creates one or not (under ``no_grad`` too): the node's creator is the last op,
    in time, that records its number (or an op inside that one).
    """
    forward: dict[str | None, float] = defaultdict(float)
    backward: dict[str | None, float] = defaultdict(float)
    label_of_node: dict[int, str | None] = {}
    nodes = []
    for event in sorted(events, key=lambda event: (event.time_range.start, -event.time_range.end)):
        label, in_backward = _enclosing(event, labels)
        if event.name.startswith(_BACKWARD_NODE):
            if not in_backward:
                nodes.append(event)
        elif not in_backward:
            forward[event.name if event.name in labels else label] += event.self_cpu_time_total
            if event.sequence_nr >= 0:
                label_of_node[event.sequence_nr] = event.name if event.name in labels else label
    for node in nodes:
        backward[label_of_node.get(node.sequence_nr)] += node.cpu_time_total
    return forward, backward


def profile_parts(model: DSSLAC, n_updates: int) -> tuple[dict[str, tuple[float, float]], float]:
    """
    Forward and backward milliseconds per eager update of each part, ``OPTIMIZER`` and ``OTHER`` (the rest of the
    update; its backward: the nodes of ops outside the parts), over a profile of ``n_updates`` updates; and the
    profiled milliseconds per update.
    """
    ranges: list[record_function] = []

    def enter(label: str) -> None:
        ranges.append(record_function(label))
        ranges[-1].__enter__()

    def leave() -> None:
        ranges.pop().__exit__(None, None, None)

    with eager_updates(model), part_ranges(model.policy, enter, leave), profile(activities=[ProfilerActivity.CPU]) as prof:
        start = time.perf_counter()
        model.train(gradient_steps=n_updates, batch_size=model.batch_size)
        update_ms = (time.perf_counter() - start) * 1e3 / n_updates
    forward, backward = time_by_label(list(prof.events()), {*PARTS, OPTIMIZER})
    per_update = 1e3 * n_updates  # microseconds per profile -> milliseconds per update
    times = {label: (forward[label] / per_update, backward[label] / per_update) for label in (*PARTS, OPTIMIZER)}
    rest = update_ms - sum(sum(pair) for pair in times.values())
    other_backward = backward[None] / per_update
    times[OTHER] = (rest - other_backward, other_backward)
    return times, update_ms


def profile_ops(model: DSSLAC, n_updates: int, top: int) -> tuple[list[tuple[str, float, float]], dict[str, float], float]:
    """
    The ``top`` ops by self CPU time over ``n_updates`` updates as (name, calls, ms) per update; the self ms per update
    of all ops of each of ``ARITHMETIC_KINDS``; and the profiled ms per update.
    """
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        start = time.perf_counter()
        model.train(gradient_steps=n_updates, batch_size=model.batch_size)
        update_ms = (time.perf_counter() - start) * 1e3 / n_updates
    averages = sorted(prof.key_averages(), key=lambda average: average.self_cpu_time_total, reverse=True)
    rows = [(average.key, average.count / n_updates, average.self_cpu_time_total / 1e3 / n_updates) for average in averages]
    by_kind = dict.fromkeys(ARITHMETIC_KINDS, 0.0)
    for name, _, ms in rows:
        kind = arithmetic_kind(name)
        if kind is not None:
            by_kind[kind] += ms
    return rows[:top], by_kind, update_ms


def part_table(
    flops: dict[str, float], times: dict[str, tuple[float, float]], profiled_ms: float, update_ms: float
) -> list[str]:
    """The by-part markdown table: MFLOP, forward, backward and total ms per update, share and GFLOP/s of each part."""

    def gflops(count: float, ms: float) -> str:
        return f"{count / (ms * 1e6):.1f}" if count > 0 and ms > 0 else "-"

    lines = [
        "| part | MFLOP/update | forward ms | backward ms | total ms | share | GFLOP/s |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for label, (forward, backward) in times.items():
        count = flops.get(label, 0.0)
        total = forward + backward
        mflop = f"{count / 1e6:.1f}" if label != OPTIMIZER else "-"
        lines.append(
            f"| {label} | {mflop} | {forward:.2f} | {backward:.2f} | {total:.2f} | {total / profiled_ms:.1%} | "
            f"{gflops(count, total)} |"
        )
    forward_sum, backward_sum = (sum(pair[index] for pair in times.values()) for index in (0, 1))
    lines.append(
        f"| update, profiled | {flops['update'] / 1e6:.1f} | {forward_sum:.2f} | {backward_sum:.2f} | {profiled_ms:.2f} | "
        f"100.0% | {gflops(flops['update'], profiled_ms)} |"
    )
    lines.append(
        f"| update, without the profiler | {flops['update'] / 1e6:.1f} | | | {update_ms:.2f} | "
        f"{update_ms / profiled_ms:.1%} | {gflops(flops['update'], update_ms)} |"
    )
    return lines


def op_table(rows: list[tuple[str, float, float]], profiled_ms: float, width: int = 100) -> list[str]:
    """
    The by-op markdown table: calls and self ms per update, share of the profiled update. Names longer than ``width``
    (inductor's kernels name every op they fuse) keep their start and their end, which numbers the kernel.
    """
    lines = ["| op | calls/update | self ms/update | share |", "|---|---:|---:|---:|"]
    for name, calls, ms in rows:
        shown = name if len(name) <= width else f"{name[: width - 30]}...{name[-27:]}"
        lines.append(f"| {shown.replace('|', '/')} | {calls:.1f} | {ms:.2f} | {ms / profiled_ms:.1%} |")
    return lines


def floor_table(
    update_ms: float,
    profiled_ms: float,
    arithmetic_ms: dict[str, float],
    arithmetic_flops: dict[str, float],
    sgemm: float,
    free_ms: float | None = None,
) -> list[str]:
    """
    The floor markdown table: the timed update; its convolutions and matrix products at their shares of the profiled
    update (``arithmetic_ms`` of ``profiled_ms``), with their GFLOP/s; the rest; and the update with the convolutions
    and matrix products at ``sgemm`` GFLOP/s and the rest as timed, in ms and updates/s. With ``free_ms`` (the update
    timed with ``FreeConvolution`` layers) the convolutions' time is measured instead: the update less that one.
    """
    lines = ["| | ms/update | GFLOP/s | updates/s |", "|---|---:|---:|---:|"]
    lines.append(f"| update | {update_ms:.2f} | | {1e3 / update_ms:.1f} |")
    kinds_ms = {kind: update_ms * arithmetic_ms[kind] / profiled_ms for kind in ARITHMETIC_KINDS}
    if free_ms is not None:
        lines.append(f"| update with free convolutions | {free_ms:.2f} | | {1e3 / free_ms:.1f} |")
        kinds_ms["convolutions"] = update_ms - free_ms
    for kind, ms in kinds_ms.items():
        rate = f"{arithmetic_flops[kind] / (ms * 1e6):.1f}" if ms > 0 else "-"
        lines.append(f"| of which {kind} | {ms:.2f} | {rate} | |")
    rest_ms = max(0.0, update_ms - sum(kinds_ms.values()))
    floor_ms = rest_ms + sum(arithmetic_flops.values()) / (sgemm * 1e6)
    lines.append(f"| the rest (elementwise ops, copies, optimizer, Python) | {rest_ms:.2f} | | |")
    lines.append(f"| floor: the rest, and both at sgemm's {sgemm:.1f} GFLOP/s | {floor_ms:.2f} | | {1e3 / floor_ms:.1f} |")
    return lines


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="cpu_pixels32", help="hyperparameter preset (and its env keywords)")
    parser.add_argument("--size", type=int, choices=[32, 64], help="frame width and height (default: the preset's)")
    parser.add_argument("--updates", type=int, default=40, help="updates per timed burst (3 bursts, median)")
    parser.add_argument("--profile-updates", type=int, default=10, help="updates per profile")
    parser.add_argument("--top", type=int, default=15, help="ops in the by-op table")
    parser.add_argument("--fill", type=int, default=600, help="random agent steps in the replay buffer")
    parser.add_argument("--compile", action="store_true", help="compile_updates=True (a few minutes of compilation)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument(
        "--free-convolutions",
        action="store_true",
        help="also time the update with free stand-ins for the convolutions (a second model, compiled again with "
        "--compile): the floor's convolution time measured, not read off the profile",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    th.set_num_threads(args.threads)
    if args.compile:  # the compiled kernels by name in the profiler's tables
        th._inductor.config.cpp.enable_kernel_profile = True
    sgemm = sgemm_gflops()
    print(f"single-thread sgemm (1024x1024 float32): {sgemm:.1f} GFLOP/s, the core's reference", flush=True)

    env_kwargs = preset_env_kwargs(args.preset, {"width": args.size, "height": args.size} if args.size else None)
    print(f"filling the buffer with {args.fill} random agent steps", file=sys.stderr, flush=True)
    model = build_model(args.preset, env_kwargs, args.fill, args.compile)
    if args.compile:
        print("compiling the update (torch.compile, a few minutes on a CPU)", file=sys.stderr, flush=True)
    model.train(gradient_steps=10, batch_size=model.batch_size)

    print("timing, counting FLOPs and profiling", file=sys.stderr, flush=True)
    update_ms = update_seconds(model, args.updates) * 1e3
    flops, arithmetic_flops = count_flops(model)
    eager_ms = update_ms
    if args.compile:  # the by-part table's reference: the eager update without the profiler
        with eager_updates(model):
            eager_ms = update_seconds(model, args.updates) * 1e3
    times, parts_ms = profile_parts(model, args.profile_updates)
    ops, arithmetic_ms, ops_ms = profile_ops(model, args.profile_updates, args.top)
    free_ms = None
    if args.free_convolutions:
        print("timing the update with free convolutions", file=sys.stderr, flush=True)
        free = build_model(args.preset, env_kwargs, args.fill, args.compile, free=True)
        free.train(gradient_steps=10, batch_size=free.batch_size)
        free_ms = update_seconds(free, args.updates) * 1e3
    if not all(math.isfinite(value) for pair in times.values() for value in pair):
        raise RuntimeError(f"non-finite times by part: {times}")

    size = model.observation_space.shape[-1]  # type: ignore[index]
    update_path = "compiled (compile_updates=True)" if args.compile else "eager"
    print(
        f"\nDS-SLAC update on {cpu_model()}, torch {th.__version__}, {th.get_num_threads()} thread(s); preset {args.preset}, "
        f"{size}x{size} frames; latent batch {model.latent_batch_size}, actor-critic batch {model.batch_size}, sequences "
        f"of {model.sequence_length} transitions; {update_path} update: {1e3 / update_ms:.2f} updates/s ({update_ms:.1f} ms, "
        f"median of 3 x {args.updates}), {flops['update'] / update_ms / 1e6:.1f} GFLOP/s against sgemm's {sgemm:.1f}\n"
    )
    profiled = f"profile of {args.profile_updates} updates"
    eager_note = " (eager update: the by-part profile runs without compile_updates)" if args.compile else ""
    print(f"By part{eager_note}, per update, {profiled}:\n")
    print("\n".join(part_table(flops, times, parts_ms, eager_ms)))
    print(f"\nBy op ({update_path} update), per update, top {args.top} by self CPU time, {profiled}:\n")
    print("\n".join(op_table(ops, ops_ms)))
    measured = (
        "the convolutions as the update less the update with free convolutions, the matrix products at their share of "
        "the by-op profile"
        if free_ms is not None
        else "at their share of the by-op profile"
    )
    print(
        f"\nFloor ({update_path} update): the update as timed, less its convolutions and matrix products ({measured}), "
        f"plus their FLOPs at the sgemm's rate:\n"
    )
    print("\n".join(floor_table(update_ms, ops_ms, arithmetic_ms, arithmetic_flops, sgemm, free_ms)))


if __name__ == "__main__":
    main()
