"""
Does a Point agent's reward critic know that looking for a lost goal pays? Along episodes of the agent's own stochastic
policy (filtered online as it acts), this scores with the twin critic's minimum Q(z, a) the action the agent took and
three one-step alternatives on the same belief z: turning in place to the left (the script's search of
``benchmarks/ceiling.py``), to the right, and driving straight ahead at full speed. Steps are split by whether the goal
is in the frame (``goal_view``'s rule) and, when it is not, for how many frames it has been gone.

A search action scored above the agent's own where the goal has been gone a while means the critic would move the
actor toward searching and the actor does not follow; scored below, the critic itself does not value a turn that is
followed by the agent's own behaviour (a one-step deviation cannot find a search that pays only over several steps).

    python benchmarks/tools/diagnostics/search_values.py runs/<run>                 # its model.zip (or newest checkpoint)
    python benchmarks/tools/diagnostics/search_values.py runs/<run> --episodes 10
"""

import argparse
import sys
from pathlib import Path

# The benchmarks' shared modules (ceiling.py, goal_view.py, machine.py) and reward_by_view.py
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
import torch as th
from ceiling import FULL_FORWARD
from goal_view import goal_mask, in_view
from machine import cpu_model
from reward_by_view import load_agent

from sb3_dsslac import DSSLAC
from sb3_dsslac.common.envs import make_env

# One-step alternatives, in the Point's action units (forward force, turn rate): the script's search turns left in place
ALTERNATIVES = {
    "turn left in place": (0.0, 1.0),
    "turn right in place": (0.0, -1.0),
    "straight ahead": (FULL_FORWARD["Point"], 0.0),
}
# Frames since the goal was last in view: the groups of the table (lower bound, upper bound inclusive)
GONE_FOR = {
    "goal in view": (0, 0),
    "gone 1-2 frames": (1, 2),
    "gone 3-8 frames": (3, 8),
    "gone 9+ frames, or not seen yet": (9, float("inf")),
}


def episode_values(model: DSSLAC, env, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """
    One episode of the agent's stochastic policy from ``env.reset(seed=seed)``.

    :return: (T,) frames since the goal was last in view (0: in view), and (T, 1 + len(ALTERNATIVES)) the critic's
        min Q of the agent's action, then of each alternative, on the belief the agent acted on
    """
    policy = model.policy
    policy.set_training_mode(False)
    alternatives = th.as_tensor(policy.scale_action(np.array(list(ALTERNATIVES.values()), dtype=np.float32))).float()
    frame, _ = env.reset(seed=seed)
    z2, action = policy.initial_state(1)
    start = th.ones(1, dtype=th.bool)
    gone, values = [], []
    since, done = 10**9, False
    while not done:
        since = 0 if in_view(goal_mask(frame)) else since + 1
        with th.inference_mode():
            observation, _ = policy.obs_to_tensor(frame)
            z, z2 = policy.belief_step(observation, z2, action, start, False)
            action = policy.actor(z, deterministic=False)
            candidates = th.cat([action, alternatives])
            q_values = policy.critic(z.expand(len(candidates), -1), candidates).min(dim=0).values.squeeze(-1)
        gone.append(since)
        values.append(q_values.numpy())
        frame, _, terminated, truncated, _ = env.step(policy.unscale_action(action.numpy())[0])
        start = th.zeros(1, dtype=th.bool)
        done = terminated or truncated
    return np.array(gone), np.array(values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a train run folder of a Point task (or a model.zip inside one)")
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--episode-seed", type=int, default=10_000, help="reset seed of the first episode (+1 each)")
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error("--episodes must be positive")
    th.set_num_threads(1)
    model, env_id, env_kwargs = load_agent(args.run)
    env = make_env(env_id, "pixels", env_kwargs=env_kwargs)
    if env.unwrapped.robot_spec.name != "Point":
        raise SystemExit(f"{env_id}: the alternatives are the Point's actions, not the {env.unwrapped.robot_spec.name}'s")
    try:
        episodes = [episode_values(model, env, seed) for seed in range(args.episode_seed, args.episode_seed + args.episodes)]
    finally:
        env.close()
    gone = np.concatenate([episode[0] for episode in episodes])
    values = np.concatenate([episode[1] for episode in episodes])
    print(f"{args.run}: {args.episodes} episodes ({len(gone)} steps) of its stochastic policy on {env_id}; {cpu_model()}\n")
    names = list(ALTERNATIVES)
    print(
        "| steps | share | Q of the agent's action | "
        + " | ".join(f"{name}: Q minus the agent's (share above it)" for name in names)
        + " |\n|---|---:|---:|"
        + "---:|" * len(names)
    )
    for group, (low, high) in GONE_FOR.items():
        rows = (gone >= low) & (gone <= high)
        if not rows.any():
            continue
        own = values[rows, 0]
        cells = [
            f"{(values[rows, k + 1] - own).mean():+.3f} ({(values[rows, k + 1] > own).mean():.0%})" for k in range(len(names))
        ]
        print(f"| {group} | {rows.mean():.0%} | {own.mean():.3f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
