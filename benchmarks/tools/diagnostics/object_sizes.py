"""
How large do the goal and the hazards look in a task's first-person frames? Random-policy episodes on each task at
each frame size (the same env seeds and actions everywhere): the share of frames that show any pixel of the object,
the share that show it in view (``goal_view.IN_VIEW_SHARE`` of the frame, 10/4096: the same area at every size, 2.5
pixels at 32x32), and the median size of the object in the frames that show it, in pixels and in per mille of the
frame. No model is involved: it says how much of an image likelihood an object can weigh in, task against task.

    python benchmarks/tools/diagnostics/object_sizes.py                                   # PointGoal1 and PointGoal2, 32x32
    python benchmarks/tools/diagnostics/object_sizes.py --envs SafetyGym/CarGoal1-v0 --sizes 32 64 --episodes 20
"""

import argparse
import sys
from pathlib import Path

# The benchmarks' shared modules (machine.py) sit one folder up
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
from goal_view import in_view, object_masks
from hazard_visibility import random_episode
from machine import cpu_model

from sb3_dsslac.common.envs import make_env


def size_rows(env_id: str, size: int, episodes: int, action_repeat: int) -> list[str]:
    """Markdown rows, one per object (goal, hazard), of ``episodes`` random-policy episodes at ``size`` x ``size``."""
    env = make_env(env_id, "pixels", env_kwargs={"width": size, "height": size, "action_repeat": action_repeat})
    try:
        frames = np.concatenate([random_episode(env, seed)[0] for seed in range(episodes)])
    finally:
        env.close()
    rows = []
    for name, mask in sorted(object_masks(frames).items(), key=lambda item: item[0] != "goal"):
        pixels = mask.sum(axis=(1, 2))
        shown = pixels[pixels > 0]
        median = float(np.median(shown)) if len(shown) else 0.0
        rows.append(
            f"| {env_id.split('/')[-1]} | {size}x{size} | {name} | {len(frames):,} | {np.mean(pixels > 0):.3f} | "
            f"{np.mean(in_view(mask)):.3f} | {median:.1f} | {1000 * median / (size * size):.1f} |"
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["SafetyGym/PointGoal1-v0", "SafetyGym/PointGoal2-v0"])
    parser.add_argument("--sizes", type=int, nargs="+", default=[32], help="frame widths and heights in pixels")
    parser.add_argument("--episodes", type=int, default=10, help="random-policy episodes per task and size (seeds 0, 1, ...)")
    parser.add_argument("--action-repeat", type=int, default=4, help="simulator steps per agent step (and per frame)")
    args = parser.parse_args()
    if min(args.sizes) < 1 or args.episodes < 1 or args.action_repeat < 1:
        parser.error("--sizes, --episodes and --action-repeat must be positive")
    print(f"action repeat {args.action_repeat}, random policy, {args.episodes} episodes per task and size; {cpu_model()}\n")
    print(
        "| task | frame | object | frames | shown (any pixel) | in view (goal_view's share) | median pixels when shown "
        "| the same, per mille of the frame |\n|---|---|---|---:|---:|---:|---:|---:|"
    )
    for env_id in args.envs:
        for size in args.sizes:
            print("\n".join(size_rows(env_id, size, args.episodes, args.action_repeat)), flush=True)


if __name__ == "__main__":
    main()
