"""
Checks of what a user asks for, made before any env, model or run folder is built, so that bad input ends in one line
naming the flag or keyword at fault instead of a traceback minutes later: keyword values against the annotations and
ranges of the function that takes them (``DSSLAC.__init__`` calls ``check_arguments`` itself), unknown keywords with
the valid names, env ids and env keywords against the env's constructor, devices, saved models and the command line's
counts and seeds.
"""

import argparse
import collections.abc
import difflib
import inspect
import math
import numbers
import re
import types
import typing
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import gymnasium as gym
from gymnasium import spaces
import numpy as np
import torch as th
from stable_baselines3.common.preprocessing import is_image_space, is_image_space_channels_first

from sb3_dsslac.common.env_info import cost_from_info
from sb3_dsslac.common.envs import make_env
from sb3_dsslac.common.lagrange import LAGRANGE_RULES
from sb3_dsslac.common.policies import LATENT_MODELS

# Seeds the commands take: numpy's and Gymnasium's seeding wants [0, 2**32 - 1]; the evaluation env adds 10_000 and
# the agent steps done to a run's seed, so the commands keep seeds below 2**31
MAX_SEED = 2**31 - 1
# Keywords of ``gymnasium.make`` itself, valid for every env id
GYM_MAKE_KEYWORDS = ("max_episode_steps", "disable_env_checker")


class InputError(ValueError):
    """Bad input, its message naming the flag or keyword it came from; the command line prints it as one line."""


def error_line(error: Exception) -> str:
    """The one line a command prints for ``error``: ``error: <message>``, its whitespace collapsed and the "Error: "
    that some of SB3's messages start with dropped."""
    return f"error: {' '.join(str(error).split()).removeprefix('Error: ')}"


class Check(NamedTuple):
    """A condition on a keyword's value beyond its type, and the words the error message gives it."""

    holds: Callable[[Any], bool]
    text: str


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def _number_text(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


def _numbers(low: float, high: float = math.inf, low_open: bool = False, high_open: bool = False) -> Check:
    """Numbers (or each number of a list) in the interval; other values (schedules, words) are left to the type check."""

    def within(value: float) -> bool:
        above = value > low if low_open else value >= low
        below = value < high if high_open else value <= high
        return not math.isnan(value) and above and below

    def holds(value: Any) -> bool:
        values = value if isinstance(value, (list, tuple)) else [value]
        return all(within(float(item)) for item in values if _is_number(item))

    if high == math.inf:
        text = f"{'>' if low_open else '>='} {_number_text(low)}"
    else:
        text = f"in {'(' if low_open else '['}{_number_text(low)}, {_number_text(high)}{')' if high_open else ']'}"
    return Check(holds, text)


def _words(*words: str) -> Check:
    return Check(lambda value: not isinstance(value, str) or value in words, " or ".join(map(repr, words)))


def _entropy_coefficient(value: Any) -> bool:
    if not isinstance(value, str):
        return not _is_number(value) or value > 0
    prefix, _, initial = value.partition("_")
    try:
        return prefix == "auto" and (not initial or float(initial) > 0)
    except ValueError:
        return False


def _train_frequency(value: Any) -> bool:
    if isinstance(value, tuple):
        return len(value) == 2 and _is_number(value[0]) and value[0] >= 1 and value[1] in ("step", "episode")
    return not _is_number(value) or value >= 1


_POSITIVE = _numbers(0, low_open=True)
_NON_NEGATIVE = _numbers(0)
_AT_LEAST_ONE = _numbers(1)

# Ranges of the keywords of DSSLAC and LatentPolicy that neither checks itself before training (SB3 leaves most to the
# first update); DSSLAC checks cost_target and actor_critic_transitions against the others at construction
RANGES: dict[str, Check] = {
    "learning_rate": _POSITIVE,
    "latent_learning_rate": _POSITIVE,
    "buffer_size": _AT_LEAST_ONE,
    "learning_starts": _NON_NEGATIVE,
    "latent_pretrain_steps": _NON_NEGATIVE,
    "batch_size": _AT_LEAST_ONE,
    "latent_batch_size": _AT_LEAST_ONE,
    "sequence_length": _AT_LEAST_ONE,
    "burn_in": _NON_NEGATIVE,
    "belief_refresh_interval": _NON_NEGATIVE,
    "tau": _numbers(0, 1, low_open=True),
    "gamma": _numbers(0, 1),
    "cost_gamma": _numbers(0, 1, high_open=True),
    "train_freq": Check(_train_frequency, ">= 1, or (n >= 1, 'step' or 'episode')"),
    "gradient_steps": _numbers(-1),
    "ent_coef": Check(_entropy_coefficient, "> 0, or 'auto' or 'auto_<initial value > 0>'"),
    "target_entropy": _words("auto"),
    "cost_limit": _NON_NEGATIVE,
    "episode_length": _AT_LEAST_ONE,
    "lagrange_init": _POSITIVE,
    "lagrange_learning_rate": _NON_NEGATIVE,
    "pid_kp": _NON_NEGATIVE,
    "pid_ki": _NON_NEGATIVE,
    "pid_kd": _NON_NEGATIVE,
    "pid_cost_ema": _numbers(0, 1, high_open=True),
    "lagrange": _words(*LAGRANGE_RULES),
    "lr_decay_milestone": _NON_NEGATIVE,
    "lr_decay_factor": _POSITIVE,
    "cvar_risk_level": _numbers(0, 1, low_open=True),
    "cost_critic": _words("iqn", "mean"),
    "n_quantiles": _AT_LEAST_ONE,
    "max_grad_norm": _POSITIVE,
    "actor_max_grad_norm": _POSITIVE,
    "image_noise": _POSITIVE,
    "cost_loss_weight": _NON_NEGATIVE,
    "cost_positive_weight": _NON_NEGATIVE,
    "bf16": _words("auto"),
    "stats_window_size": _AT_LEAST_ONE,
    "seed": _numbers(0, 2**32 - 1),
    "z1_dim": _AT_LEAST_ONE,
    "z2_dim": _AT_LEAST_ONE,
    "feature_dim": _AT_LEAST_ONE,
    "hidden_units": _AT_LEAST_ONE,
    "n_cosines": _AT_LEAST_ONE,
    "cost_critic_hidden_dim": _AT_LEAST_ONE,
    "reward_loss_weight": _NON_NEGATIVE,
    "image_channels": Check(lambda value: len(value) == 4 and _AT_LEAST_ONE.holds(value), "4 channel counts >= 1"),
    "latent_min_std": _POSITIVE,
    "latent_max_std": _POSITIVE,
    "latent_mean_bound": _POSITIVE,
    "latent_kl_balance": _numbers(0, 1),
    "latent_overshooting": _AT_LEAST_ONE,
    "latent_reward_overshooting": _NON_NEGATIVE,
    "latent_overshooting_stride": _AT_LEAST_ONE,
    "latent_recurrence": _words(*LATENT_MODELS),
    "actor_critic_memory": _NON_NEGATIVE,
}


def _fits(value: Any, annotation: Any) -> bool | None:
    """Whether ``value`` fits the annotation; None where the annotation is beyond these checks (an env class, Any)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        fits = [_fits(value, arg) for arg in args]
        return True if True in fits else (None if None in fits else False)
    if annotation is type(None):
        return value is None
    if annotation is bool:
        return isinstance(value, (bool, np.bool_))
    if annotation is int:
        return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))
    if annotation is float:
        return _is_number(value)
    if annotation is str:
        return isinstance(value, str)
    if annotation is dict or origin is dict:
        return isinstance(value, Mapping)
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:  # converted with tuple(): a list does too
        return isinstance(value, (list, tuple)) and all(_fits(item, args[0]) is not False for item in value)
    if origin is tuple:
        return isinstance(value, tuple) and len(value) == len(args) and False not in map(_fits, value, args)
    if origin is collections.abc.Callable:
        return callable(value)
    if origin is type:
        return isinstance(value, type) and issubclass(value, args[0])
    return None


def _describe(annotation: Any) -> str:
    """The annotation in words: ``float | None`` is "a number or None"."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):  # the forms _fits checks: "a string" for ``th.device | str``
        return " or ".join(_describe(arg) for arg in args if _fits(None, arg) is not None)
    words = {type(None): "None", bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    if annotation in words:
        return words[annotation]
    if annotation is dict or origin is dict:
        return "a mapping"
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        return f"a list of {getattr(args[0], '__name__', args[0])}"
    if origin is tuple:
        return f"a tuple ({', '.join(getattr(arg, '__name__', str(arg)) for arg in args)})"
    if origin is collections.abc.Callable:
        return "a schedule (callable)"
    if origin is type:
        return f"a subclass of {args[0].__name__}"
    return getattr(annotation, "__name__", str(annotation))


def _annotations(function: Callable[..., Any]) -> dict[str, Any]:
    """The parameters' annotations of ``function`` (a class: its ``__init__``), with string annotations resolved."""
    target = function.__init__ if isinstance(function, type) else function  # type: ignore[misc]
    try:
        return typing.get_type_hints(target)
    except (NameError, TypeError):  # an annotation that does not resolve: use them as written
        return {name: parameter.annotation for name, parameter in inspect.signature(function).parameters.items()}


def check_arguments(function: Callable[..., Any], arguments: Mapping[str, Any], ranges: Mapping[str, Check] = RANGES) -> None:
    """
    Check the values of ``function``'s parameters found in ``arguments`` against their annotations and ``ranges``.

    :param function: the function (or class) that takes them
    :param arguments: parameter name -> value (``locals()`` at the top of ``function`` checks every argument given)
    :param ranges: parameter name -> the condition its value must meet beyond its type
    :raises ValueError: naming the first parameter whose value does not fit, what it must be and what it got
    """
    annotations = _annotations(function)
    for name, parameter in inspect.signature(function).parameters.items():
        if name not in arguments:
            continue
        value, annotation, check = arguments[name], annotations.get(name, parameter.annotation), ranges.get(name)
        fits = _fits(value, annotation)
        if fits is False or (check is not None and value is not None and fits is not None and not check.holds(value)):
            expected = _describe(annotation) if fits is not None else "a value"
            raise ValueError(f"{name} must be {expected}{f' ({check.text})' if check else ''}, got {value!r}")


def check_related_arguments(arguments: Mapping[str, Any]) -> None:
    """
    The ranges of ``DSSLAC``'s keywords that depend on another: ``actor_critic_transitions`` (at most ``sequence_length``,
    one fewer with the policy's ``previous_action_input`` or ``actor_critic_memory``: a window's first frame has no
    previous action in it),
    ``stored_beliefs`` (a burn-in to start), ``belief_refresh_interval`` (stored beliefs), the policy's
    ``latent_overshooting`` (a roll inside the window), ``latent_reward_overshooting`` and ``latent_overshooting_stride``
    (on such rolls), and
    ``cost_target``.
    """
    transitions, length = arguments["actor_critic_transitions"], arguments["sequence_length"]
    most, range_text = length, f"[1, sequence_length={length}]"
    policy_kwargs = arguments["policy_kwargs"] or {}
    takes_previous = [name for name in ("previous_action_input", "actor_critic_memory") if policy_kwargs.get(name)]
    if takes_previous:
        most = length - 1
        range_text = f"[1, sequence_length - 1 = {most}] with {' and '.join(takes_previous)} (a window's first frame has no "
        range_text += "previous action in it)"
    if not 1 <= transitions <= most:
        raise ValueError(f"actor_critic_transitions must be in {range_text}, got {transitions}")
    if arguments.get("stored_beliefs") and arguments.get("burn_in", 0) < 1:
        raise ValueError(
            f"stored_beliefs=True starts each window's burn-in from a stored belief: it needs burn_in >= 1, got "
            f"burn_in={arguments.get('burn_in', 0)}"
        )
    if arguments.get("belief_refresh_interval", 0) > 0 and not arguments.get("stored_beliefs"):
        raise ValueError(
            f"belief_refresh_interval={arguments['belief_refresh_interval']} re-filters the replay buffer's stored beliefs: "
            "it needs stored_beliefs=True"
        )
    depth = policy_kwargs.get("latent_overshooting", 1)
    if isinstance(depth, int) and depth > length:
        raise ValueError(
            f"policy_kwargs latent_overshooting rolls z1's prior up to that many steps inside a window of sequence_length="
            f"{length} transitions: it must be in [1, {length}], got {depth}"
        )
    reward_weight = policy_kwargs.get("latent_reward_overshooting", 0.0)
    if isinstance(reward_weight, (int, float)) and reward_weight > 0 and isinstance(depth, int) and depth < 2:
        raise ValueError(
            f"policy_kwargs latent_reward_overshooting={reward_weight} weighs the reward on the latent overshooting's "
            f"open-loop rolls: it needs latent_overshooting >= 2, got {depth}"
        )
    stride = policy_kwargs.get("latent_overshooting_stride", 1)
    if isinstance(stride, int) and stride > 1 and isinstance(depth, int) and depth < 2:
        raise ValueError(
            f"policy_kwargs latent_overshooting_stride={stride} picks the starts of the latent overshooting's open-loop "
            f"rolls: it needs latent_overshooting >= 2, got {depth}"
        )
    target, limit = arguments["cost_target"], arguments["cost_limit"]
    if target is not None and not 0.0 <= target <= limit:
        raise ValueError(f"cost_target must be in [0, cost_limit={limit:g}] or None, got {target}")


def _keyword_names(function: Callable[..., Any], skip: tuple[str, ...] = ()) -> list[str]:
    """The names ``function`` takes as keywords, private ones (``_init_setup_model``) and ``skip`` left out."""
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return [
        name
        for name, parameter in inspect.signature(function).parameters.items()
        if parameter.kind in kinds and not name.startswith("_") and name not in ("self", *skip)
    ]


def _unknown_name(name: str, valid: list[str], label: str, owner: str) -> InputError:
    """The error for a keyword ``owner`` does not take: the closest names, then every valid one."""
    close = difflib.get_close_matches(name, valid, n=3)
    hint = f"did you mean {' or '.join(close)}? " if close else ""
    return InputError(f"{label}: {owner} takes no keyword {name!r}; {hint}valid: {', '.join(valid)}")


def _labels(error: Exception, sources: Mapping[str, str]) -> str:
    """The sources of the keywords that ``error``'s message names (the flags to fix), else all of them."""
    named = [label for name, label in sources.items() if re.search(rf"\b{re.escape(name)}\b", str(error))]
    return ", ".join(dict.fromkeys(named or sources.values())) or "the keywords"


def check_keywords(
    function: Callable[..., Any],
    keywords: Mapping[str, Any],
    sources: Mapping[str, str],
    owner: str,
    skip: tuple[str, ...] = (),
    ranges: Mapping[str, Check] = RANGES,
    also_valid: tuple[str, ...] = (),
) -> None:
    """
    Check keywords for ``function``: each must be one of its parameters (a ``**kwargs`` takes any) and fit it.

    :param function: the function (or class) they are for
    :param keywords: name -> value
    :param sources: name -> where it was given, as the error names it ("--hyperparams tau")
    :param owner: what takes them, as the error names it ("DSSLAC")
    :param skip: parameters that are not the user's to give (an env's observation space)
    :param ranges: see ``check_arguments``
    :param also_valid: names taken besides the parameters, unchecked (``gymnasium.make``'s own keywords)
    :raises InputError: naming the source of the first keyword at fault
    """
    valid = [*_keyword_names(function, skip), *also_valid]
    takes_any = any(p.kind == inspect.Parameter.VAR_KEYWORD for p in inspect.signature(function).parameters.values())
    for name in keywords:
        if name not in valid and not takes_any:
            raise _unknown_name(name, valid, sources.get(name, name), owner)
    try:
        check_arguments(function, keywords, ranges)
    except ValueError as error:
        raise InputError(f"{_labels(error, sources)}: {error}") from None


def check_algorithm(
    algorithm: type,
    policy: str | type,
    hyperparams: Mapping[str, Any],
    sources: Mapping[str, str],
    set_elsewhere: Mapping[str, str],
    env: gym.Env | None = None,
) -> None:
    """
    Check an SB3 algorithm's keywords (DSSLAC's) before training: names and values against its signature, the policy's
    keywords against the policy's, then the algorithm built without its networks (``_init_setup_model=False``) on
    ``env`` (or none), which runs its own checks of spaces, combinations and the episode length, and the replay
    buffer's keywords against its class.

    :param algorithm: the algorithm class
    :param policy: its policy, a name of ``algorithm.policy_aliases`` or the class
    :param hyperparams: the keywords
    :param sources: keyword -> where it was given ("--hyperparams tau", "--batch-size", "--preset cpu")
    :param set_elsewhere: keywords the caller sets itself -> the flag that sets them ("seed" -> "--seed")
    :param env: the env it will train on (see ``probe_env``; the caller closes it), or None
    :raises InputError: naming where the keyword at fault was given
    """
    for name, flag in set_elsewhere.items():
        if name in hyperparams:
            raise InputError(f"{sources.get(name, name)}: {name} is set by {flag}, not as a keyword")
    check_keywords(algorithm, hyperparams, sources, algorithm.__name__, skip=("policy", "env", *set_elsewhere))
    policy_kwargs = hyperparams.get("policy_kwargs")
    policy_class = algorithm.policy_aliases.get(policy, policy) if isinstance(policy, str) else policy
    if policy_kwargs is not None and isinstance(policy_class, type):
        label = sources.get("policy_kwargs", "policy_kwargs")
        check_keywords(
            policy_class,
            policy_kwargs,
            {name: f"{label} {name}" for name in policy_kwargs},
            policy_class.__name__,
            skip=("observation_space", "action_space", "lr_schedule"),
        )
    try:
        model = algorithm(policy, env, **{**hyperparams, "verbose": 0, "_init_setup_model": False})
    except (ValueError, TypeError) as error:
        raise InputError(f"{_labels(error, sources)}: {error}") from None
    buffer_kwargs = hyperparams.get("replay_buffer_kwargs") or {}
    label = sources.get("replay_buffer_kwargs", "replay_buffer_kwargs")
    check_keywords(
        model.replay_buffer_class,
        buffer_kwargs,
        {name: f"{label} {name}" for name in buffer_kwargs},
        model.replay_buffer_class.__name__,
        skip=("buffer_size", "observation_space", "action_space", "device", "n_envs", "optimize_memory_usage"),
    )


def check_env_id(env_id: str, flag: str = "--env") -> gym.envs.registration.EnvSpec:
    """
    The registered spec of ``env_id`` (``module:EnvId`` imports the module first, as ``gymnasium.make`` does), the
    Safety-Gym tasks registered.

    :raises InputError: for an unknown id (with the closest registered ones) or a module that does not import
    """
    import safety_envs  # noqa: F401 (registers SafetyGym/*)

    module, _, name = env_id.rpartition(":")
    if module:
        try:
            __import__(module)
        except ImportError as error:
            raise InputError(f"{flag} {env_id}: cannot import {module!r}, which should register the env ({error})") from None
    try:
        return gym.spec(name)
    except gym.error.Error:
        close = difflib.get_close_matches(name, list(gym.registry), n=3)
        hint = f"did you mean {' or '.join(close)}? " if close else ""
        raise InputError(
            f"{flag} {env_id}: no registered env has this id; {hint}for your own env, register it with gymnasium.register, "
            "or pass 'my_module:MyEnv-v0' so that my_module (which registers it) is imported first"
        ) from None


def check_env_kwargs(spec: gym.envs.registration.EnvSpec, env_kwargs: Mapping[str, Any], sources: Mapping[str, str]) -> None:
    """
    Check env keywords against the env's constructor (and ``gymnasium.make``'s own): names and annotated types.

    :param spec: the env's registered spec (``check_env_id``)
    :param env_kwargs: the keywords
    :param sources: keyword -> where it was given ("--env-kwargs width")
    :raises InputError: naming where the keyword at fault was given
    """
    creator = spec.entry_point if callable(spec.entry_point) else gym.envs.registration.load_env_creator(spec.entry_point)
    check_keywords(creator, env_kwargs, sources, spec.id, ranges={}, also_valid=GYM_MAKE_KEYWORDS)


def probe_env(env_id: str, obs_type: str | None, env_kwargs: Mapping[str, Any], sources: Mapping[str, str]) -> gym.Env:
    """
    Make the env a run will train on and take one random step: the env's constructor checks its keywords' values (a
    width of 0), and the step shows whether it reports ``info["cost"]``. The caller closes it.

    :param env_id: the env id
    :param obs_type: the observation type (None: the env's)
    :param env_kwargs: the env's other keywords
    :param sources: keyword -> where it was given ("obs_type" -> "--obs-type", "width" -> "--env-kwargs width")
    :raises InputError: naming the env id, or where the keyword the env rejected was given
    """
    try:
        env = make_env(env_id, obs_type, env_kwargs=dict(env_kwargs))
    except (ValueError, TypeError, AssertionError, gym.error.Error) as error:
        given = {name: sources.get(name, name) for name in env_kwargs}
        if obs_type is not None:
            given["obs_type"] = sources.get("obs_type", "obs_type")
        label = _labels(error, given) if given else f"--env {env_id}"
        raise InputError(f"{label}: the env {env_id} rejected them: {error}") from None
    try:
        env.reset(seed=0)
        cost_from_info(env.step(env.action_space.sample())[-1])
    except ValueError as error:
        env.close()
        raise InputError(f"--env {env_id}: {error}") from None
    return env


def check_device(device: str, flag: str = "--device") -> None:
    """
    ``device`` is "auto" or a torch device this machine has (SB3 quietly falls back to the CPU for a missing GPU).

    :raises InputError: naming the flag
    """
    if device == "auto":
        return
    try:
        parsed = th.device(device)
    except (RuntimeError, TypeError):
        raise InputError(f"{flag} {device}: not a torch device; use auto, cpu, cuda, cuda:<index> or mps") from None
    if parsed.type == "cpu":
        return
    backend = {"mps": th.backends.mps}.get(parsed.type, getattr(th, parsed.type, None))
    if backend is None or not backend.is_available():
        build = " (this torch has no CUDA)" if parsed.type == "cuda" and th.version.cuda is None else ""
        raise InputError(f"{flag} {device}: no {parsed.type} device on this machine{build}; use --device cpu or auto")
    count = backend.device_count() if hasattr(backend, "device_count") else 1
    if parsed.index is not None and parsed.index >= count:
        raise InputError(f"{flag} {device}: this machine has {count} {parsed.type} device(s), numbered from 0")


def check_model_file(path: str, name: str = "MODEL") -> None:
    """
    ``path`` is a model saved by SB3's ``save``: a zip file holding its ``data``.

    :raises InputError: naming the argument
    """
    if not Path(path).is_file():
        raise InputError(f"{name} {path}: no such file")
    if not zipfile.is_zipfile(path):
        raise InputError(f"{name} {path}: not a saved model (a model.zip of DSSLAC.save); this file is not a zip file")
    with zipfile.ZipFile(path) as archive:
        if "data" not in archive.namelist():
            raise InputError(f"{name} {path}: a zip file, but not a saved model (it has no 'data' entry)")


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1."""
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return value


# The formats imageio writes the evaluation videos in
VIDEO_SUFFIXES = (".mp4", ".gif")


def video_file(text: str) -> str:
    """An argparse type: a file name ending in one of ``VIDEO_SUFFIXES``."""
    if Path(text).suffix.lower() not in VIDEO_SUFFIXES:
        raise argparse.ArgumentTypeError(f"must be a {' or '.join(VIDEO_SUFFIXES)} file, got {text!r}")
    return text


def non_negative_int(text: str) -> int:
    """An argparse type: an integer >= 0."""
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}")
    return value


def seed(text: str) -> int:
    """An argparse type: a seed, an integer in [0, MAX_SEED]."""
    value = _integer(text)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be a seed in [0, {MAX_SEED}], got {text!r}")
    return value


def check_spaces(observation_space: spaces.Space, action_space: spaces.Space) -> None:
    """Raise a ValueError naming the fix for spaces DS-SLAC cannot handle."""
    if not isinstance(action_space, spaces.Box):
        raise ValueError(
            f"DS-SLAC needs a continuous Box action space, got {action_space}. "
            "Discrete-action envs need a different algorithm (or a wrapper mapping a Box to the discrete actions)."
        )
    if not isinstance(observation_space, spaces.Box) or len(observation_space.shape) not in (1, 3):
        raise ValueError(
            f"DS-SLAC encodes Box images (C, H, W) or flat Box vectors, got {observation_space}. "
            "For safety_envs use obs_type='pixels' or obs_type='state'; "
            "flatten or select Dict observations with a wrapper."
        )


def _model_view(space: spaces.Space) -> tuple[int, ...]:
    """The shape a model sees of an observation space: images channels first, as SB3's VecTransposeImage gives them."""
    shape = tuple(space.shape or ())
    if is_image_space(space, check_channels=False) and not is_image_space_channels_first(space):  # type: ignore[arg-type]
        return (shape[2], shape[0], shape[1])
    return shape


def check_env_fits_model(env: gym.Env, observation_space: spaces.Space, action_space: spaces.Space, env_id: str) -> None:
    """
    Check that an env gives the observations and takes the actions a saved model was trained on, before any episode.

    :param env: the env the model is about to run in
    :param observation_space: the model's (images channels first)
    :param action_space: the model's
    :param env_id: the env's id, for the message
    :raises InputError: saying what differs and which env keywords would make the env fit
    """
    seen, trained = _model_view(env.observation_space), tuple(observation_space.shape or ())
    if seen != trained:
        if len(seen) == 3 and len(trained) == 3:
            fix = (
                f"its frames are {seen[2]}x{seen[1]}, the model's {trained[2]}x{trained[1]} "
                f"(a safety_envs task makes them with --env-kwargs width={trained[2]} height={trained[1]})"
            )
        else:
            kind = "pixels" if len(trained) == 3 else "state"
            fix = f"the model was trained on {kind} (--obs-type {kind})"
        raise InputError(f"--env {env_id}: observations of shape {seen} (channels first) against the model's {trained}: {fix}")
    if env.action_space.shape != action_space.shape:
        raise InputError(
            f"--env {env_id}: it takes actions of shape {env.action_space.shape}, the model gives {action_space.shape} "
            "(another robot?)"
        )
