"""
The thesis's protocol from the command line: ``python -m sb3_dsslac train | plot | evaluate | beliefs | tune``.

This module parses arguments, has ``validation`` check them before any env, model or run folder is made (bad input
ends with one ``error:`` line and exit status 2), and dispatches to ``runs``, ``rollouts``, ``plotting``, ``beliefs``
and ``hpo``.

Units: ``--sim-steps`` and every ``*-every`` are simulator steps (the thesis's "environment steps"); DSSLAC counts
agent steps, ``action_repeat`` simulator steps each (2 on the Safety-Gym tasks).
"""

import argparse
import sys
from pathlib import Path
from typing import Any, NoReturn

from sb3_dsslac.app.rollouts import evaluate, format_episodes
from sb3_dsslac.app.runs import (
    CONFIG_FILE,
    RunStoppedError,
    TrainConfig,
    find_run_config,
    parse_hyperparams,
    resume,
    train,
)
from sb3_dsslac.common.env_info import action_repeat_of
from sb3_dsslac.dsslac import DSSLAC
from sb3_dsslac.presets import PRESET_ENV_KWARGS, PRESETS, preset_env_kwargs, preset_hyperparams
from sb3_dsslac.common.validation import (
    InputError,
    check_algorithm,
    check_device,
    check_env_id,
    check_env_kwargs,
    check_model_file,
    error_line,
    non_negative_int,
    positive_int,
    probe_env,
    seed,
    video_file,
)

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
    "cost_target": float,
    "lagrange_init": float,
    "lagrange_learning_rate": float,
    "n_quantiles": int,
    "cvar_risk_level": float,
}


# One line per preset of ``presets.PRESETS`` for ``--help``; the help lists every preset, these or not
PRESET_SUMMARIES: dict[str, str] = {
    "thesis": "Table 5.2, the thesis's hyperparameters (a GPU's work: about 0.3 updates/s on a 2-core CPU)",
    "thesis_fast": "thesis with one shared batch per update and bfloat16 where the device computes it natively",
    "cpu": "small networks, a short warm-up and few updates: a pixel run in minutes on a CPU, learns little",
    "cpu_learning": "the CPU learning benchmark's, on state vectors: learns PointGoal1 in about 30 minutes",
    "cpu_pixels": "the pixel learning benchmark's: 64x64 frames, a quarter of the thesis's convolution widths",
    "cpu_pixels32": "cpu_pixels on 32x32 frames at action repeat 4, the multiplier aiming at cost 20",
    "cpu_pixels32_bounded": "cpu_pixels32 with bounded latents (every std in [0.1, 2], every |mean| <= 10)",
    "cpu_pixels32_pid": "cpu_pixels32_bounded learning from 4 transitions per window, with the PID multiplier",
    "cpu_pixels32_prev_action": "cpu_pixels32_pid with the previous action beside the belief (actor and critics)",
    "cpu_pixels32_gru": "cpu_pixels32_pid with a deterministic GRU z2 (an RSSM's recurrent state) in the latent model",
    "cpu_pixels32_gru_stored": "cpu_pixels32_gru whose windows continue the acting filter's stored belief (a 4-frame burn-in)",
    "cpu_pixels32_gru_overshooting": "cpu_pixels32_gru_stored with latent overshooting (z1's prior rolled 2-4 steps ahead)",
}


class _Parser(argparse.ArgumentParser):
    """``ArgumentParser`` whose errors are one line (``error: ...``, exit status 2) pointing to ``--help``."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"error: {message} (see {self.prog} --help)\n")


def _preset_help() -> str:
    """Every preset of ``PRESETS`` with its summary and the env keywords it sets."""
    lines = []
    for name in PRESETS:
        env_kwargs = " ".join(f"{key}={value}" for key, value in PRESET_ENV_KWARGS.get(name, {}).items())
        sets = f" ({name} sets {env_kwargs}; --env-kwargs replaces them)" if env_kwargs else ""
        lines.append(f"{name}: {PRESET_SUMMARIES.get(name, 'see sb3_dsslac/presets.py')}{sets}")
    return "; ".join(lines)


# ``--env-kwargs`` of the commands that run a saved model
_RUN_ENV_KWARGS_HELP = "keywords of the env as YAML, on top of the model's run's where it ran on this env: width=32 height=32"


def _add_model_flags(parser: argparse.ArgumentParser, threads_help: str) -> None:
    parser.add_argument("--preset", choices=list(PRESETS), default="thesis", help=_preset_help())
    parser.add_argument("--obs-type", choices=["pixels", "state"], help="observation type (default: the env's)")
    parser.add_argument(
        "--env-kwargs",
        nargs="+",
        metavar="KEY=VALUE",
        help="keywords of the env as YAML, on top of the preset's: width=32 height=32 for 32x32 frames",
    )
    parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (one this machine has)")
    parser.add_argument("--threads", type=positive_int, help=threads_help)
    group = parser.add_argument_group("hyperparameters (on top of the preset; agent steps)")
    for name, kind in HYPERPARAM_FLAGS.items():
        group.add_argument(f"--{name.replace('_', '-')}", dest=name, type=kind, metavar=kind.__name__.upper())
    group.add_argument(
        "--hyperparams", nargs="+", metavar="KEY=VALUE", help="other DSSLAC keywords as YAML: policy_kwargs='{z1_dim: 16}'"
    )


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="python -m sb3_dsslac",
        description="DS-SLAC from the command line: train with the thesis's protocol, resume, plot learning curves, "
        "evaluate a model, show a pixel agent's beliefs, tune with Optuna (docs/cli.md).",
    )
    commands = parser.add_subparsers(dest="command", required=True)

    train_parser = commands.add_parser("train", help="train with the thesis's evaluation protocol")
    train_parser.add_argument("--env", help="env id, e.g. SafetyGym/PointGoal1-v0")
    train_parser.add_argument(
        "--sim-steps", type=positive_int, help=f"simulator steps of training (default {TrainConfig.sim_steps})"
    )
    train_parser.add_argument("--seed", type=seed, default=0)
    train_parser.add_argument("--out", help="run folder (default runs/<env>_<seed>_<timestamp>)")
    train_parser.add_argument("--resume", metavar="RUN_DIR", help="continue this run from its last checkpoint")
    train_parser.add_argument("--eval-every", type=positive_int, default=25_000, help="simulator steps between evaluations")
    train_parser.add_argument("--eval-episodes", type=positive_int, default=10)
    train_parser.add_argument("--eval-seed", type=seed, help="seed of the evaluation env (default seed + 10000)")
    train_parser.add_argument(
        "--deterministic-eval",
        action="store_true",
        help="evaluate with the filter's means and the mean action (default: sampled, the thesis's protocol)",
    )
    train_parser.add_argument("--stochastic-eval", action="store_true", help="the default; kept for old command lines")
    train_parser.add_argument(
        "--checkpoint-every", type=positive_int, default=100_000, help="simulator steps between checkpoints"
    )
    train_parser.add_argument("--n-envs", type=positive_int, default=1, help="training envs, each in its own process")
    train_parser.add_argument("--quiet", action="store_true", help="no logs on stdout")
    train_parser.add_argument("--no-progress-bar", action="store_true")
    _add_model_flags(train_parser, "torch CPU threads (default: torch's; 1 is often fastest on a busy CPU)")

    plot_parser = commands.add_parser("plot", help="learning curves and the normalised score table of runs")
    plot_parser.add_argument("runs", nargs="+", metavar="RUN_DIR")
    plot_parser.add_argument("--out", default=".", help="folder of curves.png, scores.csv and scores.md")

    eval_parser = commands.add_parser("evaluate", help="per-episode reward and cost of a saved model, and a video")
    eval_parser.add_argument("model", help="a saved model (.zip)", metavar="MODEL")
    eval_parser.add_argument("--env", help="env id (default: the model's run's)")
    eval_parser.add_argument("--episodes", type=positive_int, default=10)
    eval_parser.add_argument("--seed", type=seed, default=0, help="episode i is reset with seed + i")
    policy = eval_parser.add_mutually_exclusive_group()
    policy.add_argument("--stochastic", action="store_true", help="sample the filter and the action (the thesis's protocol)")
    policy.add_argument("--deterministic", action="store_true", help="the filter's means and the mean action")
    eval_parser.add_argument("--video", type=video_file, help="video file (.mp4 or .gif)")
    eval_parser.add_argument("--video-episodes", type=non_negative_int, default=1, help="episodes recorded into the video")
    eval_parser.add_argument("--obs-type", choices=["pixels", "state"])
    eval_parser.add_argument("--env-kwargs", nargs="+", metavar="KEY=VALUE", help=_RUN_ENV_KWARGS_HELP)
    eval_parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (one this machine has)")

    beliefs_parser = commands.add_parser(
        "beliefs", help="a pixel agent's frames beside its latent model's reconstructions and predicted cost, as a PNG"
    )
    beliefs_parser.add_argument("model", help="a saved model (.zip) trained on pixels", metavar="MODEL")
    beliefs_parser.add_argument("--env", help="env id (default: the model's run's)")
    beliefs_parser.add_argument("--env-kwargs", nargs="+", metavar="KEY=VALUE", help=_RUN_ENV_KWARGS_HELP)
    beliefs_parser.add_argument("--seed", type=seed, default=0, help="seed of the episode")
    beliefs_parser.add_argument("--steps", type=positive_int, help="agent steps to run (default: the whole episode)")
    beliefs_parser.add_argument("--frames", type=positive_int, default=10, help="frames shown")
    beliefs_parser.add_argument("--stochastic", action="store_true", help="sample the filter and the action")
    beliefs_parser.add_argument("--out", default="beliefs.png", help="the PNG")
    beliefs_parser.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (one this machine has)")

    tune_parser = commands.add_parser("tune", help="Optuna search, maximising eval reward under the cost budget")
    tune_parser.add_argument("--env", required=True)
    tune_parser.add_argument("--timesteps", type=positive_int, required=True, help="simulator steps per trial")
    tune_parser.add_argument("--n-trials", type=positive_int, default=10, help="trials run by this process")
    tune_parser.add_argument(
        "--total-trials",
        type=positive_int,
        help="instead of --n-trials: run trials until the study has this many finished, retrying those of dead workers",
    )
    tune_parser.add_argument(
        "--heartbeat-interval",
        type=positive_int,
        default=60,
        help="seconds between a running trial's heartbeats on an RDB storage; a trial silent for twice this is failed "
        "and retried",
    )
    tune_parser.add_argument("--storage", help="sqlite:///f.db, postgresql://..., or a journal file (*.log, *.journal)")
    tune_parser.add_argument("--study-name", default="dsslac")
    tune_parser.add_argument("--n-evaluations", type=positive_int, default=4, help="evaluations per trial (pruning points)")
    tune_parser.add_argument("--eval-episodes", type=positive_int, default=5)
    tune_parser.add_argument(
        "--n-startup-trials", type=non_negative_int, default=5, help="random trials before TPE and pruning"
    )
    tune_parser.add_argument("--sampler-seed", type=seed, help="seed of TPE (leave unset with several workers)")
    tune_parser.add_argument("--out", help="folder for the trials' CSV")
    _add_model_flags(
        tune_parser,
        "torch CPU threads per worker (default 1, so that several workers on one machine do not oversubscribe its cores)",
    )
    return parser


def _checked_run_inputs(args: argparse.Namespace, set_elsewhere: dict[str, str]) -> tuple[dict[str, Any], dict[str, Any], int]:
    """
    The DSSLAC keywords (flags and ``--hyperparams`` on top of the preset) and env keywords (``--env-kwargs``, the
    preset's under them) of ``train`` or ``tune``, checked before any work (``validation``): first the device, the env
    id and every keyword's name and value, then on one probe of the env the keywords' values, ``info["cost"]``, the
    spaces and the episode length.

    :param args: the parsed command line
    :param set_elsewhere: DSSLAC keywords the command sets itself -> the flag that sets them
    :return: the DSSLAC keywords given (without the preset's), the env keywords given, and the env's action repeat
    :raises InputError: naming the flag at fault
    """
    check_device(args.device)
    spec = check_env_id(args.env)
    env_kwargs = parse_hyperparams(args.env_kwargs, flag="--env-kwargs")
    env_sources = {name: f"--preset {args.preset} (env keyword {name})" for name in PRESET_ENV_KWARGS.get(args.preset, {})}
    env_sources.update({name: f"--env-kwargs {name}" for name in env_kwargs})
    merged_env_kwargs = preset_env_kwargs(args.preset, env_kwargs)
    obs_type = {}
    if args.obs_type is not None:  # it replaces an obs_type of --env-kwargs
        obs_type, env_sources["obs_type"] = {"obs_type": args.obs_type}, "--obs-type"
    check_env_kwargs(spec, {**merged_env_kwargs, **obs_type}, env_sources)

    flagged = {name: getattr(args, name) for name in HYPERPARAM_FLAGS if getattr(args, name) is not None}
    given = parse_hyperparams(args.hyperparams)
    sources = {name: f"--preset {args.preset} ({name})" for name in PRESETS[args.preset]}
    sources.update({name: f"--{name.replace('_', '-')}" for name in flagged})
    sources.update({name: f"--hyperparams {name}" for name in given})
    hyperparams = {**flagged, **given}
    resolved = preset_hyperparams(args.preset, hyperparams)
    check_algorithm(DSSLAC, "LatentPolicy", resolved, sources, set_elsewhere)
    env = probe_env(args.env, args.obs_type, merged_env_kwargs, env_sources)
    try:
        check_algorithm(DSSLAC, "LatentPolicy", resolved, sources, set_elsewhere, env)
        return hyperparams, env_kwargs, action_repeat_of(env)
    finally:
        env.close()


def _experiment_fields(
    args: argparse.Namespace, sim_steps: int, hyperparams: dict[str, Any], env_kwargs: dict[str, Any], threads: int | None
) -> dict[str, Any]:
    """The fields of ``Experiment`` (what ``train`` and each ``tune`` trial train) from the flags both commands take."""
    return {
        "env": args.env,
        "sim_steps": sim_steps,
        "preset": args.preset,
        "hyperparams": hyperparams,
        "obs_type": args.obs_type,
        "env_kwargs": env_kwargs,
        "eval_episodes": args.eval_episodes,
        "device": args.device,
        "threads": threads,
    }


# What ``train --resume`` takes besides the run folder: a new total of simulator steps, and how much it prints; the
# run's own config.yaml holds every other setting
RESUME_FLAGS = ("command", "resume", "sim_steps", "quiet", "no_progress_bar")


def _check_resume_flags(args: argparse.Namespace) -> None:
    """Refuse the flags that ``--resume`` would ignore, naming them, instead of continuing with other settings silently."""
    defaults = vars(build_parser().parse_args(["train"]))
    ignored = [name for name, value in vars(args).items() if name not in RESUME_FLAGS and value != defaults[name]]
    if ignored:
        flags = ", ".join(f"--{name.replace('_', '-')}" for name in ignored)
        raise InputError(
            f"{flags}: --resume continues {args.resume} with the settings of its {CONFIG_FILE}; drop them "
            "(--sim-steps extends the run)"
        )


def _train_command(args: argparse.Namespace) -> None:
    if args.resume is not None:
        _check_resume_flags(args)
        run_dir = resume(args.resume, sim_steps=args.sim_steps)
    else:
        if args.env is None:
            raise InputError("train needs --env (or --resume RUN_DIR)")
        hyperparams, env_kwargs, action_repeat = _checked_run_inputs(
            args, {"seed": "--seed", "device": "--device", "verbose": "--quiet"}
        )
        sim_steps = TrainConfig.sim_steps if args.sim_steps is None else args.sim_steps
        if sim_steps < action_repeat:
            raise InputError(
                f"--sim-steps {sim_steps}: less than one agent step; {args.env} repeats each action {action_repeat} "
                "simulator steps"
            )
        config = TrainConfig(
            **_experiment_fields(args, sim_steps, hyperparams, env_kwargs, args.threads),
            seed=args.seed,
            eval_every=args.eval_every,
            eval_deterministic=args.deterministic_eval,
            eval_seed=args.eval_seed,
            checkpoint_every=args.checkpoint_every,
            n_envs=args.n_envs,
            verbose=0 if args.quiet else 1,
            progress_bar=not args.no_progress_bar,
        )
        run_dir = train(config, args.out)
    print(f"run folder: {run_dir}")


def _plot_command(args: argparse.Namespace) -> None:
    from sb3_dsslac.app.plotting import report

    if Path(args.out).is_file():
        raise InputError(f"--out {args.out}: a file; plot writes curves.png, scores.csv and scores.md into a folder")
    print(report(args.runs, args.out))


def _model_and_run(args: argparse.Namespace) -> tuple[str, TrainConfig | None, bool, dict[str, Any]]:
    """
    The env id of ``args.model`` (``--env``, else its run's), its run's config if any, whether that run used this
    env, and the env keywords to run it with (the run's where it used this env, ``--env-kwargs`` on top); the model
    file, ``--device``, ``--env`` and ``--env-kwargs`` checked first.
    """
    check_model_file(args.model)
    check_device(args.device)
    spec = check_env_id(args.env) if args.env is not None else None
    given = parse_hyperparams(args.env_kwargs, flag="--env-kwargs")
    run_config = find_run_config(Path(args.model))
    if args.env is None and run_config is None:
        raise InputError(f"MODEL {args.model} is not in a run folder (no {CONFIG_FILE} beside it): pass the env id (--env)")
    env_id = args.env or run_config.env  # type: ignore[union-attr]
    same_env = run_config is not None and run_config.env == env_id
    env_kwargs = {**(run_config.env_kwargs if same_env else {}), **given}  # type: ignore[union-attr]
    sources = {name: f"the run's env keyword {name}" for name in env_kwargs}
    sources.update({name: f"--env-kwargs {name}" for name in given})
    check_env_kwargs(spec or check_env_id(env_id), env_kwargs, sources)
    return env_id, run_config, same_env, env_kwargs


def _evaluate_command(args: argparse.Namespace) -> None:
    env_id, run_config, same_env, env_kwargs = _model_and_run(args)
    if args.deterministic or args.stochastic:
        deterministic = args.deterministic
    else:  # the protocol of the model's run, else the thesis's
        deterministic = run_config.eval_deterministic if run_config is not None else False
    model = DSSLAC.load(args.model, device=args.device)
    results = evaluate(
        model,
        env_id=env_id,
        episodes=args.episodes,
        deterministic=deterministic,
        seed=args.seed,
        video=args.video,
        video_episodes=args.video_episodes,
        obs_type=args.obs_type or (run_config.obs_type if same_env else None),  # type: ignore[union-attr]
        env_kwargs=env_kwargs,
    )
    print(format_episodes(results, model.cost_limit, deterministic))
    if args.video:
        print(f"video: {args.video}")


def _beliefs_command(args: argparse.Namespace) -> None:
    from sb3_dsslac.app.beliefs import episode_beliefs, mean_cost_probabilities, plot_beliefs

    env_id, _, _, env_kwargs = _model_and_run(args)
    model = DSSLAC.load(args.model, device=args.device)
    beliefs = episode_beliefs(
        model,
        env_id,
        seed=args.seed,
        max_steps=args.steps,
        deterministic=not args.stochastic,
        env_kwargs=env_kwargs,
    )
    path = plot_beliefs(beliefs, args.out, n_frames=args.frames)
    on_costly, on_free = mean_cost_probabilities(beliefs)
    print(
        f"{len(beliefs.costs)} steps, reward {beliefs.rewards.sum():.2f}, cost {beliefs.costs.sum():g}; "
        f"mean predicted p(cost): {on_costly:.3f} on the costly steps, {on_free:.3f} on the others\nwrote {path}"
    )


def _tune_command(args: argparse.Namespace) -> None:
    from sb3_dsslac.app.hpo import TuneSpec, summarize_study, tune, write_trials

    hyperparams, env_kwargs, action_repeat = _checked_run_inputs(args, {"device": "--device"})
    if args.timesteps // action_repeat < args.n_evaluations:
        raise InputError(
            f"--timesteps {args.timesteps}: {args.timesteps // action_repeat} agent steps ({args.env} repeats each action "
            f"{action_repeat} simulator steps), fewer than the --n-evaluations {args.n_evaluations} evaluations"
        )
    threads = 1 if args.threads is None else args.threads
    spec = TuneSpec(
        **_experiment_fields(args, args.timesteps, hyperparams, env_kwargs, threads), n_evaluations=args.n_evaluations
    )
    study = tune(
        spec,
        n_trials=args.n_trials,
        storage=args.storage,
        study_name=args.study_name,
        n_startup_trials=args.n_startup_trials,
        sampler_seed=args.sampler_seed,
        total_trials=args.total_trials,
        heartbeat_interval=args.heartbeat_interval,
    )
    print(summarize_study(study))
    if args.out is not None:
        print(f"trials: {write_trials(study, args.out)}")


def main(argv: list[str] | None = None) -> int:
    """
    Run a command; errors of bad input end with a one-line message and exit status 2, a run that could not write its
    folder (a full disk, no permission) with a one-line message and exit status 1.
    """
    args = build_parser().parse_args(argv)
    command = {
        "train": _train_command,
        "plot": _plot_command,
        "evaluate": _evaluate_command,
        "beliefs": _beliefs_command,
        "tune": _tune_command,
    }
    try:
        command[args.command](args)
    except (ValueError, FileNotFoundError, FileExistsError) as error:
        print(error_line(error), file=sys.stderr)
        return 2
    except RunStoppedError as error:
        print(error_line(error), file=sys.stderr)
        return 1
    return 0
