"""
Is the goal's bearing out of view missing from a pixel agent's belief, or only not linear in it? ``goal_memory.py``
scores a linear ridge probe from the belief; this runs the same episodes (its ``goal_episode``) and scores, on the same
kinds of step, halves and penalties, three readouts beside it: ridge on random ReLU features of the belief (``--features``
of them, ``relu(W x + b)`` on the belief standardised over all steps, W and b Gaussian: a readout of the information in
it by any smooth function, given the data), ridge on the actor's last hidden layer (what the policy itself computes
from the belief) and the previous action alone (the control).

    python benchmarks/tools/diagnostics/goal_memory_nonlinear.py runs/<run>    # a pixel run on a Goal task
"""

import argparse
import sys
import time
from pathlib import Path

# The benchmarks' shared modules (machine.py, goal_memory.py) sit one folder up
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
import torch as th
from goal_memory import STEP_KINDS, goal_episode, pooled_steps, probe_score
from machine import cpu_model

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.rollouts import make_model_env
from sb3_dsslac.app.runs import FINAL_MODEL, find_run_config
from sb3_dsslac.common.policies import LatentPolicy


def random_relu_features(beliefs: np.ndarray, n_features: int, seed: int) -> np.ndarray:
    """(N, Z) beliefs -> (N, n_features) ``relu(W x + b)`` of the standardised beliefs, W ~ N(0, 1/Z), b ~ N(0, 1)."""
    rng = np.random.default_rng(seed)
    standardised = (beliefs - beliefs.mean(axis=0)) / (beliefs.std(axis=0) + 1e-6)
    weights = rng.normal(0.0, 1.0 / np.sqrt(beliefs.shape[1]), (beliefs.shape[1], n_features))
    return np.maximum(standardised @ weights + rng.normal(0.0, 1.0, n_features), 0.0)


def actor_hidden(policy: LatentPolicy, beliefs: np.ndarray, previous_actions: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """The actor's last hidden layer on each belief (with the previous action and the memory where the policy takes
    them; the probe's beliefs carry the memory after z), (N, H)."""
    z_dim = policy.latent.z_dim
    with th.no_grad():
        beliefs_tensor = th.as_tensor(beliefs, dtype=th.float32)
        inputs = policy.actor_critic_input(
            beliefs_tensor[:, :z_dim],
            th.as_tensor(previous_actions, dtype=th.float32),
            th.as_tensor(starts),
            memory=beliefs_tensor[:, z_dim:],
        )
        return policy.actor.net[:-1](inputs).double().numpy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a train run folder (its model.zip) on a Goal task, from pixels")
    parser.add_argument("--episodes", type=int, default=60)
    parser.add_argument("--features", type=int, default=1024, help="random ReLU features of the belief")
    parser.add_argument("--seed", type=int, default=10_000, help="reset seed of the first episode (goal_memory.py's)")
    args = parser.parse_args()
    config = find_run_config(args.run / FINAL_MODEL)
    if config is None:
        raise SystemExit(f"{args.run}: not a finished train run (no {FINAL_MODEL} with its config)")
    th.set_num_threads(1)
    th.manual_seed(args.seed)
    model = DSSLAC.load(args.run / FINAL_MODEL, device="cpu")
    env = make_model_env(model, config.env, "pixels", env_kwargs=config.env_kwargs)
    started = time.perf_counter()
    try:
        episodes = [goal_episode(model, env, seed) for seed in range(args.seed, args.seed + args.episodes)]
    finally:
        env.close()
    since, episode_ids, bearings, beliefs, previous_actions = pooled_steps(episodes)
    starts = np.concatenate([np.arange(len(episode.bearings)) == 0 for episode in episodes])
    readouts = {
        "belief, linear": beliefs,
        f"belief, {args.features} random ReLU features": random_relu_features(beliefs, args.features, args.seed),
        "actor's last hidden layer": actor_hidden(model.policy, beliefs, previous_actions, starts),
        "previous action": previous_actions,
    }
    seconds = time.perf_counter() - started
    print(f"{args.run}: {args.episodes} episodes, {len(bearings)} agent steps, {cpu_model()}; {seconds:.0f} s")
    print()
    print("| steps | count | " + " | ".join(f"{name}: R² (median error, deg)" for name in readouts) + " |")
    print("|---|---:|" + "---:|" * len(readouts))
    for kind, (fewest, most) in STEP_KINDS.items():
        rows = (since >= fewest) & (since <= most)
        cells = []
        for inputs in readouts.values():
            score = probe_score(inputs, bearings, episode_ids, rows)
            cells.append("-" if score is None else f"{score.r2:.2f} ({score.median_error:.0f})")
        print(f"| {kind} | {int(rows.sum())} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
