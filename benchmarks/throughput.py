"""
Training throughput of DS-SLAC at the thesis's shapes (64x64 images, sequences of 10, latent batch 32, actor-critic
batch 64 and the thesis's networks) and at the small presets ``cpu`` (PointGoal1 pixels) and ``cpu_learning``
(PointGoal1 state vectors), on SafetyGym/PointGoal1-v0. Prints one table:

- for each update path (one update = one latent-model update + one actor-critic update, Algorithm 1): updates/s, ATen
  ops per update, those of them that are not views (the kernel launches on a GPU) and host syncs per update
  (``sb3_dsslac.engine.dispatch.DispatchCounter`` over 3 updates after the warm-up, the reads of Adam's step counters left
  out);
- simulator and agent steps/s of the env alone;
- agent steps/s of real training at the thesis shapes (bursts of ``--burst`` env steps and ``--burst`` updates);
- peak host and device memory.

    python benchmarks/throughput.py                  # CPU, 12 timed updates per thesis-shape path
    python benchmarks/throughput.py --quick          # CPU: fewer updates and paths, about 4 minutes on 2 cores
    python benchmarks/throughput.py --device cuda    # GPU, adds the compile_updates paths at the thesis shapes

The small presets always time ``compile_updates=True`` beside the eager update, the thesis shapes only on CUDA or
with ``--compile``.

The first row re-creates the thesis code's update path (as the thesis's public code does it) on this
package's networks, so that both run in the same process on the same machine: each batch assembled on the host by a
Python loop over per-sequence lists of frame references and copied to the device (pageable), separate latent and
actor-critic batches (two encoder passes), NCHW convolutions, a Python loop of Polyak updates (two kernels per
tensor) and an extra logging forward of the cost critic.
"""

import argparse
import resource
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from env_throughput import single_env_rate
from machine import cpu_model
from stable_baselines3.common.utils import set_random_seed

import safety_envs  # noqa: F401  (registers the SafetyGym/* ids)
from sb3_dsslac import DSSLAC
from sb3_dsslac.common.buffers import SequenceBatch
from sb3_dsslac.engine.dispatch import DispatchCounter, optimizer_step_tensors
from sb3_dsslac.nn.critics import sample_taus
from sb3_dsslac.presets import preset_env_kwargs, preset_hyperparams

ENV_ID = "SafetyGym/PointGoal1-v0"


class ThesisStyleUpdates:
    """
    The reference code's update path around a ``DSSLAC`` model's networks (changed in place: NCHW convolutions and
    frames, and a Python loop of Polyak updates).

    :param model: a model whose replay buffer holds the frames to sample from
    """

    def __init__(self, model: DSSLAC) -> None:
        self.model = model
        model.policy.latent.to(memory_format=th.contiguous_format)
        model.updates.step.update_targets = self._python_loop_polyak  # type: ignore[method-assign]
        buffer = model.replay_buffer
        buffer.set_channels_last_frames(False)  # frames as the reference code keeps them, (C, H, W)
        length = buffer.sequence_length
        valid = buffer.valid_windows(length)
        starts, envs = valid // buffer.n_envs, valid % buffer.n_envs
        slots = (starts[:, None] + np.arange(length + 1)) % buffer.buffer_size
        # One stored sequence per window: a list of references to its frames (frames are shared, as LazyFrames are)
        self.sequences = [[buffer.observations[slot, env] for slot in row] for row, env in zip(slots, envs, strict=True)]
        # Per-sequence actions, rewards, costs and terminations live on the device
        fields = (buffer.actions, buffer.rewards, buffer.costs, buffer.terminated)
        self.fields = [th.as_tensor(field[slots[:, :-1], envs[:, None]]).to(model.device) for field in fields]

    def sample(self, batch_size: int) -> SequenceBatch:
        """A uniform batch of stored sequences, frames stacked on the host by a Python loop and copied to the device."""
        picks = np.random.randint(0, len(self.sequences), size=batch_size)
        frames = np.empty((batch_size, *np.shape(self.sequences[0])), dtype=np.uint8)
        for row, pick in enumerate(picks):
            frames[row] = np.array(self.sequences[pick])
        on_device = th.as_tensor(picks).to(self.model.device)
        return SequenceBatch(th.tensor(frames, device=self.model.device), *(field[on_device] for field in self.fields))

    def update(self) -> None:
        """One latent update on its own batch, then one actor-critic update on a second batch encoded again."""
        model = self.model
        model.updates.step.latent_update(self.sample(model.latent_batch_size))
        batch = self.sample(model.batch_size)
        with th.no_grad():
            latents = model.policy.latent.sample_latents(model.policy.preprocess(batch.observations), batch.actions)
        model.updates.step.actor_critic_update(batch, latents)
        with th.no_grad():  # the reference logs the cost critic's value with one more forward pass
            taus = sample_taus(model.batch_size, model.n_quantiles, model.device)
            model.policy.cost_critic(latents[:, -2], batch.actions[:, -1], taus).mean().item()

    def _python_loop_polyak(self) -> None:
        policy, tau = self.model.policy, self.model.tau
        for target_net, net in ((policy.critic_target, policy.critic), (policy.cost_critic_target, policy.cost_critic)):
            for target, source in zip(target_net.parameters(), net.parameters(), strict=True):
                target.data.mul_(1.0 - tau)
                target.data.add_(tau * source.data)


def synchronize(device: th.device) -> None:
    if device.type == "cuda":
        th.cuda.synchronize(device)


def filled_model(device: str, buffer_size: int, fill_steps: int, **keywords: Any) -> DSSLAC:
    """A thesis-size model whose buffer holds ``fill_steps`` agent steps of random-action PointGoal1 frames."""
    model = DSSLAC(
        "LatentPolicy",
        gym.make(ENV_ID),
        buffer_size=buffer_size,
        learning_starts=fill_steps,
        latent_pretrain_steps=0,
        device=device,
        seed=0,
        **keywords,
    )
    model.learn(fill_steps)
    model.latent_pretrained = True
    return model


def with_buffer_of(source: DSSLAC, device: str, **keywords: Any) -> DSSLAC:
    """A fresh thesis-size model sharing ``source``'s replay buffer."""
    model = DSSLAC("LatentPolicy", gym.make(ENV_ID), latent_pretrain_steps=0, device=device, seed=0, **keywords)
    model.replay_buffer = source.replay_buffer
    model.set_logger(source.logger)
    model.latent_pretrained = True
    return model


def measure_paths(
    paths: dict[str, tuple[DSSLAC, Callable[[int], Any]]], n_updates: int, rounds: int, device: th.device
) -> tuple[list[str], dict[str, float]]:
    """
    Table rows of updates/s (and the ratio to the first path), ATen ops per update (all, and not views) and host syncs
    per update of each path ``label: (model, run)``, ``run(n)`` running ``n`` updates of ``model``; and the updates/s
    by label.

    Each path first runs one untimed update (allocations, cuDNN autotuning, compilation), then 3 updates under a
    ``DispatchCounter`` (the reads of the optimizers' step counters, host tensors that wait for nothing, left out),
    which also warm up any recompilation at a second call. Then the median updates/s over ``rounds`` rounds that take
    the paths in turn, so that a machine whose speed drifts (shared hosts, boost clocks) slows every path alike.
    """
    dispatched: dict[str, tuple[float, float]] = {}
    for label, (model, run_updates) in paths.items():
        print(f"warming up and counting: {label}", file=sys.stderr, flush=True)
        run_updates(1)
        with DispatchCounter(ignore_sync_of=optimizer_step_tensors(model)) as counter:
            run_updates(3)
        dispatched[label] = counter.ops / 3, counter.kernel_ops / 3, counter.syncs / 3
    rates: dict[str, list[float]] = {label: [] for label in paths}
    per_round = max(1, n_updates // rounds)
    for _ in range(rounds):
        for label, (_, run_updates) in paths.items():
            synchronize(device)
            start = time.perf_counter()
            run_updates(per_round)
            synchronize(device)
            rates[label].append(per_round / (time.perf_counter() - start))
    medians = {label: float(np.median(values)) for label, values in rates.items()}
    first = next(iter(medians.values()))
    rows = []
    for label, rate in medians.items():
        ops, kernel_ops, syncs = dispatched[label]
        rows.append(f"| {label} | {rate:.2f} | {rate / first:.2f}x | {ops:,.0f} | {kernel_ops:,.0f} | {syncs:.1f} |")
        print(rows[-1], flush=True)  # as it comes, for runs under a timeout
    return rows, medians


def preset_paths(preset: str, device: str, fill_steps: int) -> dict[str, tuple[DSSLAC, Callable[[int], Any]]]:
    """
    Eager and ``compile_updates=True`` models of a small preset (``cpu`` on PointGoal1 pixels, ``cpu_learning`` on its
    state vectors, ``cpu_pixels32_bounded`` on 32x32 pixels at action repeat 4: the preset's env keywords), sharing one
    buffer of ``fill_steps`` random-action agent steps. The first update runs the preset's (here empty) latent
    pre-training, which fixes the standardisation of state vectors.
    """
    obs_type = "state" if preset == "cpu_learning" else "pixels"
    paths: dict[str, tuple[DSSLAC, Callable[[int], Any]]] = {}
    source: DSSLAC | None = None
    for label, keywords in (("eager", {"compile_updates": False}), ("compile_updates=True", {"compile_updates": True})):
        set_random_seed(0)
        hyperparams = preset_hyperparams(preset, {"learning_starts": fill_steps, "latent_pretrain_steps": 0, **keywords})
        env = gym.make(ENV_ID, obs_type=obs_type, **preset_env_kwargs(preset))
        model = DSSLAC("LatentPolicy", env, device=device, seed=0, **hyperparams)
        if source is None:
            model.learn(fill_steps)
            source = model
        else:
            model.replay_buffer = source.replay_buffer
            model.set_logger(source.logger)
        paths[f"{preset} preset ({obs_type}), {label}"] = (model, lambda n, model=model: model.train(n, model.batch_size))
    return paths


def training_rate(base: DSSLAC, device: str, burst: int, **keywords: Any) -> float:
    """Agent steps/s of ``learn`` on ``base``'s buffer: one burst of ``burst`` env steps then ``burst`` updates (after
    one untimed burst when compiling)."""
    model = with_buffer_of(base, device, learning_starts=0, train_freq=burst, gradient_steps=burst, **keywords)
    if keywords.get("compile_updates"):
        model.learn(burst, reset_num_timesteps=False)
    synchronize(model.device)
    start = time.perf_counter()
    model.learn(burst, reset_num_timesteps=False)
    synchronize(model.device)
    return burst / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--quick", action="store_true", help="few timed updates, one round and bursts of 10")
    parser.add_argument("--updates", type=int, help="timed updates per thesis-shape path (default 12; quick: 1, 20 on CUDA)")
    parser.add_argument("--preset-updates", type=int, help="timed updates per small-preset path (default 40; quick: 10)")
    parser.add_argument("--rounds", type=int, help="rounds taking the paths in turn, median reported (default 3; quick: 1)")
    parser.add_argument("--burst", type=int, help="env steps and updates per training burst (default 100; quick: 10)")
    parser.add_argument("--compile", action="store_true", help="time compile_updates at the thesis shapes on the CPU too")
    parser.add_argument(
        "--presets",
        nargs="*",
        default=["cpu", "cpu_learning"],
        choices=["cpu", "cpu_learning", "cpu_pixels32_bounded"],
        help="small presets timed",
    )
    parser.add_argument(
        "--thesis",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the thesis shapes' paths, the env alone and the real training (--no-thesis: the small presets only)",
    )
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--buffer-size", type=int, default=200_000, help="replay buffer frames (the thesis's 200k)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results"), help="folder of the table")
    args = parser.parse_args()
    device = th.device(args.device)
    quick_updates = 20 if device.type == "cuda" else 1
    args.updates = args.updates or (quick_updates if args.quick else 12)
    args.preset_updates = args.preset_updates or (10 if args.quick else 40)
    args.rounds = args.rounds or (1 if args.quick else 3)
    args.burst = args.burst or (10 if args.quick else 100)
    if args.threads is not None:
        th.set_num_threads(args.threads)
    fill_steps = 1_000
    set_random_seed(0)

    thesis_rows: list[str] = []
    rows: list[tuple[str, str]] = []
    if args.thesis:
        base = filled_model(args.device, args.buffer_size, fill_steps)
        keywords_of: dict[str, dict[str, Any]] = {"this package, eager (device gather, channels-last, fused Polyak)": {}}
        if not (args.quick and device.type == "cpu"):  # a thesis-shape update takes seconds on a CPU
            keywords_of["+ share_latent_batch"] = {"share_latent_batch": True}
            keywords_of["+ bf16='auto' (bfloat16 only where native)"] = {"bf16": "auto"}
        keywords_of["+ share_latent_batch + bf16='auto'"] = {"share_latent_batch": True, "bf16": "auto"}
        if args.compile or device.type == "cuda":
            keywords_of["compile_updates=True"] = {"compile_updates": True}
            if not args.quick:
                keywords_of["+ share_latent_batch + bf16='auto' + compile_updates"] = {
                    "share_latent_batch": True,
                    "bf16": "auto",
                    "compile_updates": True,
                }

        thesis = ThesisStyleUpdates(with_buffer_of(base, args.device))
        paths: dict[str, tuple[DSSLAC, Callable[[int], Any]]] = {
            "thesis-style path (re-created reference code)": (
                thesis.model,
                lambda n, thesis=thesis: [thesis.update() for _ in range(n)],
            )
        }
        for label, keywords in keywords_of.items():
            set_random_seed(0)
            model = with_buffer_of(base, args.device, **keywords)
            paths[label] = (model, lambda n, model=model: model.train(n, model.batch_size))
        thesis_rows, rates = measure_paths(paths, args.updates, args.rounds, device)
        best = keywords_of[max(keywords_of, key=rates.__getitem__)]
        del paths, thesis  # free the models before the next ones
        env_rate, _ = single_env_rate(ENV_ID, "pixels", 500 if args.quick else 2_000)
        rows.append(("env alone, PointGoal1 pixels: simulator steps/s", f"{2 * env_rate:,.0f}"))
        rows.append(("env alone, PointGoal1 pixels: agent steps/s", f"{env_rate:,.0f}"))
        fastest = ", ".join(f"{key}={value}" for key, value in best.items()) or "defaults"
        train_rate = training_rate(base, args.device, args.burst, **best)
        del base
        rows.append((f"real training at the thesis shapes, agent steps/s (1 update per step, {fastest})", f"{train_rate:.2f}"))
        hours = 500_000 / train_rate / 3600
        rows.append(("=> hours per 1M simulator steps (500k agent steps and updates)", f"{hours:.1f}"))
        rows.append(("peak host memory (RSS), GiB", f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f}"))
        if device.type == "cuda":
            rows.append(("peak device memory, GiB", f"{th.cuda.max_memory_allocated(device) / 2**30:.2f}"))

    preset_rows = []
    for preset in args.presets:
        paths = preset_paths(preset, args.device, fill_steps)
        preset_rows += measure_paths(paths, args.preset_updates, args.rounds, device)[0]
        del paths

    name = th.cuda.get_device_name(device) if device.type == "cuda" else f"{cpu_model()}, {th.get_num_threads()} torch threads"
    header = [
        "| update path | updates/s | vs first row | ops/update | of them not views | syncs/update |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    thesis_setup = (
        f" Thesis shapes (64x64, L=10, batches 32 + 64, buffer of {args.buffer_size:,} frames): {args.updates} timed updates "
        f"per path in {args.rounds} rounds (median)."
    )
    lines = [
        f"DS-SLAC throughput on {name}, torch {th.__version__}.{thesis_setup if args.thesis else ''} Small presets: "
        f"{args.preset_updates} timed updates per path. Ops and host syncs: a DispatchCounter over 3 updates after the "
        "warm-up, divided by 3, the reads of Adam's step counters left out.",
        "",
        *([*header, *thesis_rows, ""] if thesis_rows else []),
        *([*header, *preset_rows, ""] if preset_rows else []),
        *(["| measure | value |", "|---|---:|", *(f"| {label} | {value} |" for label, value in rows)] if rows else []),
    ]
    table = "\n".join(lines)
    print("\n" + table)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"throughput_{args.device}{'_quick' if args.quick else ''}.md"
    path.write_text(table + "\n")
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
