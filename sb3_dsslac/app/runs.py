"""
Training runs of the thesis's protocol: the run config, the run folder (``config.yaml``, logs, evaluations,
checkpoints), training and resuming. Steps of a ``TrainConfig`` are simulator steps; DSSLAC counts agent steps.
"""

import contextlib
import csv
import errno
import json
import re
import shlex
import shutil
import sys
from dataclasses import asdict, dataclass, fields
from datetime import datetime
from pathlib import Path
from typing import Any

import gymnasium as gym
import torch as th
import yaml
from stable_baselines3.common.logger import CSVOutputFormat, Logger, filter_excluded_keys, make_output_format

from sb3_dsslac.app.checkpoints import (
    CHECKPOINT_DIR,
    LatestCheckpointCallback,
    find_checkpoint,
    load_newest_checkpoint,
)
from sb3_dsslac.common.atomic import atomic_file, remove_partial_files, write_atomic
from sb3_dsslac.common.env_info import action_repeat_of, episode_length_of
from sb3_dsslac.common.envs import make_eval_env, make_train_env
from sb3_dsslac.common.evaluation import CostEvalCallback, eval_policy_name
from sb3_dsslac.app.experiment import Experiment
from sb3_dsslac.dsslac import DSSLAC
from sb3_dsslac.presets import preset_hyperparams
from sb3_dsslac.version import __version__

CONFIG_FILE = "config.yaml"
TIME_ACCOUNT_FILE = "time_account.json"
FINAL_MODEL = "model.zip"
PROGRESS_FILE = "progress.csv"
EVAL_SEED_OFFSET = 10_000
# The errors of a full disk (or quota) and of a folder the run may not write, which stop a run with one error line
UNWRITABLE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS})


class _HyperparamLoader(yaml.SafeLoader):
    """YAML 1.1 reads ``1e-6`` (no dot) as a string; this loader reads it, as YAML 1.2 and Python do, as a float."""


_HyperparamLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


@dataclass
class TrainConfig(Experiment):
    """
    One training run of the thesis's protocol: an ``Experiment`` (its fields first) with its seed, evaluations and
    checkpoints. Steps are simulator steps.

    :param seed: seed of the model and the training env (the eval env gets ``eval_seed``)
    :param eval_every: simulator steps between evaluations
    :param eval_deterministic: evaluate the policy's mean action and the filter's means; False (the thesis's protocol)
        samples both
    :param eval_seed: seed of the evaluation env (None: ``seed + 10000``)
    :param checkpoint_every: simulator steps between checkpoints (model and replay buffer; only the latest is kept)
    :param n_envs: training envs, each in its own process when more than one; the updates per agent step stay the same
    :param verbose: 0 quiet, 1 logs and evaluations on stdout
    :param progress_bar: show SB3's progress bar
    """

    seed: int = 0
    eval_every: int = 25_000
    eval_deterministic: bool = False
    eval_seed: int | None = None
    checkpoint_every: int = 100_000
    n_envs: int = 1
    verbose: int = 1
    progress_bar: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("eval_every", "checkpoint_every", "n_envs"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")


class RunStoppedError(RuntimeError):
    """A run stopped because it could not write its folder (a full disk, no permission); the message says what to do."""


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
    # Runs written before the field existed evaluated deterministically, the default of the time
    saved.setdefault("eval_deterministic", True)
    return TrainConfig(**{f.name: saved[f.name] for f in fields(TrainConfig) if f.name in saved})


class ProgressCSV(CSVOutputFormat):
    """
    SB3's CSV writer of ``progress.csv``, its rewrites atomic (``common.atomic``): the one a new column makes (SB3
    rewrites the file in place, so a kill then lost every row) and the one of a resume. Rows are appended.

    :param path: the file
    :param resumed_from: the agent steps of the checkpoint a resumed run starts from, whose rows up to them are kept
        (None: a new run, an empty file)
    """

    def __init__(self, path: Path, resumed_from: int | None):
        lines = _rows_up_to(path, resumed_from) if resumed_from is not None and path.is_file() else []
        write_atomic(path, "".join(lines))
        self.path = path
        self.file = path.open("a+")
        self.keys = lines[0].rstrip("\n").split(",") if lines else []
        self.separator = ","
        self.quotechar = '"'

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        new_keys = filter_excluded_keys(key_values, key_excluded, "csv").keys() - set(self.keys)
        if new_keys:
            self._add_columns(sorted(new_keys))
        super().write(key_values, key_excluded, step)

    def _add_columns(self, names: list[str]) -> None:
        """Rewrite the file whole with ``names`` added to the header and empty values for them in the earlier rows."""
        self.file.seek(0)
        lines = self.file.readlines()
        header = ",".join([*self.keys, *names]) + "\n"
        write_atomic(self.path, header + "".join(line.rstrip("\n") + "," * len(names) + "\n" for line in lines[1:]))
        self.file.close()
        self.file = self.path.open("a+")
        self.keys.extend(names)


def _rows_up_to(path: Path, max_timesteps: int) -> list[str]:
    """The header and the rows of ``path`` logged at or before ``max_timesteps`` (or without a step); a last row cut
    short by a kill is dropped."""
    lines = path.read_text().splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines.pop()
    if not lines:
        return []
    header = lines[0].rstrip("\n").split(",")
    column = header.index("time/total_timesteps") if "time/total_timesteps" in header else None

    def before_checkpoint(line: str) -> bool:
        value = next(csv.reader([line]))[column] if column is not None else ""
        return value == "" or float(value) <= max_timesteps

    return [lines[0], *filter(before_checkpoint, lines[1:])]


def _make_logger(run_dir: Path, verbose: int, resume_from: int | None) -> Logger:
    formats = [ProgressCSV(run_dir / PROGRESS_FILE, resume_from), make_output_format("tensorboard", str(run_dir))]
    if verbose >= 1:
        formats.insert(0, make_output_format("stdout", str(run_dir)))
    return Logger(str(run_dir), formats)


def parse_hyperparams(pairs: list[str] | None, flag: str = "--hyperparams") -> dict[str, Any]:
    """
    ``["key=value", ...]`` to a dict, each value read as YAML (``policy_kwargs="{z1_dim: 16}"``; ``1e-6`` is a float).

    :param pairs: the pairs as given on the command line
    :param flag: the flag that took them, named in the error for a malformed pair
    """
    hyperparams: dict[str, Any] = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"{flag} takes key=value pairs, got {pair!r}")
        try:
            hyperparams[key.strip()] = yaml.load(value, Loader=_HyperparamLoader)
        except yaml.YAMLError as error:
            mark = getattr(error, "problem_mark", None)
            where = f" at character {mark.column + 1}" if mark is not None else ""
            problem = getattr(error, "problem", None) or "malformed"
            raise ValueError(f"{flag} {key.strip()}: {value!r} is not valid YAML ({problem}{where})") from None
    return hyperparams


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
    if (run_dir / CONFIG_FILE).exists() and find_checkpoint(run_dir) is not None:
        raise FileExistsError(
            f"{run_dir} already holds a run: continue it with `train --resume {run_dir}` or pick another --out"
        )
    if (run_dir / CONFIG_FILE).exists():
        raise FileExistsError(
            f"{run_dir} already holds a run with no checkpoint to resume from (it stopped, or is still running, before "
            "its first): delete the folder to start it again, or pick another --out"
        )
    env = make_train_env(config.env, config.n_envs, config.obs_type, config.env_kwargs)
    existing = set(run_dir.iterdir()) if run_dir.is_dir() else None
    run_dir.mkdir(parents=True, exist_ok=True)
    action_repeat = action_repeat_of(env)
    hyperparams = resolved_hyperparams(config, env)
    eval_seed = config.seed + EVAL_SEED_OFFSET if config.eval_seed is None else config.eval_seed
    policy = eval_policy_name(config.eval_deterministic)
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
    model = None
    try:
        write_atomic(run_dir / CONFIG_FILE, yaml.safe_dump(saved, sort_keys=False))
        model = DSSLAC("LatentPolicy", env, seed=config.seed, device=config.device, verbose=config.verbose, **hyperparams)
        _learn(model, config, run_dir, eval_seed, resumed=False)
    except BaseException:
        if model is None:
            env.close()
        if not _holds_results(run_dir):  # a failed start: nothing may block the corrected command
            _remove_new_entries(run_dir, existing)
        raise
    return run_dir


def _holds_results(run_dir: Path) -> bool:
    """Whether a run folder holds anything a run writes once it is going: log rows, evaluations, checkpoints, models."""
    progress = run_dir / PROGRESS_FILE
    logged = progress.is_file() and len(progress.read_text().splitlines()) > 1
    saved = any(run_dir.glob("*.zip")) or any((run_dir / CHECKPOINT_DIR).glob("*"))
    return logged or saved or (run_dir / "evaluations.npz").is_file()


def _remove_new_entries(run_dir: Path, existing: set[Path] | None) -> None:
    """Remove ``run_dir`` if it did not exist before (``existing`` None), else only what was added since."""
    if existing is None:
        shutil.rmtree(run_dir, ignore_errors=True)
        return
    for path in set(run_dir.iterdir()) - existing:
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def resume(run_dir: str | Path, sim_steps: int | None = None) -> Path:
    """
    Continue a run that was stopped from its newest complete checkpoint that loads (model, replay buffer, Lagrange
    multiplier; ``load_newest_checkpoint``); the rows of ``progress.csv`` and ``evaluations.npz`` up to the checkpoint
    are kept, later ones are redone. What writers killed with the run left half-written is removed.

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
    for folder in (run_dir, run_dir / CHECKPOINT_DIR):
        remove_partial_files(folder)
    env = make_train_env(config.env, config.n_envs, config.obs_type, config.env_kwargs)
    try:
        model = load_newest_checkpoint(run_dir, env, config.device)
    except BaseException:
        env.close()
        raise
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
        save_freq=max(config.checkpoint_every // action_repeat // model.n_envs, 1), folder=run_dir / CHECKPOINT_DIR
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
        with atomic_file(run_dir / FINAL_MODEL) as file:
            model.save(file)
        write_time_account(model, run_dir)
    except BaseException as error:
        with contextlib.suppress(OSError):  # the account of a stopped run where the disk takes it; the first error counts
            write_time_account(model, run_dir)
        if isinstance(error, OSError) and error.errno in UNWRITABLE_ERRNOS:
            raise RunStoppedError(_stopped_message(error, model, run_dir)) from error
        raise
    finally:
        if config.verbose >= 1:
            print(f"time account: {model.time_account.format()}")
        eval_env.close()
        model.logger.close()
        if model.env is not None:
            model.env.close()


def _stopped_message(error: OSError, model: DSSLAC, run_dir: Path) -> str:
    """What a run that could not write its folder says: the file, the reason, and how to go on."""
    where = error.filename or run_dir
    checkpoint = find_checkpoint(run_dir)
    if checkpoint is None:
        advice = (
            "it had no checkpoint yet: free space (or make the folder writable) and start it again with `train`, "
            "into another --out or after deleting this one"
        )
    else:
        advice = (
            f"its checkpoint at {checkpoint.timesteps} agent steps is complete: free space (or make the folder writable) "
            f"and continue it with `train --resume {run_dir}`"
        )
    return f"cannot write {where}: {error.strerror}; the run stopped at {model.num_timesteps} agent steps, and {advice}"


def write_time_account(model: DSSLAC, run_dir: Path) -> None:
    """``run_dir/time_account.json``: the run's wall seconds by activity, its wall and its process's CPU seconds (ms)."""
    summary = {name: round(seconds, 3) for name, seconds in model.time_account.summary().items()}
    write_atomic(run_dir / TIME_ACCOUNT_FILE, json.dumps(summary, indent=1) + "\n")


def read_time_account(run_dir: str | Path) -> dict[str, float] | None:
    """The time account a run wrote when it stopped or finished (``write_time_account``), or None."""
    path = Path(run_dir) / TIME_ACCOUNT_FILE
    return json.loads(path.read_text()) if path.is_file() else None


def find_run_config(model_path: Path) -> TrainConfig | None:
    """The config of the run that holds ``model_path`` (in the run folder or its checkpoints), if any."""
    for folder in (model_path.parent, model_path.parent.parent):
        if (folder / CONFIG_FILE).is_file():
            return load_config(folder)
    return None
