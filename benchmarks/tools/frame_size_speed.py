"""
Updates/s of the ``cpu`` preset's networks on PointGoal1 frames of 64x64, 84x84 and 128x128 pixels, eager and with
``compile_updates=True``, on one torch thread (``docs/performance.md``, "Frames of other sizes"). One update = one
latent-model update + one actor-critic update on the preset's batches (8 sequences of 5 frames for the latent model,
16 for the actor-critic).

    python benchmarks/tools/frame_size_speed.py                      # 64, 84 and 128, eager and compiled
    python benchmarks/tools/frame_size_speed.py --sizes 64 84 --no-compile

Each size's buffer holds ``--fill`` random-action agent steps of its own frames; the eager and the compiled model train
on the same buffer. Each path first runs 3 untimed updates (allocations, compilation), then the median updates/s of
``--rounds`` rounds of ``--updates`` updates, the paths taken in turn.
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import gymnasium as gym
import torch as th

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine import cpu_model

import safety_envs  # noqa: F401  (registers the SafetyGym/* ids)
from sb3_dsslac import DSSLAC
from sb3_dsslac.nn.image_nets import image_map_sizes
from sb3_dsslac.presets import preset_hyperparams

ENV_ID = "SafetyGym/PointGoal1-v0"


def models_of_size(size: int, fill: int, compiled: bool) -> dict[str, DSSLAC]:
    """The eager (and compiled) ``cpu`` preset models on ``size`` x ``size`` frames, sharing one filled buffer."""
    models: dict[str, DSSLAC] = {}
    paths = [("eager", False), ("compiled", True)] if compiled else [("eager", False)]
    for label, compile_updates in paths:
        hyperparams = preset_hyperparams("cpu", {"learning_starts": fill, "latent_pretrain_steps": 0})
        env = gym.make(ENV_ID, obs_type="pixels", width=size, height=size)
        model = DSSLAC("LatentPolicy", env, device="cpu", seed=0, compile_updates=compile_updates, **hyperparams)
        if not models:
            model.learn(fill)
        else:
            source = next(iter(models.values()))
            model.replay_buffer = source.replay_buffer
            model.set_logger(source.logger)
        model.latent_pretrained = True
        models[f"{size}x{size}, {label}"] = model
    return models


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 84, 128], help="frame sides in pixels")
    parser.add_argument("--fill", type=int, default=300, help="random-action agent steps in each size's buffer")
    parser.add_argument("--updates", type=int, default=20, help="timed updates per path and round")
    parser.add_argument("--rounds", type=int, default=3, help="rounds taking the paths in turn, median reported")
    parser.add_argument("--compile", action=argparse.BooleanOptionalAction, default=True, help="time compile_updates too")
    args = parser.parse_args()
    th.set_num_threads(1)

    models: dict[str, DSSLAC] = {}
    for size in args.sizes:
        print(f"filling the buffer of {size}x{size} frames", file=sys.stderr, flush=True)
        models.update(models_of_size(size, args.fill, args.compile))
    for label, model in models.items():
        print(f"warming up: {label}", file=sys.stderr, flush=True)
        model.train(3, model.batch_size)
    rates: dict[str, list[float]] = {label: [] for label in models}
    for _ in range(args.rounds):
        for label, model in models.items():
            start = time.perf_counter()
            model.train(args.updates, model.batch_size)
            rates[label].append(args.updates / (time.perf_counter() - start))

    print(f"{cpu_model()}, torch {th.__version__}, 1 torch thread; `cpu` preset networks, widths (32, 64, 128, 256)")
    first = f"{args.sizes[0]}x{args.sizes[0]}"
    print(f"| frames | path | encoder maps after each stride-2 stage | latent-model parameters | updates/s | vs {first} |")
    print("|---|---|---|---:|---:|---:|")
    for label, model in models.items():
        size, path = label.split(", ")
        side = int(size.split("x")[0])
        maps = " > ".join(f"{h}x{w}" for h, w in image_map_sizes(side, side)[1:])
        n_parameters = sum(parameter.numel() for parameter in model.policy.latent.parameters())
        rate = statistics.median(rates[label])
        base = statistics.median(rates[f"{first}, {path}"])
        print(f"| {size} | {path} | {maps} | {n_parameters:,} | {rate:.2f} | {rate / base:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
