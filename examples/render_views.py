"""Write one PNG with the first-person (64x64 observation) and third-person views of SafetyGym tasks.

Usage: ``python examples/render_views.py [--out docs/img/task_views.png] [--seed 0] [--ids SafetyGym/PointPush1-v0 ...]``.
The sheet has ``COLUMNS`` tasks per row; each task shows its observation above its ``render()`` view.
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
COLUMNS = 6
LABEL_HEIGHT = 18
DEFAULT_IDS = [f"SafetyGym/{robot}Goal{level}-v0" for robot in ("Point", "Car") for level in (0, 1, 2)] + [
    f"SafetyGym/{name}-v0" for name in ("DoggoGoal1", "PointButton1", "PointPush1", "CarButton1", "DoggoButton1", "DoggoPush1")
]


def views(env_id: str, seed: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(first-person observation, third-person render) after ``steps`` forward-ish agent steps."""
    env = gym.make(env_id, render_mode="rgb_array", render_width=TILE, render_height=TILE)
    obs, _ = env.reset(seed=seed)
    for _ in range(steps):
        obs, *_ = env.step(np.resize(np.array([0.5, 0.1], dtype=np.float32), env.action_space.shape))
    frame = env.render()
    env.close()
    return obs, frame


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("docs/img/task_views.png"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=0, help="agent steps before taking the views")
    parser.add_argument("--ids", nargs="+", default=DEFAULT_IDS, help=f"any of {safety_envs.env_ids()}")
    args = parser.parse_args()

    ids = args.ids
    rows = -(-len(ids) // COLUMNS)
    cell_height = LABEL_HEIGHT + 2 * TILE
    sheet = Image.new("RGB", (min(len(ids), COLUMNS) * TILE, rows * cell_height), "white")
    draw = ImageDraw.Draw(sheet)
    for index, env_id in enumerate(ids):
        first, third = views(env_id, args.seed, args.steps)
        x, y = (index % COLUMNS) * TILE, (index // COLUMNS) * cell_height
        draw.text((x + 4, y + 3), env_id.removeprefix("SafetyGym/"), fill="black")
        sheet.paste(Image.fromarray(first).resize((TILE, TILE), Image.NEAREST), (x, y + LABEL_HEIGHT))
        sheet.paste(Image.fromarray(third), (x, y + LABEL_HEIGHT + TILE))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(args.out, optimize=True)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.0f} KB): 64x64 observations above render() views")


if __name__ == "__main__":
    main()
