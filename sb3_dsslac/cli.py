"""
The thesis's protocol from the command line: ``python -m sb3_dsslac train | plot | evaluate | tune``.

Units: ``--sim-steps`` and every ``*-every`` are simulator steps (the thesis's "environment steps"); DSSLAC counts
agent steps, ``action_repeat`` simulator steps each (2 on the Safety-Gym tasks).
"""

import argparse
import csv
import shlex
import sys
from dataclasses import asdict, dataclass, field, fields
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
import yaml
from stable_baselines3.common.callbacks import CheckpointCallback
from stable_baselines3.common.logger import CSVOutputFormat, Logger, make_output_format
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv, VecTransposeImage
from tqdm.auto import tqdm

from sb3_dsslac.dsslac import DSSLAC
from sb3_dsslac.evaluation import CostEvalCallback, EpisodeResults
from sb3_dsslac.env_info import action_repeat_of, cost_from_info, episode_length_of
from sb3_dsslac.presets import PRESETS, preset_hyperparams
from sb3_dsslac.version import __version__

CONFIG_FILE = "config.yaml"
FINAL_MODEL = "model.zip"
CHECKPOINT_DIR = "checkpoints"
CHECKPOINT_PREFIX = "dsslac"
EVAL_SEED_OFFSET = 10_000
# DSSLAC keywords that get their own flag (``--learning-rate``); any other goes through ``--hyperparams key=value``
HYPERPARAM_FLAGS: dict[str, type] = {
    "learning_rate": float,
    "latent_learning_rate": float,
    "buffer_size": int,
    "learning_starts": int,
    "latent_pretrain_steps": int,
    "batch_size": int,
    "latent_batch_size": int,
    "sequence_length": int,
    "train_freq": int,
    "gradient_steps": int,
    "gamma": float,
    "cost_gamma": float,
    "cost_limit": float,
    "lagrange_init": float,
    "lagrange_learning_rate": float,
    "n_quantiles": int,
    "cvar_risk_level": float,
}


# ----------------------------------------------------------------------------------------------------------------------
# Envs
# ----------------------------------------------------------------------------------------------------------------------


def make_env(
    env_id: str, obs_type: str | None = None, render_mode: str | None = None, env_kwargs: dict[str, Any] | None = None
) -> gym.Env:
    """
    ``gym.make`` with the Safety-Gym tasks registered and a clear error for an unknown id.

    :param env_id: a registered id (``SafetyGym/PointGoal1-v0``), or ``module:EnvId`` to import the module that registers it
    :param obs_type: passed to the env when given ("pixels" or "state" for the Safety-Gym tasks)
    :param render_mode: passed to the env when given ("rgb_array" for videos)
    :param env_kwargs: other keywords of the env
    """
    import safety_envs  # registers SafetyGym/*

    kwargs = dict(env_kwargs or {})
    if obs_type is not None:
        kwargs["obs_type"] = obs_type
    if render_mode is not None:
        kwargs["render_mode"] = render_mode
    try:
        return gym.make(env_id, **kwargs)
    except (gym.error.Error, ModuleNotFoundError) as error:
        raise ValueError(
            f"Cannot make env {env_id!r}: {str(error).rstrip('.')}. Safety-Gym tasks: {', '.join(safety_envs.env_ids())}. "
            "For your own env, register it with gymnasium.register and pass its id, or 'my_module:MyEnv-v0' "
            "so that my_module (which registers it) is imported first."
        ) from error


def make_train_env(config: "TrainConfig") -> gym.Env | VecEnv:
    """The training env: one env in this process, or ``config.n_envs`` envs in their own processes."""
    if config.n_envs == 1:
        return make_env(config.env, config.obs_type, env_kwargs=config.env_kwargs)
    return SubprocVecEnv([partial(make_env, config.env, config.obs_type, env_kwargs=config.env_kwargs)] * config.n_envs)


def make_eval_env(env_id: str, seed: int, obs_type: str | None = None, env_kwargs: dict[str, Any] | None = None) -> VecEnv:
    """A separate, seeded, Monitor-wrapped evaluation VecEnv (channel-first images, as the training env)."""
    vec_env: VecEnv = DummyVecEnv([lambda: Monitor(make_env(env_id, obs_type, env_kwargs=env_kwargs))])
    if is_image_space(vec_env.observation_space) and not is_image_space_channels_first(vec_env.observation_space):  # type: ignore[arg-type]
        vec_env = VecTransposeImage(vec_env)
    vec_env.seed(seed)
    return vec_env


# ----------------------------------------------------------------------------------------------------------------------
# Training runs
# ----------------------------------------------------------------------------------------------------------------------


@dataclass
class TrainConfig:
    """
    One training run of the thesis's protocol. Steps are simulator steps.

    :param env: env id (see ``make_env``)
    :param sim_steps: simulator steps of training
    :param seed: seed of the model and the training env (the eval env gets ``eval_seed``)
    :param preset: a name of ``sb3_dsslac.presets.PRESETS``
    :param hyperparams: DSSLAC keywords on top of the preset
    :param obs_type: "pixels" or "state" (None: the env's default)
    :param env_kwargs: other keywords of the env
    :param eval_every: simulator steps between evaluations
    :param eval_episodes: episodes per evaluation
    :param eval_deterministic: evaluate the policy's mean action (and the filter's means)
    :param eval_seed: seed of the evaluation env (None: ``seed + 10000``)
    :param checkpoint_every: simulator steps between checkpoints (model and replay buffer; only the latest is kept)
    :param n_envs: training envs, each in its own process when more than one; the updates per agent step stay the same
    :param device: "auto", "cpu" or "cuda"
    :param threads: torch CPU threads (None: torch's default; 1 is often fastest for small networks on a busy CPU)
    :param verbose: 0 quiet, 1 logs and evaluations on stdout
    :param progress_bar: show SB3's progress bar
    """

    env: str
    sim_steps: int = 1_000_000
    seed: int = 0
    preset: str = "thesis"
    hyperparams: dict[str, Any] = field(default_factory=dict)
    obs_type: str | None = None
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    eval_every: int = 25_000
    eval_episodes: int = 10
    eval_deterministic: bool = True
    eval_seed: int | None = None
    checkpoint_every: int = 100_000
    n_envs: int = 1
    device: str = "auto"
    threads: int | None = None
    verbose: int = 1
    progress_bar: bool = True

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"Unknown preset {self.preset!r}; valid presets: {sorted(PRESETS)}")
        for name in ("sim_steps", "eval_every", "eval_episodes", "checkpoint_every", "n_envs"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


@dataclass
class Checkpoint:
    """The newest complete checkpoint of a run folder: model, replay buffer, and its agent steps."""

    model: Path
    replay_buffer: Path
    timesteps: int


def default_run_dir(config: TrainConfig, root: str | Path = "runs") -> Path:
    """``runs/<env>_<seed>_<timestamp>`` with the env id's ``/`` and ``:`` replaced."""
    name = config.env.replace("/", "-").replace(":", "-")
    return Path(root) / f"{name}_{config.seed}_{datetime.now():%Y%m%d-%H%M%S}"


def load_config(run_dir: str | Path) -> TrainConfig:
    """The ``TrainConfig`` saved in ``run_dir/config.yaml``."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{run_dir} is not a run folder: it has no {CONFIG_FILE}")
    saved = yaml.safe_load(path.read_text())
    return TrainConfig(**{f.name: saved[f.name] for f in fields(TrainConfig) if f.name in saved})


def find_checkpoint(run_dir: str | Path) -> Checkpoint | None:
    """The newest checkpoint of ``run_dir`` whose model and replay buffer were both written, or None."""
    folder = Path(run_dir) / CHECKPOINT_DIR
    found = []
    for model_path in folder.glob(f"{CHECKPOINT_PREFIX}_*_steps.zip"):
        steps = model_path.stem.removeprefix(f"{CHECKPOINT_PREFIX}_").removesuffix("_steps")
        buffer_path = folder / f"{CHECKPOINT_PREFIX}_replay_buffer_{steps}_steps.pkl"
        if steps.isdigit() and buffer_path.is_file():
            found.append(Checkpoint(model_path, buffer_path, int(steps)))
    return max(found, key=lambda checkpoint: checkpoint.timesteps, default=None)


class LatestCheckpointCallback(CheckpointCallback):
    """``CheckpointCallback`` (model and replay buffer) that deletes the older checkpoints once a new one is written."""

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            super()._on_step()
            for path in Path(self.save_path).glob(f"{self.name_prefix}_*_steps.*"):
                if not path.stem.endswith(f"_{self.num_timesteps}_steps"):
                    path.unlink()
        return True


def _resumed_csv(path: Path, max_timesteps: int | None) -> CSVOutputFormat:
    """A ``progress.csv`` writer; when resuming, it keeps the earlier rows up to ``max_timesteps`` and appends."""
    old_lines = path.read_text().splitlines(keepends=True) if max_timesteps is not None and path.is_file() else []
    writer = CSVOutputFormat(str(path))
    if old_lines:
        header = old_lines[0].rstrip("\n").split(",")
        column = header.index("time/total_timesteps") if "time/total_timesteps" in header else None

        def before_checkpoint(line: str) -> bool:
            value = next(csv.reader([line]))[column] if column is not None else ""
            return value == "" or float(value) <= max_timesteps  # type: ignore[operator]

        writer.file.writelines([old_lines[0], *filter(before_checkpoint, old_lines[1:])])
        writer.file.flush()
        writer.keys = header
    return writer


def _make_logger(run_dir: Path, verbose: int, resume_from: int | None) -> Logger:
    formats = [_resumed_csv(run_dir / "progress.csv", resume_from), make_output_format("tensorboard", str(run_dir))]
    if verbose >= 1:
        formats.insert(0, make_output_format("stdout", str(run_dir)))
    return Logger(str(run_dir), formats)


def resolved_hyperparams(config: TrainConfig, env: gym.Env) -> dict[str, Any]:
    """The DSSLAC keywords of a run: preset, then the config's overrides, then the env's episode length if unset."""
    hyperparams = preset_hyperparams(config.preset, config.hyperparams)
    if hyperparams.get("episode_length") is None:
        hyperparams["episode_length"] = episode_length_of(env)
    return hyperparams


def train(config: TrainConfig, out: str | Path | None = None) -> Path:
    """
    Train one run with periodic evaluations and checkpoints; see ``docs/cli.md`` for the run folder.

    :param config: the run
    :param out: the run folder (None: ``runs/<env>_<seed>_<timestamp>``); it must not hold a run already
    :return: the run folder
    """
    run_dir = Path(out) if out is not None else default_run_dir(config)
    if config.threads is not None:
        th.set_num_threads(config.threads)
    if (run_dir / CONFIG_FILE).exists():
        raise FileExistsError(
            f"{run_dir} already holds a run: continue it with `train --resume {run_dir}` or pick another --out"
        )
    env = make_train_env(config)
    run_dir.mkdir(parents=True, exist_ok=True)
    action_repeat = action_repeat_of(env)
    hyperparams = resolved_hyperparams(config, env)
    eval_seed = config.seed + EVAL_SEED_OFFSET if config.eval_seed is None else config.eval_seed
    policy = "deterministic" if config.eval_deterministic else "stochastic"
    saved = {
        **asdict(config),
        "resolved": {
            "action_repeat": action_repeat,
            "observation_space": str(env.observation_space),
            "agent_steps": config.sim_steps // action_repeat,
            "eval_every_agent_steps": max(config.eval_every // action_repeat, 1),
            "eval_env": f"separate env, seed {eval_seed}, {policy} policy",
            "dsslac": hyperparams,
            "sb3_dsslac_version": __version__,
            "started": f"{datetime.now():%Y-%m-%d %H:%M:%S}",
            "command": shlex.join(sys.argv),
        },
    }
    (run_dir / CONFIG_FILE).write_text(yaml.safe_dump(saved, sort_keys=False))
    model = DSSLAC("LatentPolicy", env, seed=config.seed, device=config.device, verbose=config.verbose, **hyperparams)
    _learn(model, config, run_dir, eval_seed, resumed=False)
    return run_dir


def resume(run_dir: str | Path, sim_steps: int | None = None) -> Path:
    """
    Continue a run that was stopped from its newest checkpoint (model, replay buffer, Lagrange multiplier); the rows of
    ``progress.csv`` and ``evaluations.npz`` up to the checkpoint are kept, later ones are redone.

    :param run_dir: the run folder
    :param sim_steps: a new total of simulator steps (None: the run's own)
    :return: the run folder
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"No run folder {run_dir}")
    config = load_config(run_dir)
    if sim_steps is not None:
        config.sim_steps = sim_steps
    if config.threads is not None:
        th.set_num_threads(config.threads)
    checkpoint = find_checkpoint(run_dir)
    if checkpoint is None:
        raise FileNotFoundError(
            f"No checkpoint (model and replay buffer) in {run_dir / CHECKPOINT_DIR} to resume from: "
            f"the run stopped before its first checkpoint; delete the folder and start it again with `train`"
        )
    env = make_train_env(config)
    model = DSSLAC.load(checkpoint.model, env=env, device=config.device)
    model.load_replay_buffer(checkpoint.replay_buffer)
    model.verbose = config.verbose
    model.set_random_seed(config.seed + model.num_timesteps)
    eval_seed = config.seed + EVAL_SEED_OFFSET if config.eval_seed is None else config.eval_seed
    _learn(model, config, run_dir, eval_seed + model.num_timesteps, resumed=True)
    return run_dir


def _learn(model: DSSLAC, config: TrainConfig, run_dir: Path, eval_seed: int, resumed: bool) -> None:
    """Train ``model`` up to the config's steps with the run's logger, evaluations and checkpoints, then save it."""
    action_repeat = model.action_repeat
    total = config.sim_steps // action_repeat
    start = model.num_timesteps
    model.set_logger(_make_logger(run_dir, config.verbose, start if resumed else None))
    eval_env = make_eval_env(config.env, eval_seed, config.obs_type, config.env_kwargs)
    evaluation = CostEvalCallback(
        eval_env,
        cost_limit=model.cost_limit,
        n_eval_episodes=config.eval_episodes,
        eval_freq=max(config.eval_every // action_repeat // model.n_envs, 1),  # counted in env.step calls
        log_path=str(run_dir),
        best_model_save_path=str(run_dir),
        deterministic=config.eval_deterministic,
        verbose=config.verbose,
    )
    if resumed and (run_dir / "evaluations.npz").is_file():
        evaluation.restore(str(run_dir / "evaluations.npz"), start)
    checkpoints = LatestCheckpointCallback(
        save_freq=max(config.checkpoint_every // action_repeat // model.n_envs, 1),
        save_path=str(run_dir / CHECKPOINT_DIR),
        name_prefix=CHECKPOINT_PREFIX,
        save_replay_buffer=True,
    )
    # One env: the callbacks' step counters continue from the checkpoint, so evaluations stay on their grid.
    # The evaluation runs before the checkpoint of the same step, so a checkpoint never misses its evaluation.
    for callback in (evaluation, checkpoints):
        callback.n_calls = start // model.n_envs
    try:
        if total > start:
            model.learn(
                total - start,
                callback=[evaluation, checkpoints],
                reset_num_timesteps=not resumed,
                progress_bar=config.progress_bar,
            )
        model.save(run_dir / FINAL_MODEL)
    finally:
        eval_env.close()
        model.logger.close()
        if model.env is not None:
            model.env.close()


# ----------------------------------------------------------------------------------------------------------------------
# Evaluation and videos
# ----------------------------------------------------------------------------------------------------------------------


def find_run_config(model_path: Path) -> TrainConfig | None:
    """The config of the run that holds ``model_path`` (in the run folder or its checkpoints), if any."""
    for folder in (model_path.parent, model_path.parent.parent):
        if (folder / CONFIG_FILE).is_file():
            return load_config(folder)
    return None


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


def evaluate(
    model: DSSLAC,
    env_id: str,
    episodes: int = 10,
    deterministic: bool = True,
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
    :param deterministic: act with the mean action (and the filter's means)
    :param seed: seed of the first episode
    :param video: the video file (.mp4 or .gif); None writes none
    :param video_episodes: episodes recorded into the video
    :param obs_type: the observation type the model was trained on (None: the env's default)
    :param env_kwargs: other keywords of the env
    :return: per-episode rewards, costs and lengths (agent steps)
    """
    env = make_env(env_id, obs_type, render_mode="rgb_array" if video else None, env_kwargs=env_kwargs)
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


def format_episodes(results: EpisodeResults, cost_limit: float | None = None) -> str:
    """A text table of the episodes, then their mean and standard deviation."""
    lines = [f"{'episode':>7}  {'reward':>9}  {'cost':>7}  {'length':>6}"]
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


# ----------------------------------------------------------------------------------------------------------------------
# Command line
# ----------------------------------------------------------------------------------------------------------------------


def parse_hyperparams(pairs: list[str] | None) -> dict[str, Any]:
    """``["key=value", ...]`` to a dict, each value read as YAML (``policy_kwargs="{z1_dim: 16}"``)."""
    hyperparams: dict[str, Any] = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise ValueError(f"--hyperparams takes key=value pairs, got {pair!r}")
        hyperparams[key.strip()] = yaml.safe_load(value)
    return hyperparams


def _flag_hyperparams(args: argparse.Namespace) -> dict[str, Any]:
    hyperparams = {name: getattr(args, name) for name in HYPERPARAM_FLAGS if getattr(args, name) is not None}
    return {**hyperparams, **parse_hyperparams(args.hyperparams)}


def _add_model_flags(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default="thesis",
        help="thesis: Table 5.2; thesis_fast: the same with share_latent_batch and bf16; cpu: small and quick; "
        "cpu_learning: the CPU learning benchmark's",
    )
    parser.add_argument("--obs-type", choices=["pixels", "state"], help="observation type (default: the env's)")
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda")
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's; 1 is often fastest on a busy CPU)")
    group = parser.add_argument_group("hyperparameters (on top of the preset; agent steps)")
    for name, kind in HYPERPARAM_FLAGS.items():
        group.add_argument(f"--{name.replace('_', '-')}", dest=name, type=kind, metavar=kind.__name__.upper())
    group.add_argument(
        "--hyperparams", nargs="+", metavar="KEY=VALUE", help="other DSSLAC keywords as YAML: policy_kwargs='{z1_dim: 16}'"
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m sb3_dsslac", description=__doc__.strip().splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)

    train_parser = commands.add_parser("train", help="train with the thesis's evaluation protocol")
    train_parser.add_argument("--env", help="env id, e.g. SafetyGym/PointGoal1-v0")
    train_parser.add_argument("--sim-steps", type=int, help="simulator steps of training (default 1000000)")
    train_parser.add_argument("--seed", type=int, default=0)
    train_parser.add_argument("--out", help="run folder (default runs/<env>_<seed>_<timestamp>)")
    train_parser.add_argument("--resume", metavar="RUN_DIR", help="continue this run from its last checkpoint")
    train_parser.add_argument("--eval-every", type=int, default=25_000, help="simulator steps between evaluations")
    train_parser.add_argument("--eval-episodes", type=int, default=10)
    train_parser.add_argument("--eval-seed", type=int, help="seed of the evaluation env (default seed + 10000)")
    train_parser.add_argument("--stochastic-eval", action="store_true", help="evaluate with sampled actions")
    train_parser.add_argument("--checkpoint-every", type=int, default=100_000, help="simulator steps between checkpoints")
    train_parser.add_argument("--n-envs", type=int, default=1, help="training envs, each in its own process")
    train_parser.add_argument("--quiet", action="store_true", help="no logs on stdout")
    train_parser.add_argument("--no-progress-bar", action="store_true")
    _add_model_flags(train_parser)

    plot_parser = commands.add_parser("plot", help="learning curves and the normalised score table of runs")
    plot_parser.add_argument("runs", nargs="+", metavar="RUN_DIR")
    plot_parser.add_argument("--out", default=".", help="folder of curves.png, scores.csv and scores.md")

    eval_parser = commands.add_parser("evaluate", help="per-episode reward and cost of a saved model, and a video")
    eval_parser.add_argument("model", help="a saved model (.zip)")
    eval_parser.add_argument("--env", help="env id (default: the model's run's)")
    eval_parser.add_argument("--episodes", type=int, default=10)
    eval_parser.add_argument("--seed", type=int, default=0)
    eval_parser.add_argument("--stochastic", action="store_true", help="sample actions instead of the mean")
    eval_parser.add_argument("--video", help="video file (.mp4 or .gif)")
    eval_parser.add_argument("--video-episodes", type=int, default=1, help="episodes recorded into the video")
    eval_parser.add_argument("--obs-type", choices=["pixels", "state"])
    eval_parser.add_argument("--device", default="auto")

    tune_parser = commands.add_parser("tune", help="Optuna search, maximising eval reward under the cost budget")
    tune_parser.add_argument("--env", required=True)
    tune_parser.add_argument("--timesteps", type=int, required=True, help="simulator steps per trial")
    tune_parser.add_argument("--n-trials", type=int, default=10, help="trials run by this process")
    tune_parser.add_argument("--storage", help="sqlite:///f.db, postgresql://..., or a journal file (*.log, *.journal)")
    tune_parser.add_argument("--study-name", default="dsslac")
    tune_parser.add_argument("--n-evaluations", type=int, default=4, help="evaluations per trial (pruning points)")
    tune_parser.add_argument("--eval-episodes", type=int, default=5)
    tune_parser.add_argument("--n-startup-trials", type=int, default=5, help="random trials before TPE and pruning")
    tune_parser.add_argument("--sampler-seed", type=int, help="seed of TPE (leave unset with several workers)")
    tune_parser.add_argument("--out", help="folder for the trials' CSV")
    _add_model_flags(tune_parser)
    return parser


def _train_command(args: argparse.Namespace) -> None:
    if args.resume is not None:
        run_dir = resume(args.resume, sim_steps=args.sim_steps)
    else:
        if args.env is None:
            raise ValueError("train needs --env (or --resume RUN_DIR)")
        config = TrainConfig(
            env=args.env,
            sim_steps=args.sim_steps or 1_000_000,
            seed=args.seed,
            preset=args.preset,
            hyperparams=_flag_hyperparams(args),
            obs_type=args.obs_type,
            eval_every=args.eval_every,
            eval_episodes=args.eval_episodes,
            eval_deterministic=not args.stochastic_eval,
            eval_seed=args.eval_seed,
            checkpoint_every=args.checkpoint_every,
            n_envs=args.n_envs,
            device=args.device,
            threads=args.threads,
            verbose=0 if args.quiet else 1,
            progress_bar=not args.no_progress_bar,
        )
        run_dir = train(config, args.out)
    print(f"run folder: {run_dir}")


def _plot_command(args: argparse.Namespace) -> None:
    from sb3_dsslac.plotting import report

    print(report(args.runs, args.out))


def _evaluate_command(args: argparse.Namespace) -> None:
    if not Path(args.model).is_file():
        raise FileNotFoundError(f"No model file {args.model}")
    run_config = find_run_config(Path(args.model))
    if args.env is None and run_config is None:
        raise ValueError(f"{args.model} is not in a run folder: pass the env id (--env)")
    env_id = args.env or run_config.env  # type: ignore[union-attr]
    same_env = run_config is not None and run_config.env == env_id
    model = DSSLAC.load(args.model, device=args.device)
    results = evaluate(
        model,
        env_id=env_id,
        episodes=args.episodes,
        deterministic=not args.stochastic,
        seed=args.seed,
        video=args.video,
        video_episodes=args.video_episodes,
        obs_type=args.obs_type or (run_config.obs_type if same_env else None),  # type: ignore[union-attr]
        env_kwargs=run_config.env_kwargs if same_env else None,  # type: ignore[union-attr]
    )
    print(format_episodes(results, model.cost_limit))
    if args.video:
        print(f"video: {args.video}")


def _tune_command(args: argparse.Namespace) -> None:
    from sb3_dsslac.hpo import TuneSpec, summarize_study, tune

    spec = TuneSpec(
        env=args.env,
        sim_steps=args.timesteps,
        preset=args.preset,
        hyperparams=_flag_hyperparams(args),
        obs_type=args.obs_type,
        n_evaluations=args.n_evaluations,
        eval_episodes=args.eval_episodes,
        device=args.device,
        threads=args.threads,
    )
    study = tune(
        spec,
        n_trials=args.n_trials,
        storage=args.storage,
        study_name=args.study_name,
        n_startup_trials=args.n_startup_trials,
        sampler_seed=args.sampler_seed,
    )
    print(summarize_study(study))
    if args.out is not None:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        path = Path(args.out) / f"{args.study_name}_trials.csv"
        study.trials_dataframe().to_csv(path, index=False)
        print(f"trials: {path}")


def main(argv: list[str] | None = None) -> int:
    """Run a command; errors of bad input end with a one-line message and exit status 2."""
    args = build_parser().parse_args(argv)
    command = {"train": _train_command, "plot": _plot_command, "evaluate": _evaluate_command, "tune": _tune_command}
    try:
        command[args.command](args)
    except (ValueError, FileNotFoundError, FileExistsError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0
