"""
Does a pixel agent's belief remember where the goal went? Along the agent's own episodes on a Goal task (its stochastic
policy, or its means with ``--deterministic``), each agent step records the online filter's mean belief (the filter
run on its means beside the sampled one the agent acts on, as ``tools/diagnostics/filter_memory.py`` does), the
previous action, the goal's bearing from the robot's heading (from the simulator: the angle of the goal's centre in the
horizontal plane from the direction the robot's camera looks, counter-clockwise positive) and whether the goal's centre
is inside the camera's horizontal field of view (``goal_view.goal_in_fov``), with the agent steps since it last was.
With an actor-critic memory (``LatentPolicy(actor_critic_memory=H)``) the recorded belief carries the memory the agent
acts on beside it: what the actor and critics can read the goal from.
The count starts afresh when a goal is reached: the steps before the new goal is first in view are in no row below.

A linear ridge probe from the belief to (cos, sin) of the bearing is fitted on half the episodes (even-indexed) and
scored on the other half (odd-indexed), then the halves are swapped; a probe is fitted for each kind of step (goal in
view; last in view 3-20, 3-8 and 9-20 agent steps earlier) on those steps of the fit half. The ridge penalty is chosen
on the fit half by cross-validation over its episodes (up to 5 folds of whole episodes). Reported: R^2 of (cos, sin),
pooled over the two outputs (1 - their summed squared error over their summed variance on the scored steps) and
averaged over the two halves, and the median absolute error (degrees, over the scored steps of both halves) of the
angle of the predicted (cos, sin); and the same from the previous action alone, the control (a turn under way says
which way the goal went). The headline is the belief's R^2 on the steps whose goal was last in view 3-20 agent steps
earlier.

An agent that keeps the goal in view has few such steps: 60 episodes (the default) give a trained PointGoal1 agent
about 1,000-2,300 of them. With 20 episodes (350-850 steps, about 200 per half for a belief of 80 dimensions) the same
GRU agent's headline read -0.39, with 60 it read 0.37: the probe over-fits the half it is fitted on. The table gives
the count of each kind; read a row with a few hundred steps as noise.

    python benchmarks/goal_memory.py runs/<run>  # a run of `python -m sb3_dsslac train --obs-type pixels` on a Goal task
    python benchmarks/goal_memory.py model.zip --env SafetyGym/CarGoal1-v0 --episodes 100 --deterministic

A model.zip outside a run folder runs on PointGoal1 unless ``--env`` names another Goal task, at its own frame size
and action repeat.
"""

import argparse
import os
import shlex
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

# Run from a checkout without installing: the repository (safety_envs) and the benchmarks' shared modules
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import gymnasium as gym
import numpy as np
import torch as th
from goal_view import goal_in_fov
from machine import cpu_model

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.rollouts import make_model_env
from sb3_dsslac.app.runs import CHECKPOINT_DIR, FINAL_MODEL, find_run_config
from sb3_dsslac.common.env_info import cost_from_info

DEFAULT_ENV = "SafetyGym/PointGoal1-v0"
NOT_SEEN = -1  # steps since in view of a step whose goal has not been in view since it was placed
STEP_KINDS = {  # name -> (fewest, most) agent steps since the goal was last in view
    "goal in view": (0, 0),
    "out of view 3-20 steps": (3, 20),
    "out of view 3-8 steps": (3, 8),
    "out of view 9-20 steps": (9, 20),
}
HEADLINE = "out of view 3-20 steps"
RIDGE_PENALTIES = 10.0 ** np.arange(-4.0, 3.0)  # relative to the inputs' mean sum of squares per dimension
CV_FOLDS = 5
MIN_ROWS = 2 * CV_FOLDS  # fewest steps of a kind in a fit half and in a scored half


class GoalEpisode(NamedTuple):
    """One episode of ``T`` agent steps: what the agent believed and where the goal was at each frame it acted on."""

    beliefs: np.ndarray  # (T, Z) the online filter's means
    previous_actions: np.ndarray  # (T, A) the action before each frame, scaled to [-1, 1] (zeros before the first)
    bearings: np.ndarray  # (T,) rad in [-pi, pi]: the goal from the robot's heading, counter-clockwise positive
    in_fov: np.ndarray  # (T,) bool: the goal's centre inside the camera's horizontal field of view
    new_goal: np.ndarray  # (T,) bool: the goal was placed since the previous frame (the first frame's at reset)
    reward: float
    cost: float


class ProbeScore(NamedTuple):
    """A probe's held-out scores on one kind of step."""

    r2: float  # R^2 of (cos, sin), pooled over the two outputs, mean over the two halves
    median_error: float  # degrees: median absolute error of the predicted bearing
    steps: int  # scored steps, both halves


class KindScores(NamedTuple):
    """The probes on one kind of step (``STEP_KINDS``)."""

    share: float  # of all steps
    steps: int  # steps of the kind, both halves
    belief: ProbeScore | None  # from the filter's mean belief (None: a half has under ``MIN_ROWS`` steps of the kind)
    previous_action: ProbeScore | None  # from the previous action alone, the control


def bearing(offsets: np.ndarray, headings: np.ndarray) -> np.ndarray:
    """
    Angle of each planar offset from a heading: (..., 2) m and (..., 2) directions (any length) -> (...) rad in
    [-pi, pi], counter-clockwise (to the left) positive.
    """
    cross = headings[..., 0] * offsets[..., 1] - headings[..., 1] * offsets[..., 0]
    return np.arctan2(cross, (headings * offsets).sum(axis=-1))


def goal_bearing(env: gym.Env) -> float:
    """
    The goal's bearing (rad) from the robot's heading, from the simulator state: the goal's centre seen from the
    ``vision`` camera, from the horizontal direction the camera looks (the Point's body x axis, the Car's -y axis).

    :param env: a ``safety_envs`` Goal env (``SafetyGymEnv``, or a wrapper of one)
    """
    sim = env.unwrapped
    camera, data = sim.ids.vision_camera, sim.data
    offset = data.xpos[sim.ids.goal_body, :2] - data.cam_xpos[camera, :2]
    looks_along = -data.cam_xmat[camera].reshape(3, 3)[:2, 2]  # the camera looks along its -z axis
    return float(bearing(offset, looks_along))


def steps_since_in_view(in_fov: np.ndarray, new_goal: np.ndarray) -> np.ndarray:
    """
    (T,) bool flags of one episode -> (T,) int: agent steps since the goal was last in view (0 where it is), ``NOT_SEEN``
    where the goal has not been in view since it was placed (``new_goal``).
    """
    since = np.empty(len(in_fov), dtype=np.int64)
    last_seen = None
    for step, (seen, placed) in enumerate(zip(in_fov, new_goal, strict=True)):
        if placed:
            last_seen = None
        if seen:
            last_seen = step
        since[step] = NOT_SEEN if last_seen is None else step - last_seen
    return since


def goal_episode(model: DSSLAC, env: gym.Env, seed: int, deterministic: bool = False) -> GoalEpisode:
    """
    Run one episode of ``model`` in ``env`` from reset seed ``seed``, filtering each frame twice: the filter the agent
    acts on (sampled, or its means with ``deterministic``) and the filter on its means, whose belief is recorded.
    """
    policy, latent = model.policy, model.policy.latent
    policy.set_training_mode(False)
    beliefs, previous_actions, bearings, in_fov, new_goal = [], [], [], [], []
    reward = cost = 0.0
    acting_z2, action, memory = policy.initial_state(1)
    mean_z2 = acting_z2.clone()
    start = th.ones(1, dtype=th.bool)
    observation, info = env.reset(seed=seed)
    placed, done = True, False
    with th.inference_mode():
        while not done:
            image, _ = policy.obs_to_tensor(observation)  # SB3's: channels first, batch of one
            # belief_step would encode the frame once per filter; both filters share this feature
            feature = latent.encode(policy.preprocess(image).unsqueeze(1)).squeeze(1)  # type: ignore[arg-type]
            z1, acting_z2 = latent.filter_step(feature, acting_z2, action, start, deterministic)
            mean_z1, mean_z2 = latent.filter_step(feature, mean_z2, action, start, deterministic=True)
            z = th.cat([z1, acting_z2], dim=-1)
            actor_input, memory = policy.acting_input(z, action, memory, start)
            beliefs.append(th.cat([mean_z1, mean_z2, memory], dim=-1)[0].numpy())
            previous_actions.append(action[0].numpy())
            bearings.append(goal_bearing(env))
            in_fov.append(goal_in_fov(env))
            new_goal.append(placed)
            action = policy.actor(actor_input, deterministic=deterministic)
            observation, step_reward, terminated, truncated, info = env.step(policy.unscale_action(action.numpy())[0])
            reward, cost = reward + float(step_reward), cost + cost_from_info(info)
            placed, done = bool(info.get("goal_met", False)), terminated or truncated
            start = th.zeros(1, dtype=th.bool)
    return GoalEpisode(
        np.stack(beliefs),
        np.stack(previous_actions),
        np.asarray(bearings),
        np.asarray(in_fov),
        np.asarray(new_goal),
        reward,
        cost,
    )


def episode_halves(n_episodes: int) -> tuple[np.ndarray, np.ndarray]:
    """The probe's two halves of ``n_episodes`` episodes: the even-indexed and the odd-indexed episodes."""
    episodes = np.arange(n_episodes)
    return episodes[::2], episodes[1::2]


def ridge_predict(fit_inputs: np.ndarray, fit_targets: np.ndarray, inputs: np.ndarray, penalties: np.ndarray) -> np.ndarray:
    """
    Ridge regressions with intercept, closed form (one eigendecomposition for all penalties), on inputs centred on the
    fit rows' mean. Inputs are not scaled per dimension (one that hardly varies on the fit rows would be blown up on
    others); each penalty is relative to the centred inputs' mean sum of squares per dimension, so that the same
    penalties suit beliefs of any scale.

    :param fit_inputs: (N, D) inputs of the fit rows
    :param fit_targets: (N, K) their targets
    :param inputs: (M, D) rows to predict
    :param penalties: (P,) relative ridge penalties
    :return: (P, M, K) predictions, one set per penalty
    """
    input_mean, target_mean = fit_inputs.mean(axis=0), fit_targets.mean(axis=0)
    design = fit_inputs - input_mean
    eigenvalues, eigenvectors = np.linalg.eigh(design.T @ design)
    scale = max(float(eigenvalues.mean()), 1e-12)
    projected = (inputs - input_mean) @ eigenvectors  # (M, D)
    covariance = eigenvectors.T @ (design.T @ (fit_targets - target_mean))  # (D, K)
    shrinkage = 1.0 / (eigenvalues + np.asarray(penalties)[:, None] * scale)  # (P, D)
    return (projected * shrinkage[:, None, :]) @ covariance + target_mean


def cv_folds(episode_ids: np.ndarray) -> list[np.ndarray]:
    """
    Cross-validation folds of the fit rows, (N,) the episode of each row -> row indices per fold: up to ``CV_FOLDS``
    folds of whole episodes (an episode's steps are alike; a fold holding part of one would flatter a weak penalty),
    ``CV_FOLDS`` contiguous blocks of steps where the rows hold a single episode.
    """
    episodes = np.unique(episode_ids)
    if len(episodes) == 1:
        return np.array_split(np.arange(len(episode_ids)), CV_FOLDS)
    return [np.flatnonzero(np.isin(episode_ids, fold)) for fold in np.array_split(episodes, min(CV_FOLDS, len(episodes)))]


def chosen_penalty(inputs: np.ndarray, targets: np.ndarray, episode_ids: np.ndarray) -> float:
    """The ``RIDGE_PENALTIES`` entry of least summed squared error over the held-out folds of ``cv_folds``."""
    everything = np.arange(len(targets))
    errors = np.zeros(len(RIDGE_PENALTIES))
    for fold in cv_folds(episode_ids):
        fit = np.setdiff1d(everything, fold)
        predictions = ridge_predict(inputs[fit], targets[fit], inputs[fold], RIDGE_PENALTIES)
        errors += ((predictions - targets[fold]) ** 2).sum(axis=(1, 2))
    return float(RIDGE_PENALTIES[int(np.argmin(errors))])


def r2_score(predictions: np.ndarray, targets: np.ndarray) -> float:
    """
    (N, K) predictions and targets -> R^2 pooled over the K columns: 1 - the summed squared error over the summed
    squared deviation of each column from its mean (a column of little spread, the cosine with the goal in view, does
    not dominate it as it would a mean of per-column R^2).
    """
    residual = ((predictions - targets) ** 2).sum()
    spread = max(float(((targets - targets.mean(axis=0)) ** 2).sum()), 1e-12)
    return float(1.0 - residual / spread)


def angle_errors(predictions: np.ndarray, bearings: np.ndarray) -> np.ndarray:
    """(N, 2) predicted (cos, sin) and (N,) true bearings (rad) -> (N,) absolute angle errors in degrees, in [0, 180]."""
    difference = np.arctan2(predictions[:, 1], predictions[:, 0]) - bearings
    return np.degrees(np.abs(np.arctan2(np.sin(difference), np.cos(difference))))


def probe_score(inputs: np.ndarray, bearings: np.ndarray, episode_ids: np.ndarray, rows: np.ndarray) -> ProbeScore | None:
    """
    A ridge probe from ``inputs`` to (cos, sin) of ``bearings``, fitted on the ``rows`` of one half of the episodes
    (``episode_halves``) and scored on those of the other, then swapped; None where a half has under ``MIN_ROWS``.

    :param inputs: (N, D) per step
    :param bearings: (N,) rad per step
    :param episode_ids: (N,) the episode of each step
    :param rows: (N,) bool: the steps of the kind probed
    """
    targets = np.stack([np.cos(bearings), np.sin(bearings)], axis=1)
    first, second = (rows & np.isin(episode_ids, half) for half in episode_halves(int(episode_ids.max()) + 1))
    if min(first.sum(), second.sum()) < MIN_ROWS:
        return None
    r2s, errors = [], []
    for fit, scored in ((first, second), (second, first)):
        penalty = chosen_penalty(inputs[fit], targets[fit], episode_ids[fit])
        predictions = ridge_predict(inputs[fit], targets[fit], inputs[scored], np.array([penalty]))[0]
        r2s.append(r2_score(predictions, targets[scored]))
        errors.append(angle_errors(predictions, bearings[scored]))
    pooled = np.concatenate(errors)
    return ProbeScore(float(np.mean(r2s)), float(np.median(pooled)), len(pooled))


class PooledSteps(NamedTuple):
    """Every agent step of several ``GoalEpisode``s, in episode order: what the probes read."""

    since: np.ndarray  # (N,) agent steps since the goal was last in view (``steps_since_in_view``)
    episode_ids: np.ndarray  # (N,) the index of each step's episode
    bearings: np.ndarray  # (N,) rad
    beliefs: np.ndarray  # (N, Z) float64
    previous_actions: np.ndarray  # (N, A) float64


def pooled_steps(episodes: list[GoalEpisode]) -> PooledSteps:
    """The steps of ``episodes`` pooled, each tagged with its episode."""
    return PooledSteps(
        np.concatenate([steps_since_in_view(episode.in_fov, episode.new_goal) for episode in episodes]),
        np.concatenate([np.full(len(episode.bearings), index) for index, episode in enumerate(episodes)]),
        np.concatenate([episode.bearings for episode in episodes]),
        np.concatenate([episode.beliefs for episode in episodes]).astype(np.float64),
        np.concatenate([episode.previous_actions for episode in episodes]).astype(np.float64),
    )


def goal_memory_scores(episodes: list[GoalEpisode]) -> dict[str, KindScores]:
    """The probes on each kind of step of ``STEP_KINDS``, by its name."""
    steps = pooled_steps(episodes)
    scores = {}
    for name, (fewest, most) in STEP_KINDS.items():
        rows = (steps.since >= fewest) & (steps.since <= most)
        scores[name] = KindScores(
            float(rows.mean()),
            int(rows.sum()),
            probe_score(steps.beliefs, steps.bearings, steps.episode_ids, rows),
            probe_score(steps.previous_actions, steps.bearings, steps.episode_ids, rows),
        )
    return scores


def markdown_table(scores: dict[str, KindScores]) -> str:
    """The scores as a markdown table, the headline's row in bold (n/a where a half has too few steps of a kind)."""

    def cells(score: ProbeScore | None) -> str:
        return f"{score.r2:.2f} | {score.median_error:.0f}" if score is not None else "n/a | n/a"

    lines = [
        "| agent steps | share | count | belief: R² (cos, sin) | belief: median error, deg "
        "| previous action: R² | previous action: median error, deg |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, kind in scores.items():
        label = f"**{name}**" if name == HEADLINE else name
        lines.append(f"| {label} | {kind.share:.1%} | {kind.steps} | {cells(kind.belief)} | {cells(kind.previous_action)} |")
    return "\n".join(lines)


def write_whole(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` as a whole: a temporary file beside it, then renamed over it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    temporary.write_text(text)
    os.replace(temporary, path)


def model_name(model_path: Path) -> str:
    """The model's name in the results: its run folder's for a model.zip, with the stem for a checkpoint, else its stem."""
    if model_path.name == FINAL_MODEL:
        return model_path.parent.name
    if model_path.parent.name == CHECKPOINT_DIR:
        return f"{model_path.parent.parent.name}_{model_path.stem}"
    return model_path.stem


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, help="a train run folder (its model.zip) or a saved model")
    parser.add_argument("--env", default=None, help=f"a Goal task (default: the run's own, else {DEFAULT_ENV})")
    parser.add_argument("--episodes", type=int, default=60, help="episodes of the agent (at least 2: one per half)")
    parser.add_argument("--seed", type=int, default=10_000, help="reset seed of the first episode (then +1 each)")
    parser.add_argument("--deterministic", action="store_true", help="act with the filter's means and the mean action")
    parser.add_argument(
        "--out", type=Path, default=None, help="results file (default benchmarks/results/goal_memory_<name>.md)"
    )
    args = parser.parse_args()
    path = args.model / FINAL_MODEL if args.model.is_dir() else args.model
    if not path.is_file():
        raise SystemExit(f"{args.model}: no saved model ({FINAL_MODEL} of a finished run, or a model's .zip)")
    if args.episodes < 2:
        raise SystemExit("--episodes: at least 2, one for each half of the probe")
    th.set_num_threads(1)
    th.manual_seed(args.seed)
    model = DSSLAC.load(path, device="cpu")
    shape = model.policy.latent.observation_shape
    if len(shape) != 3:
        raise SystemExit(f"{path} is not a pixel agent: its observations are {shape}, the probe needs its frames")
    config = find_run_config(path)
    env_id = args.env or (config.env if config is not None else DEFAULT_ENV)
    if config is not None:
        env_kwargs: dict[str, Any] = config.env_kwargs  # the run's own frame size and action repeat
    else:
        env_kwargs = {"width": shape[2], "height": shape[1], "action_repeat": model.action_repeat}
    env = make_model_env(model, env_id, "pixels", env_kwargs=env_kwargs)
    try:
        task = getattr(env.unwrapped, "task_spec", None)
        if task is None or task.name != "Goal":
            raise SystemExit(f"{env_id} is not a Safety-Gym Goal task (PointGoal1/2, CarGoal1/2): the probe needs its goal")
        seeds = range(args.seed, args.seed + args.episodes)
        started = time.perf_counter()
        episodes = [goal_episode(model, env, seed, args.deterministic) for seed in seeds]
        scores = goal_memory_scores(episodes)
        seconds = time.perf_counter() - started
    finally:
        env.close()
    in_view = float(np.concatenate([episode.in_fov for episode in episodes]).mean())
    reward = float(np.mean([episode.reward for episode in episodes]))
    cost = float(np.mean([episode.cost for episode in episodes]))
    policy = "means (--deterministic)" if args.deterministic else "stochastic policy"
    steps = sum(len(episode.bearings) for episode in episodes)
    summary = (
        f"{path}: {args.episodes} episodes ({steps} agent steps) of its {policy} on {env_id} ({env_kwargs}), "
        f"reset seeds {seeds.start}-{seeds.stop - 1}; {cpu_model()}; {seconds:.0f} s.\n"
        f"Reward {reward:.2f} and cost {cost:.1f} per episode; the goal's centre in the field of view in {in_view:.1%} "
        "of the steps. Out of view n steps: the goal's centre last in the field of view n agent steps earlier. R² pooled "
        "over cos and sin, held out by episodes (fitted on half, scored on the other, swapped, averaged)."
    )
    table = markdown_table(scores)
    print(f"{summary}\n\n{table}")
    out = args.out or Path(__file__).resolve().parent / "results" / f"goal_memory_{model_name(path)}.md"
    command = shlex.join(["python", "benchmarks/goal_memory.py", *sys.argv[1:]])
    title = f"# Goal memory: {model_name(path)}"
    write_whole(out, f"{title}\n\n`{command}`\n\n{summary}\n\n{table}\n")
    print(f"\nwritten to {out}")


if __name__ == "__main__":
    main()
