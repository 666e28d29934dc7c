"""
Updates/s of the same configuration in two or more source trees of sb3_dsslac, in one run: each tree's timing runs in
its own subprocess (``PYTHONPATH=<tree>``), the trees take turns over rounds, and the median is reported, so a change
is judged against the code before it on the same machine at the same time (this machine's speed drifts by +-20%).

    git worktree add /tmp/before <commit>
    python benchmarks/tools/compare_trees.py /tmp/before . --preset cpu_learning --obs-type state
    python benchmarks/tools/compare_trees.py /tmp/before . --preset thesis --obs-type pixels --updates 4
    python benchmarks/tools/compare_trees.py . --preset cpu_learning --obs-type state --keywords compile_updates=True

Only the public API is used (``DSSLAC``, ``preset_hyperparams``, ``learn``, ``train``), so any tree since the presets
works. ``--keywords`` go to every tree; ``--tree-keywords i:key=value`` to tree ``i`` only (a tree may be listed twice
with different keywords).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

# Run from a checkout: the benchmarks' shared modules (machine.py)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine import cpu_model

from sb3_dsslac.app.runs import parse_hyperparams

# Runs inside each subprocess: fill the buffer with random steps, warm up (and compile), then time ``train`` bursts.
_TIMING_CODE = """
import json, sys, time
import torch as th
import gymnasium as gym
args = json.loads(sys.argv[1])
th.set_num_threads(args["threads"])
import safety_envs  # noqa: F401
from sb3_dsslac import DSSLAC
from sb3_dsslac.presets import preset_env_kwargs, preset_hyperparams
env = gym.make(args["env"], obs_type=args["obs_type"], **preset_env_kwargs(args["preset"], args["env_kwargs"]))
hyperparams = preset_hyperparams(args["preset"], args["keywords"])
fill = args["fill"]
# One rollout of fill + 1 agent steps (a rollout runs its train_freq steps whatever learn's total), then one update
hyperparams.update(learning_starts=fill, latent_pretrain_steps=0, train_freq=fill + 1, gradient_steps=1)
hyperparams.update(buffer_size=max(fill, 2000))
model = DSSLAC("LatentPolicy", env, seed=0, verbose=0, **hyperparams)
model.learn(args["fill"] + 1)
model.train(gradient_steps=args["warmup"], batch_size=model.batch_size)
start = time.perf_counter()
model.train(gradient_steps=args["updates"], batch_size=model.batch_size)
print(json.dumps({"updates_per_s": args["updates"] / (time.perf_counter() - start)}))
"""


def time_tree(tree: Path, settings: dict, timeout: float) -> float:
    """Updates/s of one timing run with ``sb3_dsslac`` imported from ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree.resolve()), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    result = subprocess.run(
        [sys.executable, "-c", _TIMING_CODE, json.dumps(settings)],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=tree,
        check=False,
    )
    if result.returncode != 0:
        raise SystemExit(f"timing in {tree} failed:\n{result.stderr[-3000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])["updates_per_s"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("trees", nargs="+", type=Path, help="source trees (folders holding sb3_dsslac/)")
    parser.add_argument("--env", default="SafetyGym/PointGoal1-v0")
    parser.add_argument("--obs-type", default="state", choices=["state", "pixels"])
    parser.add_argument("--preset", default="cpu_learning")
    parser.add_argument(
        "--env-kwargs", nargs="*", default=[], metavar="KEY=VALUE", help="env keywords over the preset's (width=64 height=64)"
    )
    parser.add_argument("--keywords", nargs="*", default=[], metavar="KEY=VALUE", help="DSSLAC keywords for every tree")
    parser.add_argument("--tree-keywords", nargs="*", default=[], metavar="I:KEY=VALUE", help="keywords for tree I only")
    parser.add_argument("--updates", type=int, default=100, help="timed updates per round")
    parser.add_argument("--warmup", type=int, default=10, help="updates before the timing (compilation happens here)")
    parser.add_argument("--fill", type=int, default=1000, help="random agent steps in the buffer")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds per timing run")
    args = parser.parse_args()

    common = parse_hyperparams(args.keywords)
    per_tree: list[dict] = [dict(common) for _ in args.trees]
    for item in args.tree_keywords:
        index, _, pair = item.partition(":")
        per_tree[int(index)].update(parse_hyperparams([pair]))
    rates: list[list[float]] = [[] for _ in args.trees]
    for round_index in range(args.rounds):
        for index, tree in enumerate(args.trees):
            settings = {
                "env": args.env,
                "obs_type": args.obs_type,
                "preset": args.preset,
                "keywords": per_tree[index],
                "env_kwargs": parse_hyperparams(args.env_kwargs),
                "updates": args.updates,
                "warmup": args.warmup,
                "fill": args.fill,
                "threads": args.threads,
            }
            rates[index].append(time_tree(tree, settings, args.timeout))
            print(f"round {round_index + 1}, tree {index} ({tree}): {rates[index][-1]:.2f} updates/s", flush=True)

    cpu = cpu_model()
    print(
        f"\n{args.preset} preset, {args.obs_type} observations of {args.env} {args.env_kwargs or ''}; {cpu}, "
        f"{args.threads} torch thread(s); "
        f"median of {args.rounds} rounds of {args.updates} updates, trees in turn\n"
    )
    print("| tree | keywords | updates/s | vs tree 0 |\n|---|---|---:|---:|")
    base = statistics.median(rates[0])
    for index, tree in enumerate(args.trees):
        median = statistics.median(rates[index])
        print(f"| {tree} | {per_tree[index] or '-'} | {median:.2f} | {median / base:.2f}x |")


if __name__ == "__main__":
    main()
