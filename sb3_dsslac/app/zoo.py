"""
rl-zoo3's own scripts with DS-SLAC registered: ``python -m sb3_dsslac.zoo train|enjoy [rl-zoo3 flags]``.

``train`` is ``python -m rl_zoo3.train`` and ``enjoy`` is ``python -m rl_zoo3.enjoy``, every flag unchanged, with
``dsslac`` added to the zoo's algorithms and to its ``-optimize`` samplers, the Safety-Gym ids registered (so
``--gym-packages safety_envs`` is optional) and the zoo's evaluations measuring the episode cost: they log
``eval/mean_cost`` and ``eval/std_cost``, write ``costs`` into ``evaluations.npz``, keep the best model feasibility
first, and under ``-optimize`` set the cost constraint of each trial; ``-optimize`` workers may start together on a new
storage. Bad input stops before the zoo makes its log folder, envs or model: the env id, and for ``dsslac`` the
keywords of the ``-conf`` file and ``--hyperparams``, ``--env-kwargs`` and ``--device`` (``sb3_dsslac.common.validation``),
and for ``enjoy`` a ``dsslac`` model that is not in its folder, end with one ``error:`` line and exit status 2. Needs
``pip install "sb3_dsslac[zoo]"``, which also installs ``requests``: rl-zoo3 2.9.2's ``enjoy`` imports it (through its
hub module) without declaring it.
"""

import argparse
import contextlib
import functools
import importlib
import io
import sys
import types
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import optuna
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.vec_env import VecEnv

from sb3_dsslac.app.hpo import COST_CONSTRAINT, TrialCostEvalCallback, create_study, sample_dsslac_params
from sb3_dsslac.common.evaluation import CostEvalCallback
from sb3_dsslac.common.validation import InputError, check_algorithm, check_device, check_env_id, check_env_kwargs, error_line
from sb3_dsslac.dsslac import DSSLAC

ALGO = "dsslac"


class ZooEvalCallback(CostEvalCallback):
    """
    The zoo's ``EvalCallback`` with the episode cost (see ``CostEvalCallback``), its budget read from the model; the
    zoo's other algorithms, which have no budget, get SB3's plain evaluation.

    Takes the keywords of ``EvalCallback``, as the zoo passes them.
    """

    def _init_callback(self) -> None:
        super()._init_callback()
        self.cost_limit = getattr(self.model, "cost_limit", self.cost_limit)

    def _on_step(self) -> bool:
        if not hasattr(self.model, "cost_limit"):
            return EvalCallback._on_step(self)
        return super()._on_step()


class ZooTrialEvalCallback(TrialCostEvalCallback):
    """
    The zoo's ``TrialEvalCallback`` (same arguments) with the episode cost: reports the mean reward to the trial,
    prunes, and at the end sets the trial's constraint (mean eval cost minus budget, feasible when <= 0).

    :param eval_env: the evaluation env
    :param trial: the Optuna trial
    :param kwargs: the keywords of ``EvalCallback``
    """

    def __init__(self, eval_env: gym.Env | VecEnv, trial: optuna.Trial, **kwargs: Any):
        super().__init__(trial, eval_env, **kwargs)

    def _init_callback(self) -> None:
        super()._init_callback()
        self.cost_limit = getattr(self.model, "cost_limit", self.cost_limit)

    def _on_training_end(self) -> None:
        if self.evaluations_costs:
            self.trial.set_constraint(COST_CONSTRAINT, self.last_mean_cost - self.cost_limit)


def sample_zoo_params(trial: optuna.Trial, n_actions: int, n_envs: int, additional_args: dict[str, Any]) -> dict[str, Any]:
    """The zoo's sampler signature around ``sb3_dsslac.app.hpo.sample_dsslac_params``: DSSLAC keywords for one trial."""
    return sample_dsslac_params(trial)


def convert_zoo_params(params: dict[str, Any]) -> dict[str, Any]:
    """A finished trial's raw parameters back to DSSLAC keywords (the zoo's ``--trial-id``)."""
    return sample_dsslac_params(optuna.trial.FixedTrial(params), lagrange="pid" if "pid_kp" in params else "sgd")


class _RaceSafeOptuna(types.ModuleType):
    """Optuna as ``rl_zoo3.exp_manager`` sees it: every name Optuna's, but ``create_study`` survives workers that start
    together on a new storage (``sb3_dsslac.app.hpo.create_study``)."""

    create_study = staticmethod(create_study)

    def __getattr__(self, name: str) -> Any:
        return getattr(optuna, name)


def check_experiment(manager: Any, hyperparams: dict[str, Any]) -> None:
    """
    Check what a zoo experiment with DS-SLAC was given, before the zoo makes its log folder, envs or model: its device,
    env keywords, and the DSSLAC keywords of the ``-conf`` file and ``--hyperparams`` as the zoo preprocessed them.

    :param manager: the zoo's ``ExperimentManager``
    :param hyperparams: the keywords the zoo will pass to ``DSSLAC`` (``policy`` among them)
    :raises InputError: naming the flag (or the ``-conf`` file) at fault
    """
    check_device(manager.device)
    env_kwargs = manager.env_kwargs or {}
    check_env_kwargs(check_env_id(manager.env_name.gym_id), env_kwargs, {name: f"--env-kwargs {name}" for name in env_kwargs})
    keywords = dict(hyperparams)
    policy = keywords.pop("policy", "LatentPolicy")
    custom = manager.custom_hyperparams or {}
    sources = {name: f"--hyperparams {name}" if name in custom else f"-conf {manager.config} ({name})" for name in keywords}
    set_by_zoo = {"seed": "--seed", "verbose": "--verbose", "device": "--device", "tensorboard_log": "--tensorboard-log"}
    check_algorithm(DSSLAC, policy, keywords, sources, set_by_zoo)


def _checked(preprocess: Callable[..., Any]) -> Callable[..., Any]:
    """The zoo's ``ExperimentManager._preprocess_hyperparams``, then ``check_experiment`` for DS-SLAC."""

    @functools.wraps(preprocess)
    def preprocess_and_check(manager: Any, hyperparams: dict[str, Any]) -> Any:
        processed = preprocess(manager, hyperparams)
        if manager.algo == ALGO:
            check_experiment(manager, processed[0])
        return processed

    preprocess_and_check.checks_dsslac = True  # type: ignore[attr-defined]
    return preprocess_and_check


def _check_env_flags(argv: list[str]) -> None:
    """The zoo's ``--gym-packages`` import and its ``--env`` is registered (the zoo itself raises with a traceback)."""
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--env")
    parser.add_argument("--gym-packages", nargs="+", default=[])
    known, _ = parser.parse_known_args(argv)
    for module in known.gym_packages:
        try:
            importlib.import_module(module)
        except ImportError as error:
            raise InputError(f"--gym-packages {module}: cannot import it ({error})") from None
    if known.env is not None:
        check_env_id(known.env)


def _check_enjoy_model(argv: list[str]) -> None:
    """
    For ``dsslac``, the model ``enjoy`` would load is there, found by the zoo's own ``get_model_path`` (the zoo asserts
    with a traceback, and for its default folder tries the Hugging Face hub, which holds no DS-SLAC agent).
    """
    from huggingface_sb3 import EnvironmentName
    from rl_zoo3.utils import get_model_path

    # The flags of rl_zoo3.enjoy that name the model, with its defaults
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--algo", default="ppo")
    parser.add_argument("--env", default="CartPole-v1")
    parser.add_argument("-f", "--folder", default="rl-trained-agents")
    parser.add_argument("--exp-id", type=int, default=0)
    parser.add_argument("--load-best", action="store_true")
    parser.add_argument("--load-checkpoint", type=int)
    parser.add_argument("--load-last-checkpoint", action="store_true")
    known, _ = parser.parse_known_args(argv)
    if known.algo != ALGO:
        return
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # the zoo prints the experiment it picks; enjoy will again
            get_model_path(
                known.exp_id,
                known.folder,
                known.algo,
                EnvironmentName(known.env),
                known.load_best,
                known.load_checkpoint,
                known.load_last_checkpoint,
            )
    except (AssertionError, ValueError) as error:
        raise InputError(
            f"no {ALGO} model to enjoy ({error}); train one with python -m sb3_dsslac.zoo train --algo {ALGO} "
            f"--env {known.env} -f {known.folder}"
        ) from None


def register() -> None:
    """Add DS-SLAC to rl-zoo3 (algorithm, sampler, converter) and make the zoo's evaluations measure the cost."""
    import rl_zoo3.exp_manager
    import rl_zoo3.hyperparams_opt
    import rl_zoo3.utils

    import safety_envs  # noqa: F401 (registers SafetyGym/*)

    # rl_zoo3, rl_zoo3.train, rl_zoo3.enjoy and rl_zoo3.exp_manager all hold this one dict
    rl_zoo3.utils.ALGOS[ALGO] = DSSLAC
    rl_zoo3.hyperparams_opt.HYPERPARAMS_SAMPLER[ALGO] = sample_zoo_params
    rl_zoo3.hyperparams_opt.HYPERPARAMS_CONVERTER[ALGO] = convert_zoo_params
    rl_zoo3.exp_manager.EvalCallback = ZooEvalCallback
    rl_zoo3.exp_manager.TrialEvalCallback = ZooTrialEvalCallback
    rl_zoo3.exp_manager.optuna = _RaceSafeOptuna("optuna")
    manager = rl_zoo3.exp_manager.ExperimentManager
    if not getattr(manager._preprocess_hyperparams, "checks_dsslac", False):
        manager._preprocess_hyperparams = _checked(manager._preprocess_hyperparams)


def main(argv: list[str] | None = None) -> int:
    """``train`` or ``enjoy`` followed by rl-zoo3's flags; bad input ends with one ``error:`` line and status 2."""
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in ("train", "enjoy"):
        sys.exit("usage: python -m sb3_dsslac.zoo train|enjoy [rl-zoo3 flags] (see python -m rl_zoo3.train --help)")
    register()
    sys.argv = [f"{sys.argv[0]} {argv[0]}", *argv[1:]]
    try:
        _check_env_flags(argv[1:])
        if argv[0] == "enjoy":
            _check_enjoy_model(argv[1:])
        # Only the subcommand's module: rl_zoo3.enjoy loads the zoo's Hugging Face hub code, which training never needs
        if argv[0] == "train":
            from rl_zoo3.train import train

            train()
        else:
            from rl_zoo3.enjoy import enjoy

            enjoy()
    except InputError as error:
        print(error_line(error), file=sys.stderr)
        return 2
    return 0
