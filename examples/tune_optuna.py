"""
Tune DS-SLAC with Optuna: maximise the eval reward, the cost budget as a constraint, TPE and median pruning.

    python examples/tune_optuna.py --storage runs/tune.log --n-trials 2

Start the same command in several terminals (or machines, with ``--storage postgresql://...``): the workers share
the study. Same as ``python -m sb3_dsslac tune --env SafetyGym/PointGoal1-v0 --preset cpu --timesteps 4000 ...``.
"""

import argparse

from sb3_dsslac.app.hpo import TuneSpec, summarize_study, tune

parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
parser.add_argument("--storage", default="runs/tune_pointgoal1.log", help="journal file, sqlite:/// or postgresql:// URL")
parser.add_argument("--study-name", default="pointgoal1-cpu")
parser.add_argument("--n-trials", type=int, default=2, help="trials of this worker (a few minutes each on a CPU)")
parser.add_argument("--timesteps", type=int, default=4_000, help="simulator steps per trial")
args = parser.parse_args()

spec = TuneSpec(
    env="SafetyGym/PointGoal1-v0",
    sim_steps=args.timesteps,
    preset="cpu",
    obs_type="pixels",
    n_evaluations=2,
    eval_episodes=2,
    threads=1,
)
study = tune(spec, n_trials=args.n_trials, storage=args.storage, study_name=args.study_name, n_startup_trials=2)
print(summarize_study(study))
