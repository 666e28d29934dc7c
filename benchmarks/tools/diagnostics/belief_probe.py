"""
Does a pixel agent's belief hold the goal and the hazards? Linear probes on a finished ``train`` run: windows drawn
from the run's last replay-buffer checkpoint, each filtered by the run's latent model; a ridge regression from the belief
z of the window's last frame (and, for comparison, from that frame's encoder feature) to what the frame shows: whether
the goal (green pixels) is in view (``benchmarks/goal_view.py``: its pixels cover at least 10/4096 of the frame, 2.5
pixels at 32x32), how many goal pixels there are, the goal's mean column where it is in view, and the
same for the hazards (blue). R^2 on a held-out third of the windows: 1 is a linear readout, 0 is no better than the mean.
It also scores the latent model's own cost decoder on the windows' last transitions: its mean probability of cost on
the transitions that cost and on those that did not, and the ROC AUC between them (0.5: it cannot tell them apart),
then the same on fresh episodes of the agent's stochastic policy, filtered online as it acts (``--episodes``): the
buffer's windows are what the model trained on, the fresh episodes are held out. On those episodes it splits the
agent's reward by whether the goal is in view in the frame it acts on: the share of steps with the goal in view, the
mean reward per step with and without it, and the episode reward at the in-view rate for every step (what an agent
that kept the goal in view, or remembered where it is, would earn at the same skill), and the search after each goal
reached (a new goal appears elsewhere): the agent steps until the next goal is in view.

    python benchmarks/tools/diagnostics/belief_probe.py runs/<run>  # a run of `python -m sb3_dsslac train --obs-type pixels`

The encoder feature sees only the frame; the belief adds the filter's memory but passes through the latent bottleneck.
"""

import argparse
import sys
from pathlib import Path

# The benchmarks' shared modules (machine.py) sit one folder up
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
import torch as th
from goal_view import goal_in_view, in_view, object_masks
from machine import cpu_model

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.beliefs import episode_beliefs
from sb3_dsslac.app.runs import FINAL_MODEL, find_checkpoint, load_config

GOAL_REACHED = 0.5  # a step's reward above this holds the goal bonus (1 in every Goal task; distance terms are ~0.1)


def ridge_r2(inputs: np.ndarray, targets: np.ndarray, l2: float = 1e-2) -> float:
    """
    Held-out R^2 of a ridge regression (with intercept) fitted on the first two thirds of the rows.

    :param inputs: (N, D) features
    :param targets: (N,) values
    :param l2: ridge penalty on the weights
    """
    n_fit = 2 * len(targets) // 3
    design = np.concatenate([inputs, np.ones((len(targets), 1))], axis=1).astype(np.float64)
    fit, test = design[:n_fit], design[n_fit:]
    weights = np.linalg.solve(fit.T @ fit + l2 * np.eye(design.shape[1]), fit.T @ targets[:n_fit])
    residual = ((test @ weights - targets[n_fit:]) ** 2).mean()
    return float(1.0 - residual / max(float(targets[n_fit:].var()), 1e-12))


def frame_targets(frames: np.ndarray) -> dict[str, np.ndarray]:
    """(N, H, W, 3) uint8 frames -> per object: in-view flag, pixel count and mean column (NaN where not in view)."""
    targets = {}
    columns = np.arange(frames.shape[2])
    for name, mask in object_masks(frames).items():
        count = mask.sum(axis=(1, 2))
        shown = in_view(mask)
        column = np.where(shown, (mask.sum(axis=1) * columns).sum(axis=1) / np.maximum(count, 1), np.nan)
        targets[f"{name} in view"], targets[f"{name} pixels"], targets[f"{name} column"] = shown * 1.0, count * 1.0, column
    return targets


def roc_auc(scores: np.ndarray, positive: np.ndarray) -> float | None:
    """
    Probability that a random positive row scores above a random negative one (ties count half); None without both.

    :param scores: (N,) predicted scores
    :param positive: (N,) bool labels
    """
    n_positive, n_negative = int(positive.sum()), int((~positive).sum())
    if n_positive == 0 or n_negative == 0:
        return None
    order = np.argsort(scores, kind="mergesort")
    ranks = np.empty(len(scores))
    ranks[order] = np.arange(1, len(scores) + 1)
    for value in np.unique(scores[positive]):  # average ranks over ties
        tied = scores == value
        ranks[tied] = ranks[tied].mean()
    return float((ranks[positive].sum() - n_positive * (n_positive + 1) / 2) / (n_positive * n_negative))


def cost_head_scores(probabilities: np.ndarray, costs: np.ndarray) -> dict[str, float | None]:
    """The cost decoder's mean p(cost) on costly and on free transitions, their share, and the ROC AUC between them."""
    costly = costs > 0
    return {
        "costly share": float(costly.mean()),
        "p(cost) on costly": float(probabilities[costly].mean()) if costly.any() else None,
        "p(cost) on free": float(probabilities[~costly].mean()) if (~costly).any() else None,
        "ROC AUC": roc_auc(probabilities, costly),
    }


def reward_by_goal_view(in_view: list[np.ndarray], rewards: list[np.ndarray]) -> dict[str, float | None]:
    """
    The reward of each step split by whether the goal is in view in the frame the agent acted on.

    :param in_view: per episode, (T + 1,) ``goal_in_view`` of its frames
    :param rewards: per episode, (T,) rewards of the steps from each frame to the next
    :return: the share of steps with the goal in view, the mean reward per step with the goal in view and without, the
        share of the reward earned with it in view, and the episode reward (mean episode length) at the in-view rate
    """
    acted_on = np.concatenate([episode[:-1] for episode in in_view])
    reward = np.concatenate(rewards)
    total = float(reward.sum())
    return {
        "goal in view": float(acted_on.mean()),
        "reward per step in view": float(reward[acted_on].mean()) if acted_on.any() else None,
        "reward per step out of view": float(reward[~acted_on].mean()) if (~acted_on).any() else None,
        "share of the reward in view": float(reward[acted_on].sum()) / total if total > 0 else None,
        "episode reward at the in-view rate": float(reward[acted_on].mean()) * len(reward) / len(rewards)
        if acted_on.any()
        else None,
    }


def search_lengths(in_view: list[np.ndarray], rewards: list[np.ndarray]) -> tuple[list[int], int]:
    """
    The searches after each goal reached: agent steps from the step that reached a goal (reward > ``GOAL_REACHED``) to
    the first later frame that shows the (new) goal.

    :param in_view: per episode, (T + 1,) ``goal_in_view`` of its frames
    :param rewards: per episode, (T,) rewards of the steps from each frame to the next
    :return: the lengths of the searches that found the goal, and the number that the episode's end cut off
    """
    found, cut_off = [], 0
    for episode_in_view, episode_rewards in zip(in_view, rewards, strict=True):
        for step in np.flatnonzero(episode_rewards > GOAL_REACHED):
            later = np.flatnonzero(episode_in_view[step + 1 :])
            if len(later):
                found.append(int(later[0]) + 1)
            else:
                cut_off += 1
    return found, cut_off


def format_scores(scores: dict[str, float | None]) -> str:
    """``name value`` pairs, n/a where a score is undefined."""
    return ", ".join(f"{name} {value:.3f}" if value is not None else f"{name} n/a" for name, value in scores.items())


def probe(
    model: DSSLAC, n_windows: int, chunk: int = 100
) -> tuple[dict[str, dict[str, float | None]], dict[str, float], dict[str, float | None]]:
    """
    R^2 of each target from the belief and from the encoder feature, the share of frames showing each object, and the
    cost decoder's scores on the windows' last transitions.
    """
    latent, buffer = model.policy.latent, model.replay_buffer
    beliefs, features, frames, cost_probabilities, costs = [], [], [], [], []
    with th.no_grad():
        for _ in range(n_windows // chunk):
            batch = buffer.gather(buffer.sample_indices(1, chunk)[0])
            window_features = latent.encode(model.policy.preprocess(batch.observations))
            z = latent.latents_from_features(window_features, batch.actions)
            beliefs.append(z[:, -1].cpu().numpy())
            features.append(window_features[:, -1].cpu().numpy())
            frames.append(batch.observations[:, -1].permute(0, 2, 3, 1).cpu().numpy())
            cost_probabilities.append(latent.cost_probability(z[:, -2], batch.actions[:, -1], z[:, -1]).cpu().numpy())
            costs.append(batch.costs[:, -1].cpu().numpy())
    cost_head = cost_head_scores(np.concatenate(cost_probabilities), np.concatenate(costs))
    inputs = {"belief z": np.concatenate(beliefs), "encoder feature": np.concatenate(features)}
    targets = frame_targets(np.concatenate(frames))
    scores: dict[str, dict[str, float | None]] = {}
    for target_name, values in targets.items():
        rows = ~np.isnan(values)
        scores[target_name] = {
            input_name: round(ridge_r2(x[rows], values[rows]), 3) if rows.sum() >= 30 else None
            for input_name, x in inputs.items()
        }
    shares = {name.removesuffix(" in view"): float(v.mean()) for name, v in targets.items() if name.endswith(" in view")}
    return scores, shares, cost_head


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a train run folder (model.zip and checkpoints/)")
    parser.add_argument("--windows", type=int, default=3000, help="windows drawn from the replay buffer")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=5, help="fresh episodes for the held-out cost-decoder scores")
    parser.add_argument("--episode-seed", type=int, default=10_000, help="reset seed of the first fresh episode (+1 each)")
    args = parser.parse_args()
    checkpoint = find_checkpoint(args.run)
    if checkpoint is None:
        raise SystemExit(f"{args.run} has no checkpoint with a replay buffer (checkpoints/dsslac_replay_buffer_*.pkl)")
    th.set_num_threads(1)
    th.manual_seed(args.seed)
    np.random.seed(args.seed)
    model_path = args.run / FINAL_MODEL if (args.run / FINAL_MODEL).is_file() else checkpoint.model
    model = DSSLAC.load(model_path, device="cpu")
    if len(model.policy.latent.observation_shape) != 3:
        raise SystemExit(f"{args.run} is not a pixel run: its observations are {model.policy.latent.observation_shape}")
    model.load_replay_buffer(checkpoint.replay_buffer)
    scores, shares, cost_head = probe(model, args.windows)
    where = f"buffer at {checkpoint.timesteps:,} agent steps, {args.windows} windows"
    print(f"{args.run}: {model_path.name}, {where}, {cpu_model()}")
    print(", ".join(f"{name} in view in {share:.1%} of the frames" for name, share in shares.items()))
    print("\n| held-out R^2 of | from the belief z | from the encoder feature |\n|---|---:|---:|")
    for target_name, row in scores.items():
        cells = [f"{value:.3f}" if value is not None else "n/a" for value in row.values()]
        print(f"| {target_name} | {' | '.join(cells)} |")
    print(f"\ncost decoder on the windows' last transitions: {format_scores(cost_head)}")
    if args.episodes > 0:
        config = load_config(args.run)
        seeds = range(args.episode_seed, args.episode_seed + args.episodes)
        kwargs = {"deterministic": False, "env_kwargs": config.env_kwargs}  # sampled, as the agent acts in training
        episodes = [episode_beliefs(model, config.env, seed=seed, **kwargs) for seed in seeds]
        probabilities = np.concatenate([episode.cost_probabilities for episode in episodes])
        costs = np.concatenate([episode.costs for episode in episodes])
        held_out = format_scores(cost_head_scores(probabilities, costs))
        print(f"cost decoder on {args.episodes} fresh episodes ({len(costs)} steps), online filter: {held_out}")
        rewards = [episode.rewards for episode in episodes]
        in_view = [goal_in_view(episode.frames) for episode in episodes]
        by_view = reward_by_goal_view(in_view, rewards)
        mean_reward = sum(float(reward.sum()) for reward in rewards) / len(rewards)
        print(f"reward on the same episodes (mean {mean_reward:.2f}) by the goal in view: {format_scores(by_view)}")
        found, cut_off = search_lengths(in_view, rewards)
        if found or cut_off:
            searched = (
                f"median {np.median(found):.0f}, mean {np.mean(found):.1f}, {sum(found)} steps in all" if found else "none"
            )
            print(
                f"goals reached {len(found) + cut_off}; searches for the next goal, agent steps: {searched}; {cut_off} cut off"
            )


if __name__ == "__main__":
    main()
