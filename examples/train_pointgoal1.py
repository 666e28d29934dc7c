"""
Train DS-SLAC on Safety-Gym PointGoal1 from pixels with the CPU preset (a few minutes on a 2-core CPU), then plot the
learning curves, print the normalised score table and record a video of the trained agent.

    python examples/train_pointgoal1.py --out runs/pointgoal1

The same run as one command (the thesis's protocol with smaller numbers):

    python -m sb3_dsslac train --env SafetyGym/PointGoal1-v0 --preset cpu --sim-steps 20000 --eval-every 5000 \
        --eval-episodes 3 --threads 1 --out runs/pointgoal1

For the thesis's setting use ``--preset thesis --sim-steps 1000000`` (the defaults) on a GPU.
"""

import argparse
import importlib.util

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.plotting import report
from sb3_dsslac.app.rollouts import evaluate, format_episodes
from sb3_dsslac.app.runs import FINAL_MODEL, TrainConfig, train

parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
parser.add_argument("--out", default="runs/pointgoal1", help="run folder (must not hold a run yet)")
parser.add_argument("--sim-steps", type=int, default=20_000, help="simulator steps of training")
parser.add_argument("--seed", type=int, default=0)
args = parser.parse_args()

config = TrainConfig(
    env="SafetyGym/PointGoal1-v0",
    obs_type="pixels",
    preset="cpu",
    sim_steps=args.sim_steps,
    seed=args.seed,
    eval_every=args.sim_steps // 4,
    eval_episodes=3,
    checkpoint_every=args.sim_steps // 2,
    threads=1,  # small networks on a busy 2-core CPU: one torch thread is the fastest
    verbose=0,
)
run_dir = train(config, args.out)
print(report([run_dir], run_dir))

video = run_dir / ("agent.mp4" if importlib.util.find_spec("imageio_ffmpeg") else "agent.gif")
model = DSSLAC.load(run_dir / FINAL_MODEL)
results = evaluate(model, config.env, episodes=2, obs_type=config.obs_type, video=video, video_episodes=1)
print(format_episodes(results, model.cost_limit))
print(f"run folder: {run_dir} (video: {video.name})")
