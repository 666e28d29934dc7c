"""
Training throughput of DS-SLAC at the thesis's shapes: 64x64 images, sequences of 10, latent batch 32, actor-critic
batch 64 and the thesis's networks, on SafetyGym/PointGoal1-v0 frames. Prints one table:

- updates/s of each update path (one update = one latent-model update + one actor-critic update, Algorithm 1);
- simulator and agent steps/s of the env alone;
- agent steps/s of real training (bursts of ``--burst`` env steps and ``--burst`` updates);
- peak host and device memory.

    python benchmarks/throughput.py                  # CPU, 10 timed updates per path
    python benchmarks/throughput.py --quick          # CPU, under 2 minutes
    python benchmarks/throughput.py --device cuda    # GPU, adds the compiled path

The first row re-creates the thesis code's update path (``../shared/REFERENCE_IMPLS.md`` sections 6 and 9) on this
package's networks, so that both run in the same process on the same machine: each batch assembled on the host by a
Python loop over per-sequence lists of frame references and copied to the device (pageable), separate latent and
actor-critic batches (two encoder passes), NCHW convolutions, a Python loop of Polyak updates (two kernels per
tensor) and an extra logging forward of the cost critic.
"""

import argparse
import resource
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from env_throughput import single_env_rate
from stable_baselines3.common.utils import set_random_seed

import safety_envs  # noqa: F401  (registers the SafetyGym/* ids)
from sb3_dsslac import DSSLAC
from sb3_dsslac.buffers import SequenceBatch
from sb3_dsslac.critics import sample_taus

ENV_ID = "SafetyGym/PointGoal1-v0"


class ThesisStyleUpdates:
    """
    The reference code's update path around a ``DSSLAC`` model's networks (changed in place: NCHW convolutions and a
    Python loop of Polyak updates).

    :param model: a model whose replay buffer holds the frames to sample from
    """

    def __init__(self, model: DSSLAC) -> None:
        self.model = model
        model.policy.latent.to(memory_format=th.contiguous_format)
        model._update_targets = self._python_loop_polyak  # type: ignore[method-assign]
        buffer = model.replay_buffer
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
        model._latent_update(self.sample(model.latent_batch_size))
        batch = self.sample(model.batch_size)
        with th.no_grad():
            latents = model.policy.latent.sample_latents(model.policy.preprocess(batch.observations), batch.actions)
        model._actor_critic_update(batch, latents)
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


def updates_per_second(
    runners: dict[str, Callable[[int], Any]], n_updates: int, rounds: int, device: th.device
) -> dict[str, float]:
    """
    Median updates/s of each ``runner(n)`` (running ``n`` updates) over ``rounds`` rounds that take the runners in
    turn, so that a machine whose speed drifts (shared hosts, boost clocks) slows every path alike. Each runner first
    runs two untimed updates (allocations, cuDNN autotuning, compilation).
    """
    for run_updates in runners.values():
        run_updates(2)
    rates: dict[str, list[float]] = {name: [] for name in runners}
    per_round = max(1, n_updates // rounds)
    for _ in range(rounds):
        for name, run_updates in runners.items():
            synchronize(device)
            start = time.perf_counter()
            run_updates(per_round)
            synchronize(device)
            rates[name].append(per_round / (time.perf_counter() - start))
    return {name: float(np.median(values)) for name, values in rates.items()}


def training_rate(device: str, buffer_size: int, fill_steps: int, burst: int, **keywords: Any) -> float:
    """Agent steps/s of ``learn`` after the warm-up: one burst of ``burst`` env steps then ``burst`` updates (after
    one untimed burst when compiling)."""
    model = filled_model(device, buffer_size, fill_steps, train_freq=burst, gradient_steps=burst, **keywords)
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
    parser.add_argument("--quick", action="store_true", help="2 timed updates per path and bursts of 10: under 2 min")
    parser.add_argument("--updates", type=int, default=12, help="timed updates per path (60 is better on a GPU)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds taking the paths in turn (median reported)")
    parser.add_argument("--burst", type=int, default=100, help="env steps and updates per training burst")
    parser.add_argument("--compile", action="store_true", help="time compile_updates on the CPU too (always on CUDA)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    parser.add_argument("--buffer-size", type=int, default=200_000, help="replay buffer frames (the thesis's 200k)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    args = parser.parse_args()
    if args.quick:
        args.updates, args.rounds, args.burst = 2, 1, 10
    if args.threads is not None:
        th.set_num_threads(args.threads)
    fill_steps = 1_000
    device = th.device(args.device)
    set_random_seed(0)

    base = filled_model(args.device, args.buffer_size, fill_steps)
    paths: list[tuple[str, dict[str, Any]]] = [
        ("this package, eager (device gather, channels-last, fused Polyak)", {}),
        ("+ share_latent_batch", {"share_latent_batch": True}),
        ("+ bf16", {"bf16": True}),
        ("+ share_latent_batch + bf16", {"share_latent_batch": True, "bf16": True}),
    ]
    if args.compile or device.type == "cuda":
        compiled = {"share_latent_batch": True, "bf16": True, "compile_updates": True}
        paths.append(("+ share_latent_batch + bf16 + compile_updates", compiled))

    thesis = ThesisStyleUpdates(with_buffer_of(base, args.device))
    thesis_label = "thesis-style path (re-created reference code)"
    runners: dict[str, Callable[[int], Any]] = {thesis_label: lambda n, thesis=thesis: [thesis.update() for _ in range(n)]}
    for label, keywords in paths:
        set_random_seed(0)
        model = with_buffer_of(base, args.device, **keywords)
        runners[label] = lambda n, model=model: model.train(n, model.batch_size)
    rates = updates_per_second(runners, args.updates, args.rounds, device)
    thesis_rate = rates[thesis_label]
    rows = [(f"updates/s, {label}", f"{rate:.2f}", f"{rate / thesis_rate:.2f}x") for label, rate in rates.items()]
    best_label = max(rates, key=rates.__getitem__)
    best = dict(paths).get(best_label, {})
    runners.clear()  # free the models before the training run

    env_rate, _ = single_env_rate(ENV_ID, "pixels", 500 if args.quick else 2_000)
    rows.append(("env alone, PointGoal1 pixels: simulator steps/s", f"{2 * env_rate:,.0f}", ""))
    rows.append(("env alone, PointGoal1 pixels: agent steps/s", f"{env_rate:,.0f}", ""))
    fastest = ", ".join(f"{key}={value}" for key, value in best.items()) or "defaults"
    train_rate = training_rate(args.device, args.buffer_size, fill_steps, args.burst, **best)
    rows.append((f"real training, agent steps/s (1 update per step, {fastest})", f"{train_rate:.2f}", ""))
    hours = 500_000 / train_rate / 3600
    rows.append(("=> hours per 1M simulator steps (500k agent steps and updates)", f"{hours:.1f}", ""))
    rows.append(("peak host memory (RSS), GiB", f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f}", ""))
    if device.type == "cuda":
        rows.append(("peak device memory, GiB", f"{th.cuda.max_memory_allocated(device) / 2**30:.2f}", ""))

    name = th.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {th.get_num_threads()} torch threads"
    lines = [
        f"DS-SLAC throughput on {name}: thesis shapes (64x64, L=10, batches 32 + 64), {args.updates} timed updates "
        f"per path in {args.rounds} rounds (median), buffer of {args.buffer_size:,} frames, torch {th.__version__}",
        "",
        "| measure | value | vs thesis-style |",
        "|---|---:|---:|",
        *(f"| {label} | {value} | {ratio} |" for label, value, ratio in rows),
    ]
    table = "\n".join(lines)
    print("\n" + table)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"throughput_{args.device}{'_quick' if args.quick else ''}.md"
    path.write_text(table + "\n")
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
