"""
The steps of ``benchmarks/tools/gpu_check.sh``: the update's correctness on CUDA first, then its speed. No simulator: the
replay buffers hold frames of ``tests.synthetic_envs.HazardPointEnv`` (the update's cost does not depend on what the
frames show), so the check needs no MuJoCo and no EGL.

    PYTHONPATH=. python benchmarks/tools/gpu_check.py checks [--cpu] --out DIR      # the correctness checks, a JSON row each
    PYTHONPATH=. python benchmarks/tools/gpu_check.py speed ROW [--cpu] --out DIR   # one row of the speed table (SPEED_ROWS)
    PYTHONPATH=. python benchmarks/tools/gpu_check.py table --out DIR               # both tables from DIR's rows

The checks, on CUDA (``--cpu``: those that can run on the CPU, at the same small sizes; the others skipped, saying so):

- the sub-pixel transposed convolution (``sb3_dsslac::subpixel_conv_transpose2d``) against ``F.conv_transpose2d``,
  forward and backward, NCHW and channels-last;
- the fused posterior rollout's hand-written backward against autograd's step by step, in float64;
- one seeded burst of 3 updates on the CPU and on CUDA from the same weights, optimizer states and buffer, with TF32
  off and the same random numbers (drawn on the host): every statistic of every update against the CPU's;
- ``torch.cuda.set_sync_debug_mode("error")`` around a burst: no host sync inside it;
- a model saved on the CPU, ``DSSLAC.load(device="cuda")`` (and a file of the format before the multiplier moved to the
  saved attributes), then a burst: the multiplier on the host with its value;
- torch >= 2.13: ``compile_updates=True`` bursts replayed as CUDA graphs, ``counters["inductor"]["cudagraph_skips"]``
  staying 0, no fallback to eager, and no host sync inside a compiled burst.
"""

import argparse
import contextlib
import json
import sys
import time
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path

from typing import Any

# Run from a checkout: the benchmarks' shared modules (machine.py) and the repository (tests' envs)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
import torch as th
import torch.nn.functional as F
from stable_baselines3.common.logger import configure

from sb3_dsslac import DSSLAC
from sb3_dsslac.engine.bursts import compiles_backward
from sb3_dsslac.engine.dispatch import DispatchCounter, optimizer_step_tensors
from sb3_dsslac.nn.convolutions import SubpixelConvTranspose2d
from sb3_dsslac.nn.fused_rollout import posterior_steps
from sb3_dsslac.nn.latent import LatentModel
from sb3_dsslac.nn.numerics import float32_precision
from sb3_dsslac.presets import preset_hyperparams
from tests.synthetic_envs import HazardPointEnv

SKIPPED_ON_CPU = "skipped (no CUDA: --cpu)"
# The check's model: 32x32 pixels, narrow convolutions, small networks (a few seconds per burst on a CPU)
SMALL_MODEL: dict[str, Any] = {
    "buffer_size": 2_000,
    "learning_starts": 10_000,
    "latent_pretrain_steps": 0,
    "batch_size": 8,
    "latent_batch_size": 4,
    "sequence_length": 3,
    "n_quantiles": 8,
    "seed": 0,
    "policy_kwargs": {
        "image_channels": (8, 8, 16, 16),
        "z1_dim": 4,
        "z2_dim": 8,
        "feature_dim": 16,
        "hidden_units": (32, 32),
        "n_cosines": 8,
        "cost_critic_hidden_dim": 32,
    },
}
# Rows of the speed table: (preset or None for DSSLAC's defaults, frame size, compile_updates); thesis: Table 5.2's
# networks, sequences of 10, batches of 64 and 32
SPEED_ROWS: dict[str, tuple[str | None, int, bool]] = {
    "thesis": (None, 64, False),
    "thesis+compile": (None, 64, True),
    "cpu_pixels32_bounded": ("cpu_pixels32_bounded", 32, False),
    "cpu_pixels32_bounded+compile": ("cpu_pixels32_bounded", 32, True),
}
CPU_SPEED_ROWS: dict[str, tuple[str | None, int, bool]] = {"small": (None, 32, False), "small+compile": (None, 32, True)}


def relative_error(value: th.Tensor, reference: th.Tensor) -> float:
    """The largest absolute difference over the reference's largest magnitude (1 if that is 0)."""
    value, reference = value.detach().double().cpu(), reference.detach().double().cpu()
    return float((value - reference).abs().max() / reference.abs().max().clamp(min=1.0e-12))


@contextlib.contextmanager
def host_drawn_noise(seed: int) -> Iterator[None]:
    """
    The update's random numbers (``torch.randn``, ``torch.rand``, ``torch.randn_like``) drawn from one host generator
    seeded with ``seed`` and moved to their device: the same numbers on every device.
    """
    generator = th.Generator().manual_seed(seed)
    randn, rand, randn_like = th.randn, th.rand, th.randn_like

    def on_host(draw: Callable[..., th.Tensor]) -> Callable[..., th.Tensor]:
        def drawn(*size: Any, device: Any = None, dtype: Any = None, **kwargs: Any) -> th.Tensor:
            return draw(*size, generator=generator, dtype=dtype).to(device)

        return drawn

    th.randn, th.rand = on_host(randn), on_host(rand)
    th.randn_like = lambda like, **kwargs: on_host(randn)(like.shape, device=like.device, dtype=like.dtype)
    try:
        yield
    finally:
        th.randn, th.rand, th.randn_like = randn, rand, randn_like


def small_model(device: str | th.device = "cpu", **keywords: Any) -> DSSLAC:
    """The check's model with warm-up data (60 agent steps of random actions) and no pre-training left."""
    model = DSSLAC("LatentPolicy", HazardPointEnv(obs_type="pixels"), device=device, **{**SMALL_MODEL, **keywords})
    model.learn(60)
    model.latent_pretrained = True
    return model


def moved(model: DSSLAC, folder: Path, device: th.device, **keywords: Any) -> DSSLAC:
    """``model`` saved and loaded onto ``device`` with its replay buffer (``keywords``: attributes to change on load)."""
    model.save(folder / "model.zip")
    model.save_replay_buffer(folder / "buffer.pkl")
    loaded = DSSLAC.load(folder / "model.zip", env=HazardPointEnv(obs_type="pixels"), device=device, **keywords)
    loaded.load_replay_buffer(folder / "buffer.pkl")
    loaded.set_logger(configure(None, []))
    return loaded


def burst_statistics(model: DSSLAC, indices: th.Tensor, seed: int) -> dict[str, list[float]]:
    """Every statistic of every update of one burst on the windows ``indices``, with the random numbers of ``seed``."""
    with host_drawn_noise(seed), float32_precision("ieee"):
        history = model.updates.burst(model.replay_buffer, indices.to(model.device), model.current_lagrange_learning_rate)
    return {name: [float(value) for value in values] for name, values in history.items()}


def check_subpixel(device: th.device, folder: Path) -> str:
    errors = []
    for layout in (th.contiguous_format, th.channels_last):
        th.manual_seed(0)
        layer = SubpixelConvTranspose2d(16, 3, 5, stride=2, padding=2, output_padding=1).to(device, memory_format=layout)
        x = th.randn(8, 16, 16, 16, device=device).contiguous(memory_format=layout).requires_grad_()
        with float32_precision("ieee"):
            out = layer(x)
            reference = F.conv_transpose2d(x, layer.weight, layer.bias, stride=2, padding=2, output_padding=1)
            grad = th.randn_like(reference)
            grads = th.autograd.grad(out, (x, layer.weight, layer.bias), grad)
            reference_grads = th.autograd.grad(reference, (x, layer.weight, layer.bias), grad)
        assert out.is_contiguous(memory_format=layout), "the output is not in the input's layout"
        errors += [relative_error(out, reference), *map(relative_error, grads, reference_grads)]
    assert max(errors) < 1e-4, f"relative errors {errors}"
    return f"forward, input, weight and bias gradients within {max(errors):.1e} (NCHW and channels-last)"


def check_rollout(device: th.device, folder: Path) -> str:
    th.manual_seed(0)
    model = LatentModel((9,), 2, feature_dim=6, z1_dim=3, z2_dim=4, hidden_units=(7, 7)).double().to(device)
    batch, steps = 5, 4

    def randn(*shape: int) -> th.Tensor:
        return th.randn(*shape, dtype=th.float64, device=device)

    features, actions = randn(batch, steps, 6).requires_grad_(), randn(batch, steps, 2).requires_grad_()
    z1_mean, z1_std = model.z1_posterior_init(randn(batch, 6))
    z1 = z1_mean + z1_std * randn(batch, 3)
    z2_mean, z2_std = model.z2_init(z1)
    first = (z1_mean, z1_std, z1, z2_mean + z2_std * randn(batch, 4))
    noise = randn(steps, batch, 3), randn(steps, batch, 4)
    inputs = [features, actions, *model.parameters()]

    def outputs_and_grads(rollout: tuple[th.Tensor, ...]) -> list[th.Tensor]:
        weights = [th.linspace(-1.0, 2.0, value.numel(), dtype=th.float64, device=device).view_as(value) for value in rollout]
        loss = sum((value * weight).sum() for value, weight in zip(rollout, weights, strict=True))
        return [*rollout, *th.autograd.grad(loss, inputs, retain_graph=True, materialize_grads=True)]

    fused = outputs_and_grads(posterior_steps(features, actions, first, *noise, model.z1_posterior, model.z2_transition))
    reference = outputs_and_grads(model._posterior_steps(features, actions, first, *noise))
    error = max(map(relative_error, fused, reference))
    assert error < 1e-10, f"relative error {error:.1e}"
    return f"latents and {len(inputs)} gradients within {error:.1e} (float64)"


def check_burst_against_cpu(device: th.device, folder: Path) -> str:
    model = small_model()
    on_device = moved(model, folder, device)
    indices = model.replay_buffer.sample_indices(3, model.latent_batch_size + model.batch_size)
    expected = burst_statistics(model, indices, seed=5)
    statistics = burst_statistics(on_device, indices, seed=5)
    assert statistics.keys() == expected.keys()
    # The first latent statistics come before any weight moved; after that, a gradient that rounding alone keeps from
    # zero moves its weight by about the step size in Adam's first step whichever the device
    first = max(relative_error(th.tensor(values[0]), th.tensor(expected[name][0])) for name, values in statistics.items())
    later = max(relative_error(th.tensor(values), th.tensor(expected[name])) for name, values in statistics.items())
    assert first < 1e-3 and later < 5e-2, f"first update {first:.1e}, all updates {later:.1e}"
    return f"{len(statistics)} statistics x 3 updates: first update within {first:.1e}, all within {later:.1e}"


def burst_without_sync(model: DSSLAC, updates: int) -> None:
    """A burst of ``updates`` updates under ``set_sync_debug_mode("error")``: any host sync inside it raises."""
    indices = model.replay_buffer.sample_indices(updates, model.latent_batch_size + model.batch_size)
    th.cuda.set_sync_debug_mode("error")
    try:
        history = model.updates.burst(model.replay_buffer, indices, model.current_lagrange_learning_rate)
    finally:
        th.cuda.set_sync_debug_mode("default")
    model.updates.end_burst(history, 0, 0)


def check_no_sync_in_a_burst(device: th.device, folder: Path) -> str:
    model = moved(small_model(), folder, device)
    model.train(gradient_steps=2, batch_size=model.batch_size)  # the device's one-off set-ups (handles, allocations)
    burst_without_sync(model, 3)
    return "3 eager updates under set_sync_debug_mode('error')"


def check_load_on_device(device: th.device, folder: Path) -> str:
    model = small_model()
    model.lagrange_raw.fill_(0.7)
    loaded = moved(model, folder, device)
    assert loaded.lagrange_raw.is_cpu and loaded.lagrange_raw.item() == 0.7, loaded.lagrange_raw
    loaded.train(gradient_steps=2, batch_size=loaded.batch_size)
    assert next(loaded.policy.parameters()).device.type == device.type
    # The format before the multiplier moved into the saved attributes: a torch variable, which SB3 loads on `device`
    torch_save_params = DSSLAC._get_torch_save_params
    DSSLAC._get_torch_save_params = lambda self: (torch_save_params(self)[0], ["log_ent_coef", "lagrange_raw"])
    try:
        model.save(folder / "old.zip")
    finally:
        DSSLAC._get_torch_save_params = torch_save_params
    old = DSSLAC.load(folder / "old.zip", device=device)
    assert old.lagrange_raw.is_cpu and old.lagrange_raw.item() == 0.7, old.lagrange_raw
    return f"multiplier {loaded.lagrange_multiplier:.4f} on the host, a burst of 2 updates on {device.type}"


def check_cuda_graphs(device: th.device, folder: Path) -> str:
    if not compiles_backward():
        return f"skipped (torch {th.__version__}: compile_updates runs eagerly before 2.13)"
    from torch._dynamo.utils import counters

    model = moved(small_model(), folder, device, compile_updates=True)
    skips = counters["inductor"]["cudagraph_skips"]
    start = time.perf_counter()
    model.train(gradient_steps=2, batch_size=model.batch_size)  # compiles both steps, records the graphs
    compile_seconds = time.perf_counter() - start
    model.train(gradient_steps=2, batch_size=model.batch_size)
    assert model.updates.compiled_steps, "compile_updates fell back to eager"
    burst_without_sync(model, 2)
    skipped = counters["inductor"]["cudagraph_skips"] - skips
    assert skipped == 0, f"cudagraph_skips {skipped} (run with TORCH_LOGS=perf_hints for the reason)"
    return f"cudagraph_skips 0, no sync in a compiled burst, first burst (compilation) {compile_seconds:.0f} s"


CHECKS: dict[str, tuple[Callable[[th.device, Path], str], bool]] = {
    # name: (check, runs on the CPU too)
    "sub-pixel op against F.conv_transpose2d": (check_subpixel, True),
    "fused rollout backward against autograd": (check_rollout, True),
    "seeded burst: CPU against the device": (check_burst_against_cpu, True),
    "no host sync inside a burst": (check_no_sync_in_a_burst, False),
    "save, load(device=...), a burst": (check_load_on_device, True),
    "compiled bursts as CUDA graphs": (check_cuda_graphs, False),
}


def run_checks(on_cpu: bool, out: Path) -> int:
    """Each check in turn, its result as a JSON row in ``out/checks.jsonl``; the number that failed."""
    device = th.device("cpu" if on_cpu else "cuda")
    failed = 0
    for name, (check, cpu_too) in CHECKS.items():
        start = time.perf_counter()
        if on_cpu and not cpu_too:
            result, detail = "skip", SKIPPED_ON_CPU
        else:
            folder = out / "work" / check.__name__
            folder.mkdir(parents=True, exist_ok=True)
            try:
                detail = check(device, folder)
                result = "skip" if detail.startswith("skipped") else "pass"
            except Exception as error:  # a check's failure, whatever it is, is a row of the table
                traceback.print_exc()
                result, detail = "FAIL", f"{type(error).__name__}: {error}".splitlines()[0][:300]
                failed += 1
        row = {"check": name, "device": device.type, "result": result, "detail": detail}
        row["seconds"] = round(time.perf_counter() - start, 1)
        print(json.dumps(row), flush=True)
        with open(out / "checks.jsonl", "a") as file:
            file.write(json.dumps(row) + "\n")
    return failed


def speed_row(name: str, on_cpu: bool, out: Path) -> None:
    """One row of the speed table: updates/s of a path, whether it compiled, and what one update dispatches."""
    preset, size, compile_updates = (CPU_SPEED_ROWS if on_cpu else SPEED_ROWS)[name]
    device = th.device("cpu" if on_cpu else "cuda")
    row: dict[str, Any] = {"path": name, "device": device.type, "compile_updates": compile_updates}
    if on_cpu and compile_updates:
        row["compiled"] = "skipped (--cpu: compiling takes minutes on a CPU)"
        return write_row(out / "speed.jsonl", row)
    fill = {"buffer_size": 2_000, "learning_starts": 120, "latent_pretrain_steps": 0, "seed": 0}
    if on_cpu:
        keywords = {**SMALL_MODEL, **fill, "compile_updates": compile_updates}
    elif preset is None:
        keywords = {**fill, "compile_updates": compile_updates}
    else:
        keywords = preset_hyperparams(preset, {**fill, "compile_updates": compile_updates})
    model = DSSLAC("LatentPolicy", HazardPointEnv(obs_type="pixels", size=size), device=device, **keywords)
    model.learn(120)  # warm-up data only
    model.latent_pretrained = True
    updates = 3 if on_cpu else 20
    skips = cudagraph_skips()
    start = time.perf_counter()
    model.train(updates, model.batch_size)  # allocations, autotuning and any compilation
    synchronize(device)
    row["first_burst_s"] = round(time.perf_counter() - start, 1)
    with DispatchCounter(ignore_sync_of=optimizer_step_tensors(model)) as counter:
        model.train(3, model.batch_size)
    row["ops_per_update"], row["syncs_per_update"] = round(counter.ops / 3), round(counter.syncs / 3, 1)
    rates = []
    for _ in range(3):
        synchronize(device)
        start = time.perf_counter()
        model.train(updates, model.batch_size)
        synchronize(device)
        rates.append(updates / (time.perf_counter() - start))
    row["updates_per_s"] = round(float(np.median(rates)), 2)
    compiled = bool(model.updates.compiled_steps)
    if not compile_updates:
        row["compiled"] = "no (eager)"
    elif not compiled:
        row["compiled"] = f"no: ran eagerly (torch {th.__version__})"
    elif device.type == "cuda":
        skipped = cudagraph_skips() - skips
        row["compiled"] = "yes, as CUDA graphs" if skipped == 0 else f"yes, but {skipped} graphs skipped CUDA graphs"
    else:
        row["compiled"] = "yes"
    write_row(out / "speed.jsonl", row)


def cudagraph_skips() -> int:
    """Inductor's count of graphs that CUDA graph trees skipped (0 where Dynamo was never loaded)."""
    if "torch._dynamo.utils" not in sys.modules:
        return 0
    return sys.modules["torch._dynamo.utils"].counters["inductor"]["cudagraph_skips"]


def synchronize(device: th.device) -> None:
    if device.type == "cuda":
        th.cuda.synchronize(device)


def write_row(path: Path, row: dict[str, Any]) -> None:
    print(json.dumps(row), flush=True)
    with open(path, "a") as file:
        file.write(json.dumps(row) + "\n")


def print_tables(out: Path) -> None:
    """The checks' and the speed rows' tables, from the JSON rows in ``out`` (a row missing: it timed out)."""
    rows = read_rows(out / "checks.jsonl")
    print("| check | device | result | detail | s |\n|---|---|---|---|---:|")
    for name in CHECKS:
        row = rows.get(name, {"device": "", "result": "FAIL", "detail": "no result (timed out or crashed)", "seconds": ""})
        print(f"| {name} | {row['device']} | {row['result']} | {row['detail']} | {row['seconds']} |")
    speed = read_rows(out / "speed.jsonl", key="path")
    print("\n| update path | device | compile_updates | compiled | updates/s | first burst s | ops/update | syncs/update |")
    print("|---|---|---|---|---:|---:|---:|---:|")
    for name, row in speed.items():
        cells = [row.get(key, "") for key in ("updates_per_s", "first_burst_s", "ops_per_update", "syncs_per_update")]
        print(
            f"| {name} | {row['device']} | {row['compile_updates']} | {row['compiled']} | "
            + " | ".join(map(str, cells))
            + " |"
        )


def read_rows(path: Path, key: str = "check") -> dict[str, dict[str, Any]]:
    if not path.exists():
        return {}
    return {row[key]: row for row in map(json.loads, path.read_text().splitlines())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=["checks", "speed", "table"])
    parser.add_argument("row", nargs="?", help="speed: the row (SPEED_ROWS, or CPU_SPEED_ROWS with --cpu)")
    parser.add_argument("--cpu", action="store_true", help="run on the CPU, skipping what needs CUDA, at small sizes")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.cpu:
        th.set_num_threads(1)
    if args.step == "checks":
        sys.exit(1 if run_checks(args.cpu, args.out) else 0)
    elif args.step == "speed":
        speed_row(args.row, args.cpu, args.out)
    else:
        print_tables(args.out)


if __name__ == "__main__":
    main()
