"""Write one PNG with the first-person (64x64 observation) and third-person views of every SafetyGym task.

Usage: ``python examples/render_views.py [--out docs/img/task_views.png] [--seed 0]``.
"""

import argparse
import sys
from pathlib import Path

# Run from a checkout without installing.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gymnasium as gym
import numpy as np
from PIL import Image, ImageDraw

import safety_envs

TILE = 192  # pixels per view in the sheet


def views(env_id: str, seed: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(first-person observation, third-person render) after ``steps`` forward-ish agent steps."""
    env = gym.make(env_id, render_mode="rgb_array", render_width=TILE, render_height=TILE)
    obs, _ = env.reset(seed=seed)
    for _ in range(steps):
        obs, *_ = env.step(np.array([0.5, 0.1], dtype=np.float32))
    frame = env.render()
    env.close()
    return obs, frame


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("docs/img/task_views.png"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=0, help="agent steps before taking the views")
    args = parser.parse_args()

    ids = safety_envs.env_ids()
    label_height = 18
    sheet = Image.new("RGB", (len(ids) * TILE, 2 * TILE + label_height), "white")
    draw = ImageDraw.Draw(sheet)
    for column, env_id in enumerate(ids):
        first, third = views(env_id, args.seed, args.steps)
        x = column * TILE
        draw.text((x + 4, 3), env_id.removeprefix("SafetyGym/"), fill="black")
        sheet.paste(Image.fromarray(first).resize((TILE, TILE), Image.NEAREST), (x, label_height))
        sheet.paste(Image.fromarray(third), (x, label_height + TILE))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(args.out, optimize=True)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.0f} KB): top row 64x64 observations, bottom row render()")


if __name__ == "__main__":
    main()
