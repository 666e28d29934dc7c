"""
Evaluate a saved DS-SLAC model and record a video: its 64x64 first-person view (upscaled) beside a third-person view.

    python examples/evaluate_and_record.py runs/pointgoal1/model.zip --episodes 5 --video runs/pointgoal1/eval.mp4

Same as ``python -m sb3_dsslac evaluate MODEL --episodes 5 --video VIDEO``.
"""

import argparse
from pathlib import Path

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.rollouts import evaluate, format_episodes
from sb3_dsslac.app.runs import find_run_config

parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
parser.add_argument("model", help="a model saved in a run folder, e.g. runs/pointgoal1/model.zip")
parser.add_argument("--episodes", type=int, default=5)
parser.add_argument("--video", default="eval.mp4", help=".mp4 (needs imageio-ffmpeg) or .gif")
args = parser.parse_args()

model = DSSLAC.load(args.model)
run = find_run_config(Path(args.model))  # the env and observation type the model was trained on
if run is None:
    raise SystemExit(f"{args.model} is not in a run folder")
# The latent filter's state goes through predict() step by step and restarts at each episode
results = evaluate(model, run.env, episodes=args.episodes, obs_type=run.obs_type, env_kwargs=run.env_kwargs, video=args.video)
print(format_episodes(results, model.cost_limit))
