"""
Does a Point agent's reward critic know that looking for a lost goal pays? Along episodes of the agent's own stochastic
policy (filtered online as it acts), this scores with the twin critic's minimum Q(z, a) the action the agent took and
three one-step alternatives on the same belief z: turning in place to the left (the script's search of
``benchmarks/ceiling.py``), to the right, and driving straight ahead at full speed. Steps are split by whether the goal
is in the frame (``goal_view``'s rule) and, when it is not, for how many frames it has been gone. Beside them, what the
agent does there: its mean forward force, its turn rate (mean and mean magnitude) and how often it turns the same way
as the step before (the script's search always does), for the actions it took and for its actor's means.

A search action scored above the agent's own where the goal has been gone a while means the critic would move the
actor toward searching and the actor does not follow; scored below, the critic itself does not value a turn that is
followed by the agent's own behaviour (a one-step deviation cannot find a search that pays only over several steps).

    python benchmarks/tools/diagnostics/search_values.py runs/<run>                 # its model.zip (or newest checkpoint)
    python benchmarks/tools/diagnostics/search_values.py runs/<run> --episodes 10
"""

import argparse
import sys
from pathlib import Path
from typing import NamedTuple

# The benchmarks' shared modules (ceiling.py, goal_view.py, machine.py) and reward_by_view.py
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
import torch as th
from ceiling import FULL_FORWARD
from goal_view import goal_mask, in_view
from machine import cpu_model
from reward_by_view import load_agent, require_point

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


class EpisodeValues(NamedTuple):
    """One episode of ``T`` agent steps of the agent's stochastic policy."""

    gone: np.ndarray  # (T,) frames since the goal was last in view (0: in view)
    values: np.ndarray  # (T, 1 + len(ALTERNATIVES)) min Q of the agent's action, then of each alternative, same belief
    actions: np.ndarray  # (T, 2) the actions taken, in the Point's units (forward force, turn rate)
    mean_actions: np.ndarray  # (T, 2) the actor's means (tanh of the Gaussian's mean) on the same beliefs, same units


def episode_values(model: DSSLAC, env, seed: int) -> EpisodeValues:
    """One episode of the agent's stochastic policy from ``env.reset(seed=seed)``, filtered online as it acts."""
    policy = model.policy
    policy.set_training_mode(False)
    alternatives = th.as_tensor(policy.scale_action(np.array(list(ALTERNATIVES.values()), dtype=np.float32))).float()
    frame, _ = env.reset(seed=seed)
    z2, action, memory = policy.initial_state(1)
    start = th.ones(1, dtype=th.bool)
    gone, values, actions, mean_actions = [], [], [], []
    since, done = 10**9, False
    while not done:
        since = 0 if in_view(goal_mask(frame)) else since + 1
        with th.inference_mode():
            observation, _ = policy.obs_to_tensor(frame)
            z, z2 = policy.belief_step(observation, z2, action, start, False)
            state, memory = policy.acting_input(z, action, memory, start)
            action = policy.actor(state, deterministic=False)
            candidates = th.cat([action, alternatives])
            q_values = policy.critic(state.expand(len(candidates), -1), candidates).min(dim=0).values.squeeze(-1)
            mean_action = policy.actor(state, deterministic=True)
        gone.append(since)
        values.append(q_values.numpy())
        mean_actions.append(policy.unscale_action(mean_action.numpy())[0])
        actions.append(policy.unscale_action(action.numpy())[0])
        frame, _, terminated, truncated, _ = env.step(actions[-1])
        start = th.zeros(1, dtype=th.bool)
        done = terminated or truncated
    return EpisodeValues(np.array(gone), np.array(values), np.array(actions), np.array(mean_actions))


def same_way_as_before(turns: np.ndarray) -> np.ndarray:
    """(T,) turn rates -> (T,) whether each turns the same way as the step before (False for the first step)."""
    return np.r_[False, np.sign(turns[1:]) == np.sign(turns[:-1])]


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
    require_point(env, env_id, "the alternatives")
    try:
        episodes = [episode_values(model, env, seed) for seed in range(args.episode_seed, args.episode_seed + args.episodes)]
    finally:
        env.close()
    gone, values, actions, mean_actions = (np.concatenate(parts) for parts in zip(*episodes, strict=True))
    same_turn = np.concatenate([same_way_as_before(episode.actions[:, 1]) for episode in episodes])
    same_mean_turn = np.concatenate([same_way_as_before(episode.mean_actions[:, 1]) for episode in episodes])
    has_previous = np.concatenate([np.arange(len(episode.gone)) > 0 for episode in episodes])
    groups = {group: (gone >= low) & (gone <= high) for group, (low, high) in GONE_FOR.items()}
    groups = {group: rows for group, rows in groups.items() if rows.any()}
    print(f"{args.run}: {args.episodes} episodes ({len(gone)} steps) of its stochastic policy on {env_id}; {cpu_model()}\n")
    names = list(ALTERNATIVES)
    print(
        "| steps | share | Q of the agent's action | "
        + " | ".join(f"{name}: Q minus the agent's (share above it)" for name in names)
        + " |\n|---|---:|---:|"
        + "---:|" * len(names)
    )
    for group, rows in groups.items():
        own = values[rows, 0]
        cells = [
            f"{(values[rows, k + 1] - own).mean():+.3f} ({(values[rows, k + 1] > own).mean():.0%})" for k in range(len(names))
        ]
        print(f"| {group} | {rows.mean():.0%} | {own.mean():.3f} | " + " | ".join(cells) + " |")
    print(
        "\nWhat it does there (Point units in [-1, 1]; the script's search turns at 1, always the same way):\n\n"
        "| steps | forward force, mean | turn rate: mean, mean magnitude | turns as the step before | "
        "the actor's mean turn: mean magnitude | ... turns as the step before |\n|---|---:|---:|---:|---:|---:|"
    )
    for group, rows in groups.items():
        turn, mean_turn, counted = actions[rows, 1], mean_actions[rows, 1], rows & has_previous
        print(
            f"| {group} | {actions[rows, 0].mean():+.2f} | {turn.mean():+.2f}, {np.abs(turn).mean():.2f} | "
            f"{same_turn[counted].mean():.0%} | {np.abs(mean_turn).mean():.2f} | {same_mean_turn[counted].mean():.0%} |"
        )


if __name__ == "__main__":
    main()
