"""
How many latent-model updates does a preset need before its reconstructions hold the hazards and the goal? Latent
training alone (no actor-critic) on a buffer of random-policy pixel frames, probed after each of ``--checkpoints``
updates: the mean absolute reconstruction error (in [0, 1]) of the filter's beliefs along three deterministic
evaluation episodes, over the hazard pixels (blue), the goal pixels (green) and all pixels; the reward decoder's R^2
on held-out random-policy windows (another env seed: the reward says how far the robot moved toward the goal, so it
measures how much of the goal the latent holds); the R^2 of linear readouts of the goal's and the hazards' column from
the belief and from the encoder feature (``belief_probe.py``, on the training windows); and a ``beliefs.png`` of the
first episode at each checkpoint.

    python benchmarks/tools/diagnostics/reconstruction_speed.py                                # cpu_pixels, 20k random steps
    # the thesis's likelihood variance
    python benchmarks/tools/diagnostics/reconstruction_speed.py --hyperparams image_noise=0.4

One torch thread; about 6 latent updates/s at the cpu_pixels sizes on a 2-core AMD EPYC shared with two other jobs.
"""

import argparse
import json
import sys
import time
from pathlib import Path

# The benchmarks' shared modules (machine.py) sit one folder up
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
import torch as th
from belief_probe import probe
from goal_view import goal_in_view, object_masks
from machine import cpu_model

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.beliefs import EpisodeBeliefs, episode_beliefs, plot_beliefs
from sb3_dsslac.app.runs import parse_hyperparams
from sb3_dsslac.common.buffers import SequenceBatch
from sb3_dsslac.common.envs import make_env
from sb3_dsslac.presets import preset_env_kwargs, preset_hyperparams


def reconstruction_errors(episodes: list[EpisodeBeliefs]) -> dict[str, float | None]:
    """Mean absolute error of the reconstructions over hazard, goal and all pixels (None where none was seen)."""
    errors: dict[str, list[float]] = {"hazard": [], "goal": [], "all": []}
    for beliefs in episodes:
        error = np.abs(beliefs.frames.astype(np.float32) - beliefs.reconstructions.astype(np.float32)).mean(-1) / 255.0
        for name, mask in object_masks(beliefs.frames).items():
            if mask.any():
                errors[name].append(float(error[mask].mean()))
        errors["all"].append(float(error.mean()))
    return {name: round(float(np.mean(values)), 3) if values else None for name, values in errors.items()}


def held_out_windows(env_id: str, env_kwargs: dict, hyperparams: dict, steps: int) -> SequenceBatch:
    """All windows of ``steps`` random-policy agent steps of a separate env seed, as a latent update sees them."""
    hyperparams = {**hyperparams, "learning_starts": steps, "train_freq": steps + 1, "buffer_size": steps + 1}
    collector = DSSLAC("LatentPolicy", make_env(env_id, "pixels", env_kwargs=env_kwargs), seed=1, verbose=0, **hyperparams)
    collector.learn(steps)
    buffer = collector.replay_buffer
    windows = buffer.valid_windows(buffer.sequence_length)
    return buffer.gather(th.as_tensor(np.stack([windows, np.zeros_like(windows)], axis=-1)).to(buffer.device))


def reward_r2(model: DSSLAC, windows: SequenceBatch, chunk: int = 256) -> dict[str, float | None]:
    """
    R^2 of the reward decoder's means on ``windows`` (posterior latents of each window; all its transitions): over all
    transitions, and over those whose two frames both show the goal (``goal_view``'s in-view rule), where the frames hold
    what the reward depends on (None: fewer than two such transitions).
    """
    latent, predictions = model.policy.latent, []
    with th.no_grad():
        for start in range(0, len(windows.rewards), chunk):
            observations = model.policy.preprocess(windows.observations[start : start + chunk])
            actions = windows.actions[start : start + chunk]
            z = latent.sample_latents(observations, actions)
            mean, _ = latent.reward_decoder(th.cat([z[:, :-1], actions, z[:, 1:]], dim=-1))
            predictions.append(mean.squeeze(-1))
    frames = windows.observations.permute(0, 1, 3, 4, 2).numpy()  # (B, L+1, H, W, C)
    shown = goal_in_view(frames)  # (B, L+1)
    in_view = th.as_tensor(shown[:, :-1] & shown[:, 1:])
    errors, rewards = (th.cat(predictions) - windows.rewards).pow(2), windows.rewards

    def r2(mask: th.Tensor) -> float | None:
        if int(mask.sum()) < 2:
            return None
        return round(float(1.0 - errors[mask].mean() / rewards[mask].var()), 3)

    share = round(float(in_view.float().mean()), 3)
    return {"all": r2(th.ones_like(in_view)), "goal_in_view": r2(in_view), "share_in_view": share}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="SafetyGym/PointGoal1-v0")
    parser.add_argument("--preset", default="cpu_pixels")
    parser.add_argument("--hyperparams", nargs="*", default=[], metavar="KEY=VALUE", help="DSSLAC keywords (YAML)")
    parser.add_argument("--random-steps", type=int, default=20_000, help="agent steps of random-policy frames")
    parser.add_argument("--checkpoints", type=int, nargs="+", default=[1000, 2000, 4000, 7000, 10000, 14000, 20000])
    parser.add_argument("--held-out-steps", type=int, default=2_000, help="random agent steps of the reward R^2 windows")
    parser.add_argument("--probe-windows", type=int, default=1_000, help="replay windows of the linear readouts")
    parser.add_argument("--episode-steps", type=int, default=150, help="agent steps of each probe episode")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/reconstruction_speed"))
    args = parser.parse_args()
    if sorted(args.checkpoints) != args.checkpoints or args.checkpoints[0] < 1:
        raise SystemExit("--checkpoints must be increasing positive update counts")
    th.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)

    hyperparams = preset_hyperparams(args.preset, parse_hyperparams(args.hyperparams))
    # One rollout of random steps, then a single actor-critic update; the latent updates come below
    hyperparams.update(learning_starts=args.random_steps, train_freq=args.random_steps + 1, gradient_steps=1)
    hyperparams.update(latent_pretrain_steps=0, buffer_size=args.random_steps + 1)
    env_kwargs = preset_env_kwargs(args.preset)  # the frame size and action repeat the preset runs at
    model = DSSLAC("LatentPolicy", make_env(args.env, "pixels", env_kwargs=env_kwargs), seed=0, verbose=0, **hyperparams)
    model.learn(args.random_steps + 1)
    windows = held_out_windows(args.env, env_kwargs, hyperparams, args.held_out_steps)
    overrides = parse_hyperparams(args.hyperparams) or ""
    print(f"{args.env} {env_kwargs or ''}, preset {args.preset} {overrides}, {cpu_model()}, one thread")
    done = 0
    for target in args.checkpoints:
        n_updates = target - done
        model.latent_pretrain_steps = n_updates
        start = time.perf_counter()
        model._pretrain_latent()  # the latent model's own updates, as in the pre-training
        seconds = time.perf_counter() - start
        done = target
        episodes = [
            episode_beliefs(model, args.env, seed=10_000 + index, max_steps=args.episode_steps, env_kwargs=env_kwargs)
            for index in range(3)
        ]
        scores, _, _ = probe(model, args.probe_windows)
        plot_beliefs(episodes[0], args.out / f"beliefs_{done}.png", title=f"after {done:,} latent updates")
        row = {"latent_updates": done, "updates_per_s": round(n_updates / seconds, 2)}
        row["reward_r2"] = reward_r2(model, windows)
        row["readout_r2"] = {name: scores[name] for name in ("goal column", "hazard column")}
        print(json.dumps({**row, "mean_abs_error": reconstruction_errors(episodes)}), flush=True)


if __name__ == "__main__":
    main()
