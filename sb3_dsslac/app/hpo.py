"""
Optuna search for DS-SLAC: maximise the last evaluation's mean episode reward, with the cost budget as an Optuna
constraint (``trial.set_constraint``: mean eval cost minus budget, feasible when <= 0), multivariate TPE and
median pruning on the intermediate evaluations. Several processes on one storage share one study; on an RDB storage
a heartbeat marks the trial of a dead worker failed and the others retry it. Workers may start at the same moment on a
new storage: the ones that lose the race to create its schema or the study wait a little and load what the winner made.
"""

import importlib.util
import random
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import gymnasium as gym
import numpy as np
import optuna
import torch as th
from optuna.pruners import MedianPruner
from optuna.exceptions import DuplicatedStudyError, ExperimentalWarning, StorageInternalError
from optuna.samplers import TPESampler
from optuna.storages import JournalStorage, RDBStorage, RetryHeartbeatStaleTrialCallback, fail_stale_trials
from optuna.storages.journal import JournalFileBackend
from optuna.trial import TrialState
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError, IntegrityError, OperationalError, ProgrammingError
from stable_baselines3.common.vec_env import VecEnv

from sb3_dsslac.app.experiment import Experiment
from sb3_dsslac.common.atomic import write_atomic
from sb3_dsslac.common.env_info import action_repeat_of
from sb3_dsslac.common.envs import make_env, make_eval_env
from sb3_dsslac.common.evaluation import CostEvalCallback
from sb3_dsslac.dsslac import DSSLAC
from sb3_dsslac.presets import preset_hyperparams

COST_CONSTRAINT = "eval_cost_over_budget"
# What the losing side of workers creating one storage's schema or study at the same moment gets: a duplicate row or
# table (SQLite: "UNIQUE constraint failed: alembic_version.version_num", "table studies already exists"; PostgreSQL:
# a duplicate key or relation), a locked SQLite file, or Optuna's wrapping of them. Retried, then reported
RACE_ERRORS: tuple[type[Exception], ...] = (
    IntegrityError,
    OperationalError,
    ProgrammingError,
    StorageInternalError,
    DuplicatedStudyError,
)
StorageResult = TypeVar("StorageResult")


class StorageError(ValueError):
    """An Optuna storage that cannot be opened or written (bad URL, missing driver, server down), naming it."""


def storage_name(storage: str | optuna.storages.BaseStorage | None) -> str:
    """The storage as a user gave it, with a URL's password hidden; "in-memory storage" for None."""
    if storage is None:
        return "in-memory storage"
    if isinstance(storage, RDBStorage):
        storage = storage.url
    if not isinstance(storage, str):
        return type(storage).__name__
    if storage.endswith((".log", ".journal")):
        return f"journal file {storage}"
    try:
        return make_url(storage).render_as_string(hide_password=True)
    except ArgumentError:
        return storage


def retry_storage_race(
    action: Callable[[], StorageResult], storage: str | optuna.storages.BaseStorage | None, attempts: int = 10
) -> StorageResult:
    """
    ``action()`` (open a storage, create or load a study, write a study attribute), repeated after a random wait of up
    to ``0.2 * attempt`` seconds when it loses a race with another worker (``RACE_ERRORS``): the next attempt finds what
    the winner created. After ``attempts`` tries, or at once for any other error, a ``StorageError`` names the storage.
    """
    for attempt in range(1, attempts + 1):
        try:
            return action()
        except RACE_ERRORS as error:
            if attempt == attempts:
                raise StorageError(
                    f"Optuna storage {storage_name(storage)}: still failing after {attempts} tries "
                    f"({type(error).__name__}: {str(error).splitlines()[0]})"
                ) from error
            time.sleep(random.uniform(0.0, 0.2 * attempt))
        except (ImportError, ArgumentError, OSError) as error:
            raise StorageError(f"Cannot open the Optuna storage {storage_name(storage)}: {error}") from error
    raise AssertionError("unreachable")


def create_study(
    storage: str | optuna.storages.BaseStorage | None, study_name: str | None, load_if_exists: bool = True, **kwargs: Any
) -> optuna.Study:
    """
    ``optuna.create_study`` (its keywords), safe for workers that start together on a new storage: the schema and the
    study are created by the first, and the others load them (``retry_storage_race``). The zoo bridge's ``-optimize``
    creates its study with this too.
    """
    return retry_storage_race(
        lambda: optuna.create_study(storage=storage, study_name=study_name, load_if_exists=load_if_exists, **kwargs),
        storage,
    )


def sample_dsslac_params(trial: optuna.Trial, lagrange: str = "sgd") -> dict[str, Any]:
    """
    Sample DSSLAC keywords (rl-zoo3 style). Discounts are searched as ``1 - gamma`` on a log scale, batch sizes as
    powers of two; the derived values are stored as user attributes of the trial.

    :param trial: the Optuna trial
    :param lagrange: the multiplier rule the trials use: "pid" searches its three gains instead of the SGD step size
    :return: DSSLAC keywords
    """
    gamma = 1.0 - trial.suggest_float("one_minus_gamma", 1e-3, 5e-2, log=True)
    cost_gamma = 1.0 - trial.suggest_float("one_minus_cost_gamma", 1e-3, 2e-2, log=True)
    batch_size = 2 ** trial.suggest_int("batch_size_pow", 4, 7)
    latent_batch_size = 2 ** trial.suggest_int("latent_batch_size_pow", 3, 6)
    params = {
        "learning_rate": trial.suggest_float("learning_rate", 3e-5, 1e-3, log=True),
        "latent_learning_rate": trial.suggest_float("latent_learning_rate", 3e-5, 1e-3, log=True),
        "gamma": gamma,
        "cost_gamma": cost_gamma,
        "tau": trial.suggest_float("tau", 1e-3, 2e-2, log=True),
        "lagrange_learning_rate": trial.suggest_float("lagrange_learning_rate", 1e-5, 1e-2, log=True),
        "lagrange_init": trial.suggest_float("lagrange_init", 1e-3, 1.0, log=True),
        "n_quantiles": trial.suggest_categorical("n_quantiles", [16, 32, 64]),
        "cvar_risk_level": trial.suggest_categorical("cvar_risk_level", [0.25, 0.5, 1.0]),
        "batch_size": batch_size,
        "latent_batch_size": latent_batch_size,
        "sequence_length": trial.suggest_int("sequence_length", 4, 10),
    }
    if lagrange == "pid":
        # Gains per unit of episode cost over the budget; the defaults (0.05, 0.005, 0.02) swung the multiplier 0..4.9
        del params["lagrange_learning_rate"]
        params["pid_kp"] = trial.suggest_float("pid_kp", 1e-4, 1e-1, log=True)
        params["pid_ki"] = trial.suggest_float("pid_ki", 1e-5, 1e-2, log=True)
        params["pid_kd"] = trial.suggest_float("pid_kd", 1e-5, 1e-1, log=True)
    for name in ("gamma", "cost_gamma", "batch_size", "latent_batch_size"):
        trial.set_user_attr(name, params[name])
    return params


class TrialCostEvalCallback(CostEvalCallback):
    """
    ``CostEvalCallback`` that reports each evaluation's mean reward to the trial and stops training when the pruner
    says so. (Optuna keeps a trial's first constraint value only, so ``objective`` sets it once, at the end.)

    :param trial: the Optuna trial
    :param eval_env: the evaluation env
    :param kwargs: the keywords of ``CostEvalCallback``
    """

    def __init__(self, trial: optuna.Trial, eval_env: gym.Env | VecEnv, **kwargs: Any):
        super().__init__(eval_env, **kwargs)
        self.trial = trial
        self.eval_idx = 0
        self.is_pruned = False

    def _on_step(self) -> bool:
        if self.eval_freq <= 0 or self.n_calls % self.eval_freq != 0:
            return True
        continue_training = super()._on_step()
        self.eval_idx += 1
        self.trial.report(self.last_mean_reward, self.eval_idx)
        if self.trial.should_prune():
            self.is_pruned = True
            return False
        return continue_training


@dataclass
class TuneSpec(Experiment):
    """
    What each trial trains (an ``Experiment``, its fields first) and how it is judged.

    :param n_evaluations: evaluations per trial, evenly spaced (the pruner's steps)
    """

    eval_episodes: int = 5
    # Each trial one thread: torch's default, every core, oversubscribes the cores when several workers share a machine
    threads: int | None = 1
    n_evaluations: int = 4


def objective(trial: optuna.Trial, spec: TuneSpec) -> float:
    """Train one sampled configuration; return the last evaluation's mean reward (the constraint is set on the trial)."""
    if spec.threads is not None:
        th.set_num_threads(spec.threads)
    env = make_env(spec.env, spec.obs_type, env_kwargs=spec.env_kwargs)
    lagrange = preset_hyperparams(spec.preset, spec.hyperparams).get("lagrange", "sgd")
    hyperparams = preset_hyperparams(spec.preset, {**sample_dsslac_params(trial, lagrange), **spec.hyperparams})
    agent_steps = max(spec.sim_steps // action_repeat_of(env), 1)
    eval_env = make_eval_env(spec.env, seed=trial.number, obs_type=spec.obs_type, env_kwargs=spec.env_kwargs)
    model = DSSLAC("LatentPolicy", env, device=spec.device, **hyperparams)
    callback = TrialCostEvalCallback(
        trial,
        eval_env,
        cost_limit=model.cost_limit,
        n_eval_episodes=spec.eval_episodes,
        eval_freq=max(agent_steps // spec.n_evaluations, 1),
        deterministic=True,
        verbose=0,
    )
    try:
        model.learn(agent_steps, callback=callback)
    except (AssertionError, ValueError, RuntimeError) as error:  # diverged (NaN) or an invalid combination
        raise optuna.TrialPruned(f"training failed: {error}") from error
    finally:
        env.close()
        eval_env.close()
    if callback.evaluations_costs:
        trial.set_user_attr("eval_mean_costs", [float(np.mean(costs)) for costs in callback.evaluations_costs])
        trial.set_constraint(COST_CONSTRAINT, callback.last_mean_cost - callback.cost_limit)
    if callback.is_pruned:
        raise optuna.TrialPruned(f"pruned after evaluation {callback.eval_idx}")
    if not np.isfinite(callback.last_mean_reward):
        raise optuna.TrialPruned("no evaluation finished: raise --timesteps or --n-evaluations")
    return float(callback.last_mean_reward)


def storage_url(url: str) -> str:
    """
    An RDB URL with a driver SQLAlchemy can load: a plain ``postgresql://`` URL means psycopg2 to SQLAlchemy 2, so it
    becomes ``postgresql+psycopg://`` (psycopg 3, the optuna extra's driver) when only psycopg 3 is installed.
    """
    if url.startswith("postgresql://") and importlib.util.find_spec("psycopg2") is None:
        if importlib.util.find_spec("psycopg") is not None:
            return "postgresql+psycopg://" + url.removeprefix("postgresql://")
    return url


def make_storage(
    storage: str | None, heartbeat_interval: int = 60, grace_period: int | None = None, max_retry: int = 3
) -> RDBStorage | JournalStorage | None:
    """
    ``None`` (in memory), a journal file (``*.log`` / ``*.journal``: several processes on one machine or a shared
    file system) or an RDB URL (``sqlite:///study.db``, ``postgresql://user:password@host/db`` for several machines).

    On an RDB storage every running trial beats every ``heartbeat_interval`` seconds; a trial whose worker died (no beat
    for ``grace_period`` seconds, default twice the interval) is marked failed by the next worker that starts a trial,
    and a copy with the same parameters is queued for the workers (up to ``max_retry`` times per trial).
    """
    if storage is None:
        return None
    if storage.endswith((".log", ".journal")):
        return retry_storage_race(lambda: JournalStorage(JournalFileBackend(storage)), storage)
    # Heartbeats and their retry callback are experimental in Optuna: chosen, so not warned about on every tune
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExperimentalWarning)
        retry = RetryHeartbeatStaleTrialCallback(max_retry=max_retry)
        # Opening a new database creates its schema: several workers starting together race for it
        return retry_storage_race(
            lambda: RDBStorage(
                storage_url(storage),
                heartbeat_interval=heartbeat_interval,
                grace_period=grace_period,
                heartbeat_stale_trial_callback=retry,
            ),
            storage,
        )


def _finish_study(study: optuna.Study, objective: Any, total_trials: int, poll_seconds: float) -> None:
    """
    Run trials until ``total_trials`` of the study are finished (complete or pruned), counting the other workers'
    running trials as on their way; while those cover the rest, wait and look for dead workers' trials to retry.
    """
    while True:
        with warnings.catch_warnings():  # experimental in Optuna, as the heartbeats (see make_storage)
            warnings.simplefilter("ignore", ExperimentalWarning)
            fail_stale_trials(study)  # a no-op without heartbeats
        states = [trial.state for trial in study.get_trials(deepcopy=False)]
        finished = states.count(TrialState.COMPLETE) + states.count(TrialState.PRUNED)
        if finished >= total_trials:
            return
        if TrialState.WAITING in states or finished + states.count(TrialState.RUNNING) < total_trials:
            study.optimize(objective, n_trials=1, gc_after_trial=True)
        else:
            time.sleep(poll_seconds)


def tune(
    spec: TuneSpec,
    n_trials: int,
    storage: str | None = None,
    study_name: str = "dsslac",
    n_startup_trials: int = 5,
    sampler_seed: int | None = None,
    show_progress_bar: bool = True,
    total_trials: int | None = None,
    heartbeat_interval: int = 60,
) -> optuna.Study:
    """
    Run ``n_trials`` trials in this process on the study ``study_name`` (created or joined: ``load_if_exists``), or,
    with ``total_trials``, trials until the study has that many finished, whichever worker runs them.

    :param spec: what each trial trains
    :param n_trials: trials of this process (ignored with ``total_trials``)
    :param storage: see ``make_storage``
    :param study_name: the study's name in the storage
    :param n_startup_trials: random trials before TPE, and completed trials before the pruner prunes
    :param sampler_seed: seed of TPE (leave None when several workers share the study, or they sample alike)
    :param show_progress_bar: Optuna's progress bar over this process's trials
    :param total_trials: finished (complete or pruned) trials of the whole study to reach; a worker waits while the
        others' running trials cover the rest, and retries those of a worker that died (RDB storages, see
        ``make_storage``); workers starting at once may overshoot by one trial each
    :param heartbeat_interval: seconds between the heartbeats of a running trial on an RDB storage
    :return: the study
    """
    study = create_study(
        make_storage(storage, heartbeat_interval=heartbeat_interval),
        study_name,
        sampler=TPESampler(n_startup_trials=n_startup_trials, seed=sampler_seed, multivariate=True),
        pruner=MedianPruner(n_startup_trials=n_startup_trials, n_warmup_steps=spec.n_evaluations // 3),
        direction="maximize",
    )
    for key, value in (("env", spec.env), ("sim_steps_per_trial", spec.sim_steps)):
        retry_storage_race(lambda key=key, value=value: study.set_user_attr(key, value), storage)
    if total_trials is not None:
        _finish_study(study, lambda trial: objective(trial, spec), total_trials, poll_seconds=heartbeat_interval)
        return study
    study.optimize(
        lambda trial: objective(trial, spec), n_trials=n_trials, gc_after_trial=True, show_progress_bar=show_progress_bar
    )
    return study


def summarize_study(study: optuna.Study) -> str:
    """Trial counts and the best feasible trial (the highest reward with mean eval cost within the budget)."""
    states = [trial.state for trial in study.trials]
    counts = ", ".join(f"{state.name.lower()} {states.count(state)}" for state in optuna.trial.TrialState if state in states)
    lines = [f"study {study.study_name!r}: {len(study.trials)} trials ({counts})"]
    try:
        best = study.best_trial
    except ValueError:
        lines.append("no feasible trial yet (every finished trial's mean eval cost is over the budget)")
    else:
        over = best.constraints[COST_CONSTRAINT]
        lines.append(f"best feasible trial #{best.number}: eval reward {best.value:.3f}, cost - budget {over:.2f}")
        lines += [f"  {name}: {value}" for name, value in best.params.items()]
    return "\n".join(lines)


def write_trials(study: optuna.Study, folder: str | Path) -> Path:
    """
    ``folder/<study name>_trials.csv``: every trial of the study, one row each (``Study.trials_dataframe``), written
    whole or not at all (``common.atomic``); several workers may write it, and a reader sees one of their files whole.
    """
    path = Path(folder) / f"{study.study_name}_trials.csv"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, study.trials_dataframe().to_csv(index=False))
    return path
