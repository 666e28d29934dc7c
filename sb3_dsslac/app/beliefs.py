"""What a pixel agent sees and believes: one episode's frames beside the latent model's reconstructions of them, with
the cost decoder's probability of cost at every step, as one PNG."""

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch as th

from sb3_dsslac.common.env_info import cost_from_info
from sb3_dsslac.app.rollouts import make_model_env
from sb3_dsslac.dsslac import DSSLAC


class EpisodeBeliefs(NamedTuple):
    """One episode of ``T`` agent steps as the agent filtered it."""

    frames: np.ndarray  # (T + 1, H, W, 3) uint8 observations
    reconstructions: np.ndarray  # (T + 1, H, W, 3) uint8 decoder means of the filter's beliefs
    cost_probabilities: np.ndarray  # (T,) p(c_t > 0 | z_t, a_t, z_{t+1}) of step t -> t+1
    costs: np.ndarray  # (T,) cost of step t -> t+1
    rewards: np.ndarray  # (T,) reward of step t -> t+1


def _to_uint8_image(chw: th.Tensor) -> np.ndarray:
    """(C, H, W) floats in [0, 1] -> (H, W, C) uint8."""
    return (chw.clamp(0.0, 1.0) * 255.0).round().to(th.uint8).permute(1, 2, 0).cpu().numpy()


def episode_beliefs(
    model: DSSLAC,
    env_id: str,
    seed: int = 0,
    max_steps: int | None = None,
    deterministic: bool = True,
    env_kwargs: dict[str, Any] | None = None,
) -> EpisodeBeliefs:
    """
    Run one episode with ``model`` on pixels and record, at every step, the frame, the decoder's reconstruction of
    the filter's belief about it, and the cost decoder's probability that the step costs.

    :param model: a DS-SLAC agent trained on image observations
    :param env_id: the env (see ``make_env``), with pixel observations of the model's frame size
    :param seed: seed of the episode's reset
    :param max_steps: stop after this many agent steps (None: the whole episode)
    :param deterministic: act and filter with means (False: sampled, as the thesis evaluates)
    :param env_kwargs: other keywords of the env
    """
    policy = model.policy
    if len(policy.latent.observation_shape) != 3:
        raise ValueError(f"episode_beliefs needs an agent trained on images, this one sees {policy.latent.observation_shape}")
    env = make_model_env(model, env_id, "pixels", env_kwargs=env_kwargs)
    policy.set_training_mode(False)
    frames, reconstructions, transitions, costs, rewards = [], [], [], [], []
    try:
        observation, _ = env.reset(seed=seed)
        z2, action, memory = policy.initial_state(1)
        start = th.ones(1, dtype=th.bool, device=policy.device)
        done, steps = False, 0
        with th.inference_mode():
            while True:
                obs_tensor, _ = policy.obs_to_tensor(observation)  # SB3's: channels first, batch of one, on the device
                z, z2 = policy.belief_step(obs_tensor, z2, action, start, deterministic)  # type: ignore[arg-type]
                frames.append(np.asarray(observation))
                reconstructions.append(_to_uint8_image(policy.latent.decode(z.unsqueeze(1))[0, 0]))
                if transitions:
                    transitions[-1].append(z)
                if done or (max_steps is not None and steps == max_steps):
                    break
                actor_input, memory = policy.acting_input(z, action, memory, start)
                action = policy.actor(actor_input, deterministic=deterministic)
                transitions.append([z, action])
                env_action = policy.unscale_action(action.cpu().numpy()).reshape(env.action_space.shape)
                observation, reward, terminated, truncated, info = env.step(env_action)
                rewards.append(float(reward))
                costs.append(cost_from_info(info))
                start = th.zeros(1, dtype=th.bool, device=policy.device)
                done, steps = terminated or truncated, steps + 1
            if transitions:
                z, actions, next_z = (th.cat(parts) for parts in zip(*transitions, strict=True))
                cost_probabilities = policy.latent.cost_probability(z, actions, next_z).cpu().numpy()
            else:
                cost_probabilities = np.zeros(0)
    finally:
        env.close()
    return EpisodeBeliefs(
        np.stack(frames), np.stack(reconstructions), cost_probabilities, np.asarray(costs), np.asarray(rewards)
    )


def mean_cost_probabilities(beliefs: EpisodeBeliefs) -> tuple[float, float]:
    """Mean predicted probability of cost over the steps that cost and over those that did not (NaN where none)."""
    costly = beliefs.costs > 0
    on_costly = float(beliefs.cost_probabilities[costly].mean()) if costly.any() else float("nan")
    on_free = float(beliefs.cost_probabilities[~costly].mean()) if (~costly).any() else float("nan")
    return on_costly, on_free


def plot_beliefs(beliefs: EpisodeBeliefs, path: str | Path, n_frames: int = 10, title: str | None = None) -> Path:
    """
    Write a PNG: ``n_frames`` frames spread over the episode (the costly steps among them) above the reconstructions
    of the filter's beliefs, with the predicted probability of cost and the cost of the step into each frame, and a
    strip of both along the whole episode.

    :return: the path written
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_steps = len(beliefs.costs)
    if n_steps == 0:
        raise ValueError("the episode has no steps to show")
    picks = _pick_steps(beliefs.costs, n_frames)
    figure = plt.figure(figsize=(1.6 * len(picks), 5.6), constrained_layout=True)
    grid = figure.add_gridspec(3, len(picks), height_ratios=[1, 1, 1.1])
    for column, step in enumerate(picks):
        frame = step + 1  # the frame that step t -> t+1 led to
        for row, (images, label) in enumerate([(beliefs.frames, "observed"), (beliefs.reconstructions, "believed")]):
            axis = figure.add_subplot(grid[row, column])
            axis.imshow(images[frame])
            axis.set_xticks([])
            axis.set_yticks([])
            if column == 0:
                axis.set_ylabel(label)
            if row == 0:
                axis.set_title(f"step {frame}", fontsize=8)
            else:
                axis.set_xlabel(f"p(cost) {beliefs.cost_probabilities[step]:.2f}\ncost {beliefs.costs[step]:g}", fontsize=8)
    strip = figure.add_subplot(grid[2, :])
    steps = np.arange(1, n_steps + 1)
    strip.plot(steps, beliefs.cost_probabilities, color="tab:red", label="predicted p(cost)")
    strip.fill_between(steps, 0, (beliefs.costs > 0).astype(float), step="mid", color="k", alpha=0.15, label="cost > 0")
    strip.scatter(picks + 1, beliefs.cost_probabilities[picks], color="tab:red", s=12, zorder=3)
    strip.set_xlim(0, n_steps + 1)
    strip.set_ylim(-0.02, 1.02)
    strip.set_xlabel("agent step")
    strip.legend(loc="upper right", fontsize=8)
    figure.suptitle(
        title or f"episode of {n_steps} steps: reward {beliefs.rewards.sum():.1f}, cost {beliefs.costs.sum():g}", fontsize=10
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def _pick_steps(costs: np.ndarray, n_frames: int) -> np.ndarray:
    """Up to ``n_frames`` step indices in order: evenly spread, half of them on costly steps where there are some."""
    n_steps = len(costs)
    costly = np.flatnonzero(costs > 0)
    n_costly = min(len(costly), n_frames // 2)
    chosen = set(costly[np.linspace(0, len(costly) - 1, n_costly).round().astype(int)].tolist()) if n_costly else set()
    for step in np.linspace(0, n_steps - 1, n_frames).round().astype(int):
        if len(chosen) >= n_frames:
            break
        chosen.add(int(step))
    return np.array(sorted(chosen))
