"""
Could a pixel agent foresee its hazard costs? For each image size, episodes of a random policy on the agent's own env
(``make_env``, pixels, action repeat included), the same env seeds and actions at every size, so the same trajectories;
at each agent step that costs through a hazard, whether a hazard was in view (hazard-blue pixels covering at least
``goal_view.IN_VIEW_SHARE`` of the frame, 10/4096: 2.5 pixels at 32x32) in that step's frame or any of the W - 1 frames
before it, for each window length W: anywhere in the frame, and in its bottom quarter (the floor just ahead of the
robot). The same shares on the steps that cost nothing show how often such a sighting is harmless. No model is
involved: it bounds what any belief built from the last W frames could know about the hazard the robot stands on, as a
detector "a hazard was seen" with a hit rate (costly steps) and a false-alarm rate (free steps).

    python benchmarks/tools/diagnostics/hazard_visibility.py  # PointGoal1, 32x32 and 64x64, 20 episodes
    python benchmarks/tools/diagnostics/hazard_visibility.py --sizes 32 48 64 --windows 1 4 10 20 --episodes 40
    # 4 frames then span 16 simulator steps
    python benchmarks/tools/diagnostics/hazard_visibility.py --sizes 32 --action-repeat 4

The latent filter's belief holds about the last 4 frames (``filter_memory.py``), the thesis's training window is 8+1.
"""

import argparse
import sys
from pathlib import Path

# The benchmarks' shared modules (machine.py) sit one folder up
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import gymnasium as gym
import numpy as np
from goal_view import hazard_mask, in_view
from machine import cpu_model

from sb3_dsslac.common.envs import make_env

REGIONS = {"anywhere": 1.0, "bottom quarter": 0.25}  # share of the frame's rows, counted from the bottom


def hazard_in_view(frames: np.ndarray, rows: float = 1.0) -> np.ndarray:
    """
    (T, H, W, 3) uint8 frames -> (T,) True where the hazard-blue pixels of the bottom ``rows`` share of the rows cover at
    least ``goal_view.IN_VIEW_SHARE`` of the whole frame.
    """
    mask = hazard_mask(frames)
    height = mask.shape[1]
    mask[:, : height - round(height * rows)] = False
    return in_view(mask)


def seen_within(in_view: np.ndarray, window: int) -> np.ndarray:
    """(T,) flags -> (T,) True where a flag is set at that step or in any of the ``window - 1`` steps before it."""
    counts = np.concatenate([[0], np.cumsum(in_view)])
    starts = np.maximum(np.arange(len(in_view)) - window + 1, 0)
    return counts[1:] - counts[starts] > 0


def random_episode(env: gym.Env, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    One episode of uniform random actions from ``env.reset(seed=seed)`` (actions drawn from ``seed``, so equal at every
    image size).

    :return: (T, H, W, 3) frames seen before each action, (T,) hazard costs and (T,) total costs of the actions
    """
    rng = np.random.default_rng(seed)
    frames, hazard_costs, costs = [], [], []
    observation, _ = env.reset(seed=seed)
    done = False
    while not done:
        frames.append(observation)
        action = rng.uniform(env.action_space.low, env.action_space.high).astype(env.action_space.dtype)
        observation, _, terminated, truncated, info = env.step(action)
        hazard_costs.append(float(info.get("cost_hazards", 0.0)))
        costs.append(float(info["cost"]))
        done = terminated or truncated
    return np.stack(frames), np.array(hazard_costs), np.array(costs)


def visibility_table(env_id: str, sizes: list[int], windows: list[int], episodes: int, action_repeat: int) -> str:
    """
    Markdown: per size, window and region of the frame, the shares of hazard-costly and of cost-free agent steps with a
    hazard seen in the window (``action_repeat`` simulator steps per agent step and per frame).
    """
    header = " | ".join(f"{kind} steps, seen {region}" for region in REGIONS for kind in ("hazard-costly", "cost-free"))
    lines = [f"| frame size | window (frames) | {header} |", "|---|---:|" + "---:|" * 2 * len(REGIONS)]
    for size in sizes:
        seen: dict[tuple[int, str], tuple[list, list]] = {(w, region): ([], []) for w in windows for region in REGIONS}
        n_costly = n_steps = 0
        env = make_env(env_id, "pixels", env_kwargs={"width": size, "height": size, "action_repeat": action_repeat})
        try:
            for seed in range(episodes):
                frames, hazard_costs, costs = random_episode(env, seed)
                costly, free = hazard_costs > 0, costs == 0
                n_costly, n_steps = n_costly + int(costly.sum()), n_steps + len(costs)
                for region, rows in REGIONS.items():
                    in_view = hazard_in_view(frames, rows)
                    for window in windows:
                        flags = seen_within(in_view, window)
                        seen[window, region][0].append(flags[costly])
                        seen[window, region][1].append(flags[free])
        finally:
            env.close()
        for window in windows:
            cells = [np.concatenate(parts).mean() for region in REGIONS for parts in seen[window, region]]
            lines.append(f"| {size}x{size} | {window} | " + " | ".join(f"{cell:.2f}" for cell in cells) + " |")
        lines.append(f"| {size}x{size}: {n_costly:,} hazard-costly steps of {n_steps:,} |" + " |" * (1 + 2 * len(REGIONS)))
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="SafetyGym/PointGoal1-v0")
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64], help="frame widths and heights in pixels")
    parser.add_argument("--windows", type=int, nargs="+", default=[1, 4, 10, 20], help="frames looked back, this one included")
    parser.add_argument("--episodes", type=int, default=20, help="random-policy episodes per size (env seeds 0, 1, ...)")
    parser.add_argument("--action-repeat", type=int, default=2, help="simulator steps per agent step (and per frame)")
    args = parser.parse_args()
    if min(args.windows) < 1 or min(args.sizes) < 1 or args.episodes < 1 or args.action_repeat < 1:
        parser.error("--sizes, --windows, --episodes and --action-repeat must be positive")
    print(f"{args.env}, action repeat {args.action_repeat}, random policy, {args.episodes} episodes per size; {cpu_model()}\n")
    print(visibility_table(args.env, args.sizes, args.windows, args.episodes, args.action_repeat))


if __name__ == "__main__":
    main()
