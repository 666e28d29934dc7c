"""Evaluation episodes run step by step through ``predict``, with a video of the first-person and third-person views."""

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from tqdm.auto import tqdm

from sb3_dsslac.common.env_info import cost_from_info
from sb3_dsslac.common.envs import make_env
from sb3_dsslac.common.evaluation import EpisodeResults, eval_policy_name
from sb3_dsslac.common.validation import InputError, check_env_fits_model
from sb3_dsslac.dsslac import DSSLAC


def side_by_side(observation: np.ndarray, view: np.ndarray) -> np.ndarray:
    """
    One video frame: the agent's image observation, upscaled to the view's height, left of the view.

    :param observation: (h, w, 3) uint8 first-person image (anything else is left out)
    :param view: (H, W, 3) uint8 third-person image
    :return: (H, W + w * k, 3) uint8 with k = H // h, or the view alone
    """
    if observation.ndim != 3 or observation.shape[-1] != 3 or observation.dtype != np.uint8:
        return view
    scale = max(view.shape[0] // observation.shape[0], 1)
    upscaled = observation.repeat(scale, axis=0).repeat(scale, axis=1)
    pad = view.shape[0] - upscaled.shape[0]
    upscaled = np.pad(upscaled, ((0, max(pad, 0)), (0, 0), (0, 0)))[: view.shape[0]]
    return np.concatenate([upscaled, view], axis=1)


def make_model_env(
    model: DSSLAC,
    env_id: str,
    obs_type: str | None = None,
    render_mode: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
) -> gym.Env:
    """``make_env`` for a saved model: an env whose observations and actions differ from the model's is refused
    (``check_env_fits_model``) before any episode."""
    env = make_env(env_id, obs_type, render_mode=render_mode, env_kwargs=env_kwargs)
    try:
        check_env_fits_model(env, model.observation_space, model.action_space, env_id)
    except InputError:
        env.close()
        raise
    return env


def evaluate(
    model: DSSLAC,
    env_id: str,
    episodes: int = 10,
    deterministic: bool = False,
    seed: int = 0,
    video: str | Path | None = None,
    video_episodes: int = 1,
    obs_type: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
) -> EpisodeResults:
    """
    Run ``model`` for ``episodes`` episodes, its latent filter carried through ``predict`` (reset at each episode
    start), and optionally write a video of the first ``video_episodes``: first-person view beside third-person view.

    :param model: the agent
    :param env_id: the env (see ``make_env``)
    :param episodes: episodes to run; episode ``i`` is reset with seed ``seed + i``
    :param deterministic: act with the mean action and the filter's means (False: sampled, the thesis's protocol)
    :param seed: seed of the first episode
    :param video: the video file (.mp4 or .gif); None writes none
    :param video_episodes: episodes recorded into the video
    :param obs_type: the observation type the model was trained on (None: the env's default)
    :param env_kwargs: other keywords of the env
    :return: per-episode rewards, costs and lengths (agent steps)
    """
    env = make_model_env(model, env_id, obs_type, render_mode="rgb_array" if video else None, env_kwargs=env_kwargs)
    writer = None
    if video is not None:
        import imageio

        Path(video).parent.mkdir(parents=True, exist_ok=True)
        fps = env.metadata.get("render_fps") or 25
        timing = {"duration": 1000 / fps, "loop": 0} if str(video).endswith(".gif") else {"fps": fps}
        try:
            writer = imageio.get_writer(str(video), **timing)
        except (OSError, ValueError) as error:
            env.close()
            raise ValueError(
                f"Cannot write {video} ({error}); .mp4 needs `pip install imageio-ffmpeg`, or write a .gif"
            ) from error
    rewards, costs, lengths = np.zeros(episodes), np.zeros(episodes), np.zeros(episodes, dtype=int)
    try:
        for episode in tqdm(range(episodes), desc="episodes"):
            observation, _ = env.reset(seed=seed + episode)
            state, start, done = None, True, False
            while not done:
                action, state = model.predict(
                    observation, state=state, episode_start=np.array([start]), deterministic=deterministic
                )
                if writer is not None and episode < video_episodes:
                    writer.append_data(side_by_side(np.asarray(observation), env.render()))  # type: ignore[arg-type]
                observation, reward, terminated, truncated, info = env.step(action)
                rewards[episode] += float(reward)
                costs[episode] += cost_from_info(info)
                lengths[episode] += 1
                start, done = False, terminated or truncated
    finally:
        if writer is not None:
            writer.close()
        env.close()
    return EpisodeResults(rewards, costs, lengths)


def format_episodes(results: EpisodeResults, cost_limit: float | None = None, deterministic: bool | None = None) -> str:
    """
    A text table of the episodes, then their mean and standard deviation.

    :param results: the episodes
    :param cost_limit: the budget; given, a last line counts the episodes within it
    :param deterministic: how the episodes were run; given, a first line says so
    """
    lines = [] if deterministic is None else [f"policy: {eval_policy_name(deterministic)}"]
    lines.append(f"{'episode':>7}  {'reward':>9}  {'cost':>7}  {'length':>6}")
    for index, (reward, cost, length) in enumerate(zip(*results, strict=True)):
        lines.append(f"{index:>7}  {reward:>9.3f}  {cost:>7.1f}  {length:>6}")
    lines.append(
        f"{'mean':>7}  {results.rewards.mean():>9.3f}  {results.costs.mean():>7.1f}  {results.lengths.mean():>6.0f}"
        f"   (std: reward {results.rewards.std():.3f}, cost {results.costs.std():.1f})"
    )
    if cost_limit is not None:
        within = int((results.costs <= cost_limit).sum())
        lines.append(f"episodes within the budget {cost_limit:g}: {within}/{len(results.costs)}")
    return "\n".join(lines)
