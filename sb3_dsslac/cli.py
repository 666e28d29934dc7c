"""
The thesis's protocol from the command line: ``python -m sb3_dsslac train | plot | evaluate | beliefs | tune``. This
module only parses arguments and dispatches to ``runs``, ``rollouts``, ``plotting``, ``beliefs`` and ``hpo``.

Units: ``--sim-steps`` and every ``*-every`` are simulator steps (the thesis's "environment steps"); DSSLAC counts
agent steps, ``action_repeat`` simulator steps each (2 on the Safety-Gym tasks).
"""

import argparse
import sys
from pathlib import Path
from typing import Any

from sb3_dsslac.dsslac import DSSLAC
from sb3_dsslac.presets import PRESET_ENV_KWARGS, PRESETS
from sb3_dsslac.rollouts import evaluate, format_episodes
from sb3_dsslac.runs import TrainConfig, find_run_config, parse_hyperparams, resume, train

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


def _flag_hyperparams(args: argparse.Namespace) -> dict[str, Any]:
    hyperparams = {name: getattr(args, name) for name in HYPERPARAM_FLAGS if getattr(args, name) is not None}
    return {**hyperparams, **parse_hyperparams(args.hyperparams)}


def _add_model_flags(parser: argparse.ArgumentParser, threads_help: str) -> None:
    preset_envs = "; ".join(
        f"{name} sets {' '.join(f'{key}={value}' for key, value in env_kwargs.items())}"
        for name, env_kwargs in PRESET_ENV_KWARGS.items()
    )
    parser.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default="thesis",
        help="thesis: Table 5.2; thesis_fast: the same with share_latent_batch and bf16; cpu: small and quick; "
        "cpu_learning: the CPU learning benchmark's (state); cpu_pixels: the pixel learning benchmark's (64x64); "
        "cpu_pixels32: the same on 32x32 frames at action repeat 4, the multiplier aiming at cost 20. "
        "Env keywords of the presets (--env-kwargs replaces them): " + (preset_envs or "none"),
    )
    parser.add_argument("--obs-type", choices=["pixels", "state"], help="observation type (default: the env's)")
    parser.add_argument(
        "--env-kwargs",
        nargs="+",
        metavar="KEY=VALUE",
        help="keywords of the env as YAML, on top of the preset's: width=32 height=32 for 32x32 frames",
    )
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda")
    parser.add_argument("--threads", type=int, help=threads_help)
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
    train_parser.add_argument(
        "--deterministic-eval",
        action="store_true",
        help="evaluate with the filter's means and the mean action (default: sampled, the thesis's protocol)",
    )
    train_parser.add_argument("--stochastic-eval", action="store_true", help="the default; kept for old command lines")
    train_parser.add_argument("--checkpoint-every", type=int, default=100_000, help="simulator steps between checkpoints")
    train_parser.add_argument("--n-envs", type=int, default=1, help="training envs, each in its own process")
    train_parser.add_argument("--quiet", action="store_true", help="no logs on stdout")
    train_parser.add_argument("--no-progress-bar", action="store_true")
    _add_model_flags(train_parser, "torch CPU threads (default: torch's; 1 is often fastest on a busy CPU)")

    plot_parser = commands.add_parser("plot", help="learning curves and the normalised score table of runs")
    plot_parser.add_argument("runs", nargs="+", metavar="RUN_DIR")
    plot_parser.add_argument("--out", default=".", help="folder of curves.png, scores.csv and scores.md")

    eval_parser = commands.add_parser("evaluate", help="per-episode reward and cost of a saved model, and a video")
    eval_parser.add_argument("model", help="a saved model (.zip)")
    eval_parser.add_argument("--env", help="env id (default: the model's run's)")
    eval_parser.add_argument("--episodes", type=int, default=10)
    eval_parser.add_argument("--seed", type=int, default=0)
    policy = eval_parser.add_mutually_exclusive_group()
    policy.add_argument("--stochastic", action="store_true", help="sample the filter and the action (the thesis's protocol)")
    policy.add_argument("--deterministic", action="store_true", help="the filter's means and the mean action")
    eval_parser.add_argument("--video", help="video file (.mp4 or .gif)")
    eval_parser.add_argument("--video-episodes", type=int, default=1, help="episodes recorded into the video")
    eval_parser.add_argument("--obs-type", choices=["pixels", "state"])
    eval_parser.add_argument("--device", default="auto")

    beliefs_parser = commands.add_parser(
        "beliefs", help="a pixel agent's frames beside its latent model's reconstructions and predicted cost, as a PNG"
    )
    beliefs_parser.add_argument("model", help="a saved model (.zip) trained on pixels")
    beliefs_parser.add_argument("--env", help="env id (default: the model's run's)")
    beliefs_parser.add_argument("--seed", type=int, default=0, help="seed of the episode")
    beliefs_parser.add_argument("--steps", type=int, help="agent steps to run (default: the whole episode)")
    beliefs_parser.add_argument("--frames", type=int, default=10, help="frames shown")
    beliefs_parser.add_argument("--stochastic", action="store_true", help="sample the filter and the action")
    beliefs_parser.add_argument("--out", default="beliefs.png", help="the PNG")
    beliefs_parser.add_argument("--device", default="auto")

    tune_parser = commands.add_parser("tune", help="Optuna search, maximising eval reward under the cost budget")
    tune_parser.add_argument("--env", required=True)
    tune_parser.add_argument("--timesteps", type=int, required=True, help="simulator steps per trial")
    tune_parser.add_argument("--n-trials", type=int, default=10, help="trials run by this process")
    tune_parser.add_argument(
        "--total-trials",
        type=int,
        help="instead of --n-trials: run trials until the study has this many finished, retrying those of dead workers",
    )
    tune_parser.add_argument(
        "--heartbeat-interval",
        type=int,
        default=60,
        help="seconds between a running trial's heartbeats on an RDB storage; a trial silent for twice this is failed "
        "and retried",
    )
    tune_parser.add_argument("--storage", help="sqlite:///f.db, postgresql://..., or a journal file (*.log, *.journal)")
    tune_parser.add_argument("--study-name", default="dsslac")
    tune_parser.add_argument("--n-evaluations", type=int, default=4, help="evaluations per trial (pruning points)")
    tune_parser.add_argument("--eval-episodes", type=int, default=5)
    tune_parser.add_argument("--n-startup-trials", type=int, default=5, help="random trials before TPE and pruning")
    tune_parser.add_argument("--sampler-seed", type=int, help="seed of TPE (leave unset with several workers)")
    tune_parser.add_argument("--out", help="folder for the trials' CSV")
    _add_model_flags(
        tune_parser,
        "torch CPU threads per worker (default 1, so that several workers on one machine do not oversubscribe its cores)",
    )
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
            env_kwargs=parse_hyperparams(args.env_kwargs, flag="--env-kwargs"),
            eval_every=args.eval_every,
            eval_episodes=args.eval_episodes,
            eval_deterministic=args.deterministic_eval,
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


def _model_and_run(args: argparse.Namespace) -> tuple[str, TrainConfig | None, bool]:
    """The env id of ``args.model`` (``--env``, else its run's), its run's config if any, and whether that run used
    this env."""
    if not Path(args.model).is_file():
        raise FileNotFoundError(f"No model file {args.model}")
    run_config = find_run_config(Path(args.model))
    if args.env is None and run_config is None:
        raise ValueError(f"{args.model} is not in a run folder: pass the env id (--env)")
    env_id = args.env or run_config.env  # type: ignore[union-attr]
    return env_id, run_config, run_config is not None and run_config.env == env_id


def _evaluate_command(args: argparse.Namespace) -> None:
    env_id, run_config, same_env = _model_and_run(args)
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
        env_kwargs=run_config.env_kwargs if same_env else None,  # type: ignore[union-attr]
    )
    print(format_episodes(results, model.cost_limit, deterministic))
    if args.video:
        print(f"video: {args.video}")


def _beliefs_command(args: argparse.Namespace) -> None:
    from sb3_dsslac.beliefs import episode_beliefs, mean_cost_probabilities, plot_beliefs

    env_id, run_config, same_env = _model_and_run(args)
    model = DSSLAC.load(args.model, device=args.device)
    beliefs = episode_beliefs(
        model,
        env_id,
        seed=args.seed,
        max_steps=args.steps,
        deterministic=not args.stochastic,
        env_kwargs=run_config.env_kwargs if same_env else None,  # type: ignore[union-attr]
    )
    path = plot_beliefs(beliefs, args.out, n_frames=args.frames)
    on_costly, on_free = mean_cost_probabilities(beliefs)
    print(
        f"{len(beliefs.costs)} steps, reward {beliefs.rewards.sum():.2f}, cost {beliefs.costs.sum():g}; "
        f"mean predicted p(cost): {on_costly:.3f} on the costly steps, {on_free:.3f} on the others\nwrote {path}"
    )


def _tune_command(args: argparse.Namespace) -> None:
    from sb3_dsslac.hpo import TuneSpec, summarize_study, tune

    spec = TuneSpec(
        env=args.env,
        sim_steps=args.timesteps,
        preset=args.preset,
        hyperparams=_flag_hyperparams(args),
        obs_type=args.obs_type,
        env_kwargs=parse_hyperparams(args.env_kwargs, flag="--env-kwargs"),
        n_evaluations=args.n_evaluations,
        eval_episodes=args.eval_episodes,
        device=args.device,
        threads=1 if args.threads is None else args.threads,
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
        Path(args.out).mkdir(parents=True, exist_ok=True)
        path = Path(args.out) / f"{args.study_name}_trials.csv"
        study.trials_dataframe().to_csv(path, index=False)
        print(f"trials: {path}")


def main(argv: list[str] | None = None) -> int:
    """Run a command; errors of bad input end with a one-line message and exit status 2."""
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
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0
