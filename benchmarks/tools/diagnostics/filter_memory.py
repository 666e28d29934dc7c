"""
How much does a pixel agent's belief remember? The actor and the critics are trained on beliefs filtered over a
replay window of ``sequence_length`` frames, but act on the online filter's belief, carried from the episode's first
frame, as in the reference code. Along episodes of the agent's own stochastic policy, this prints how far the
episode-long filter's belief is from the belief filtered over only the last k frames, as a share of the belief's
variance (filter means on both sides, so that sampling noise does not count). Near 0 already at a small k means that
the belief is a function of the last k frames: what left the view earlier (the goal, once the robot turns away) is
forgotten, and the window/online mismatch does not matter.

    python benchmarks/tools/diagnostics/filter_memory.py runs/<run>  # a run of `python -m sb3_dsslac train --obs-type pixels`
    python benchmarks/tools/diagnostics/filter_memory.py model.zip --episodes 10
"""

import argparse
import sys
from pathlib import Path
from typing import Any, NamedTuple

# The benchmarks' shared modules (machine.py) sit one folder up
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch as th
from machine import cpu_model

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.runs import FINAL_MODEL, find_run_config
from sb3_dsslac.common.envs import make_env


class FilteredEpisode(NamedTuple):
    """One episode of ``T`` frames as the agent filtered it."""

    features: th.Tensor  # (T, F) encoder features
    actions: th.Tensor  # (T - 1, A) actions between the frames, scaled to [-1, 1]
    beliefs: th.Tensor  # (T, Z) the online filter's means along the episode (same frames and actions)


def filtered_episode(model: DSSLAC, env_id: str, seed: int, env_kwargs: dict[str, Any] | None = None) -> FilteredEpisode:
    """
    Run one episode with the agent's stochastic policy (sampled filter, as it acts while training).

    :param env_kwargs: keywords of the env (a run's own, e.g. its image size)
    """
    policy, latent = model.policy, model.policy.latent
    env = make_env(env_id, "pixels", env_kwargs=env_kwargs)
    policy.set_training_mode(False)
    features, actions, beliefs = [], [], []
    sampled_z2, action, memory = policy.initial_state(1)
    mean_z2 = sampled_z2.clone()
    start = th.ones(1, dtype=th.bool)
    done = False
    try:
        observation, _ = env.reset(seed=seed)
        with th.inference_mode():
            while not done:
                image, _ = policy.obs_to_tensor(observation)  # SB3's: channels first, batch of one
                # belief_step would encode the frame once per filter; both filters share this feature
                feature = latent.encode(policy.preprocess(image).unsqueeze(1)).squeeze(1)  # type: ignore[arg-type]
                z1, sampled_z2 = latent.filter_step(feature, sampled_z2, action, start)
                mean_z1, mean_z2 = latent.filter_step(feature, mean_z2, action, start, deterministic=True)
                actor_input, memory = policy.acting_input(th.cat([z1, sampled_z2], dim=-1), action, memory, start)
                action = policy.actor(actor_input)
                features.append(feature[0])
                beliefs.append(th.cat([mean_z1, mean_z2], dim=-1)[0])
                actions.append(action[0])
                observation, _, terminated, truncated, _ = env.step(policy.unscale_action(action.numpy())[0])
                done = terminated or truncated
                start = th.zeros(1, dtype=th.bool)
    finally:
        env.close()
    return FilteredEpisode(th.stack(features), th.stack(actions[:-1]), th.stack(beliefs))


def window_beliefs(model: DSSLAC, episode: FilteredEpisode, frames: int) -> th.Tensor:
    """
    Posterior means of each frame's belief filtered over only its last ``frames`` frames: (T - frames + 1, Z), for the
    frames ``frames - 1`` to ``T - 1``, as a replay window of ``frames`` frames gives its last frame.
    """
    count = len(episode.features) - frames + 1
    starts = th.arange(count).unsqueeze(1)
    window_features = episode.features[starts + th.arange(frames)]
    window_actions = episode.actions[starts + th.arange(frames - 1)]
    latent = model.policy.latent
    zeros = (th.zeros(frames, count, latent.z1_dim), th.zeros(frames, count, latent.z2_dim))
    with th.inference_mode():
        rollout = latent.posterior(window_features, window_actions, noise=zeros)
    return th.cat([rollout.z1, rollout.z2], dim=-1)[:, -1]


def mismatch_share(model: DSSLAC, episodes: list[FilteredEpisode], frames: int) -> float:
    """Mean squared distance between online and ``frames``-frame window beliefs over the online beliefs' variance."""
    online = th.cat([episode.beliefs[frames - 1 :] for episode in episodes])
    windowed = th.cat([window_beliefs(model, episode, frames) for episode in episodes])
    spread = (online - online.mean(dim=0)).pow(2).sum(dim=-1).mean()
    return float((online - windowed).pow(2).sum(dim=-1).mean() / spread)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="a train run folder (its model.zip) or a saved model")
    parser.add_argument("--env", default=None, help="the env (default: the run's own, else SafetyGym/PointGoal1-v0)")
    parser.add_argument("--episodes", type=int, default=6, help="episodes of the agent's stochastic policy")
    parser.add_argument("--seed", type=int, default=10_000, help="reset seed of the first episode (then +1 each)")
    parser.add_argument(
        "--windows", type=int, nargs="+", default=[1, 2, 4, 10, 20], help="window lengths k in frames (and the training one)"
    )
    args = parser.parse_args()
    path = args.model / FINAL_MODEL if args.model.is_dir() else args.model
    if not path.is_file():
        raise SystemExit(f"{args.model}: no saved model ({FINAL_MODEL} of a finished run, or a model's .zip)")
    th.set_num_threads(1)
    th.manual_seed(args.seed)
    model = DSSLAC.load(path, device="cpu")
    if len(model.policy.latent.observation_shape) != 3:
        raise SystemExit(f"{path} is not a pixel agent: its observations are {model.policy.latent.observation_shape}")
    config = find_run_config(path)
    env_id = args.env or (config.env if config is not None else "SafetyGym/PointGoal1-v0")
    env_kwargs = config.env_kwargs if config is not None else None  # the run's own image size
    episodes = [filtered_episode(model, env_id, args.seed + index, env_kwargs) for index in range(args.episodes)]
    frames = sum(len(episode.features) for episode in episodes)
    training_window = model.sequence_length  # transitions per replay window: z has that many frames behind it
    lengths = sorted({*args.windows, training_window})
    shortest = min(len(episode.features) for episode in episodes)
    if lengths[0] < 1 or lengths[-1] > shortest:
        raise SystemExit(f"--windows: every length must be between 1 and the shortest episode's {shortest} frames")
    print(f"{path}: {args.episodes} episodes ({frames} frames) of its stochastic policy on {env_id}, {cpu_model()}")
    print(f"training windows: {training_window} frames for z, {training_window + 1} for the next z\n")
    print("| window, frames | online-vs-window distance, share of the belief's variance |\n|---:|---:|")
    for length in lengths:
        print(f"| {length} | {mismatch_share(model, episodes, length):.3f} |")


if __name__ == "__main__":
    main()
