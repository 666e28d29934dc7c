"""
Bad input stops at the door: each command checks its arguments before any env, model or run folder is made, says what
is wrong in one ``error:`` line naming the flag (exit status 2, no traceback), and a failed start blocks nothing.
"""

import sys
import time
from pathlib import Path

import pytest
import torch as th
import yaml

import sb3_dsslac.app.cli
import sb3_dsslac.app.hpo
from sb3_dsslac import DSSLAC
from sb3_dsslac.app.cli import PRESET_SUMMARIES, main
from sb3_dsslac.app.runs import TrainConfig, train
from sb3_dsslac.common.validation import InputError, check_algorithm, error_line
from sb3_dsslac.presets import PRESETS
from tests.synthetic_envs import HazardPointEnv
from tests.test_cli import TINY_ENV, TINY_FLAGS, run_train
from tests.test_dsslac import SMALL_POLICY

PG1 = "SafetyGym/PointGoal1-v0"
BAD_POLICY_KWARGS = "policy_kwargs={z1_dim: 16"


@pytest.fixture
def no_training(monkeypatch):
    """A bad input that got past the checks fails its test at once instead of training (for 1M steps)."""

    def started(*args, **kwargs):
        raise AssertionError("training started")

    monkeypatch.setattr(sb3_dsslac.app.cli, "train", started)
    monkeypatch.setattr(sb3_dsslac.app.hpo, "tune", started)


@pytest.fixture(scope="module", autouse=True)
def restore_torch_threads():
    """A corrected command sets torch's threads for the process: give the other test modules theirs back."""
    threads = th.get_num_threads()
    yield
    th.set_num_threads(threads)


def refused(capsys, argv: list[str], *named: str) -> str:
    """Run the command as a user types it: exit status 2, one ``error:`` line naming ``named``, no traceback, quickly."""
    start = time.perf_counter()
    try:
        status = main(argv)
    except SystemExit as exit:  # argparse's errors
        status = exit.code
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert status == 2, captured.out + captured.err
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    assert "Traceback" not in captured.err + captured.out
    for name in named:
        assert name in lines[0], lines[0]
    assert time.perf_counter() - start < 30  # a probe of the env at most, no training
    return lines[0]


# Each case of issue 48's "Why", as a user types it: the flags, then what the error line must name
TRAIN_CASES = [
    (["--env", PG1, "--sim-steps", "0"], ["--sim-steps"]),
    (["--env", PG1, "--sim-steps", "-5"], ["--sim-steps"]),
    (["--env", PG1, "--preset", "cpu", "--sim-steps", "1"], ["--sim-steps", "agent step"]),
    (["--env", TINY_ENV, "--hyperparams", "tau=abc"], ["--hyperparams tau"]),
    (["--env", TINY_ENV, "--hyperparams", "batch_size=abc"], ["--hyperparams batch_size"]),
    (["--env", TINY_ENV, "--hyperparams", "no_such_key=1"], ["--hyperparams no_such_key", "valid: ", "batch_size"]),
    (["--env", TINY_ENV, "--hyperparams", BAD_POLICY_KWARGS], ["--hyperparams policy_kwargs", "not valid YAML"]),
    (["--env", PG1, "--env-kwargs", "bogus=1"], ["--env-kwargs bogus", "valid: ", "width"]),
    (["--env", PG1, "--env-kwargs", "width=abc"], ["--env-kwargs width"]),
    (["--env", TINY_ENV, "--threads", "0"], ["--threads"]),
    (["--env", "Pendulum-v1", "--preset", "cpu"], ["--env Pendulum-v1", "info['cost']"]),
    # Further bad inputs of the same kinds
    (["--env", TINY_ENV, "--hyperparams", "policy_kwargs={z1dim: 16}"], ["--hyperparams policy_kwargs z1dim", "z1_dim"]),
    (["--env", TINY_ENV, "--hyperparams", "policy_kwargs={z1_dim: -1}"], ["--hyperparams policy_kwargs z1_dim"]),
    (["--env", TINY_ENV, "--hyperparams", "policy_kwargs=16"], ["--hyperparams policy_kwargs"]),
    (["--env", TINY_ENV, "--hyperparams", "seed=3"], ["--hyperparams seed", "--seed"]),
    (["--env", TINY_ENV, "--hyperparams", "gamma=2"], ["--hyperparams gamma"]),
    (["--env", TINY_ENV, "--hyperparams", "ent_coef=auto_x"], ["--hyperparams ent_coef"]),
    (["--env", TINY_ENV, "--hyperparams", "bf16=fast"], ["--hyperparams bf16"]),
    (["--env", TINY_ENV, "--hyperparams", "tau"], ["--hyperparams", "key=value"]),
    (["--env", TINY_ENV, "--batch-size", "0"], ["--batch-size"]),
    (["--env", TINY_ENV, "--batch-size", "abc"], ["--batch-size"]),
    (["--env", TINY_ENV, "--learning-rate", "-1e-3"], ["--learning-rate"]),
    (["--env", TINY_ENV, "--cost-target", "30"], ["--cost-target"]),
    (
        ["--env", TINY_ENV, "--sequence-length", "2", "--hyperparams", "actor_critic_transitions=3"],
        ["actor_critic_transitions"],
    ),
    (["--env", TINY_ENV, "--seed", "-1"], ["--seed"]),
    (["--env", TINY_ENV, "--eval-seed", "abc"], ["--eval-seed"]),
    (["--env", TINY_ENV, "--eval-every", "0"], ["--eval-every"]),
    (["--env", TINY_ENV, "--eval-episodes", "0"], ["--eval-episodes"]),
    (["--env", TINY_ENV, "--checkpoint-every", "-1"], ["--checkpoint-every"]),
    (["--env", TINY_ENV, "--n-envs", "0"], ["--n-envs"]),
    (["--env", TINY_ENV, "--device", "gpu"], ["--device gpu"]),
    (["--env", TINY_ENV, "--device", "cuda:99"], ["--device cuda:99"]),
    (["--env", TINY_ENV, "--obs-type", "rgb"], ["--obs-type"]),
    (["--env", TINY_ENV, "--preset", "gpu"], ["--preset"]),
    (["--env", "SafetyGym/Nope-v0"], ["--env SafetyGym/Nope-v0"]),
    (["--env", "no_such_module:Env-v0"], ["--env no_such_module:Env-v0"]),
    (["--env", "Pendulum-v1", "--obs-type", "state"], ["--obs-type", "obs_type"]),
    (["--env", PG1, "--env-kwargs", "width=0"], ["--env-kwargs width"]),
    (["--env", PG1, "--preset", "cpu_pixels32", "--env-kwargs", "action_repeat=0"], ["--env-kwargs action_repeat"]),
    (["--env", TINY_ENV, "--env-kwargs", "size: 3"], ["--env-kwargs", "key=value"]),
    (["--env", TINY_ENV, "--env-kwargs", "report_cost=false"], ["--env", "info['cost']"]),
    (["--env", TINY_ENV, "--hyperparams", "replay_buffer_kwargs={foo: 1}"], ["--hyperparams replay_buffer_kwargs foo"]),
    (["--env", TINY_ENV, "--hyperparams", "buffer_size=1e5"], ["--hyperparams buffer_size", "integer"]),
    (["--env", TINY_ENV, "--hyperparams", "compile_updates=1"], ["--hyperparams compile_updates"]),
    (["--env", PG1, "--env-kwargs", "obs_type=rgb"], ["--env-kwargs obs_type"]),
    (["--env", PG1, "--env-kwargs", "max_episode_steps=0"], ["--env-kwargs max_episode_steps"]),
    (["--sim-steps", "10"], ["--env"]),
]


@pytest.mark.parametrize(("flags", "named"), TRAIN_CASES, ids=[" ".join(flags) for flags, _ in TRAIN_CASES])
def test_bad_train_input_stops_before_the_run_folder(
    flags: list[str], named: list[str], tmp_path: Path, capsys, no_training
) -> None:
    out = tmp_path / "run"
    refused(capsys, ["train", *flags, "--out", str(out), "--quiet", "--no-progress-bar"], *named)
    assert not out.exists()
    assert "━" not in capsys.readouterr().out  # no progress bar was started


def test_a_device_that_is_not_there_is_refused(tmp_path: Path, capsys, no_training) -> None:
    if th.cuda.is_available():
        pytest.skip("this machine has CUDA")
    line = refused(capsys, ["train", "--env", TINY_ENV, "--device", "cuda", "--out", str(tmp_path / "run")], "--device cuda")
    assert "cpu" in line
    assert not (tmp_path / "run").exists()


def test_the_corrected_command_runs_in_the_same_out(tmp_path: Path, capsys) -> None:
    out = tmp_path / "run"
    for flags in (["--sim-steps", "0"], ["--hyperparams", "tau=abc"], ["--threads", "0"], ["--env-kwargs", "bogus=1"]):
        refused(capsys, ["train", "--env", TINY_ENV, "--out", str(out), *flags], flags[0])
    assert run_train(out, "--sim-steps=20", "--eval-every=20", "--checkpoint-every=20") == 0
    assert yaml.safe_load((out / "config.yaml").read_text())["sim_steps"] == 20


def test_a_failed_start_leaves_nothing_behind(tmp_path: Path) -> None:
    # Past the command line's checks (the Python API), an env without costs fails at its first step
    out = tmp_path / "run"
    hyperparams = {"learning_starts": 10, "policy_kwargs": {"z1_dim": 4, "z2_dim": 8, "feature_dim": 16}}
    config = TrainConfig(
        env=TINY_ENV,
        sim_steps=20,
        preset="cpu",
        hyperparams=hyperparams,
        env_kwargs={"report_cost": False},
        verbose=0,
        progress_bar=False,
    )
    with pytest.raises(ValueError, match="did not report a cost"):
        train(config, out)
    assert not out.exists()
    # Into a folder that held other files, only what the run added goes
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="did not report a cost"):
        train(config, out)
    assert [path.name for path in out.iterdir()] == ["notes.txt"]


def test_a_folder_without_a_checkpoint_says_how_to_start_again(tmp_path: Path, capsys) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / "config.yaml").write_text("env: x\n")  # a start killed before its first checkpoint
    refused(capsys, ["train", "--env", TINY_ENV, "--out", str(out), *TINY_FLAGS], "delete the folder")


def test_tune_checks_its_flags_before_the_study(tmp_path: Path, capsys, no_training) -> None:
    storage = tmp_path / "study.log"
    tune = ["tune", "--storage", str(storage), "--n-evaluations", "2"]
    refused(capsys, [*tune, "--env", "SafetyGym/Nope-v0", "--timesteps", "100"], "--env SafetyGym/Nope-v0")
    refused(capsys, [*tune, "--env", TINY_ENV, "--timesteps", "0"], "--timesteps")
    refused(capsys, [*tune, "--env", TINY_ENV, "--timesteps", "-5"], "--timesteps")
    refused(capsys, [*tune, "--env", TINY_ENV, "--timesteps", "1"], "--timesteps", "--n-evaluations")
    refused(capsys, [*tune, "--env", TINY_ENV, "--timesteps", "100", "--hyperparams", "tau=abc"], "--hyperparams tau")
    refused(capsys, [*tune, "--env", TINY_ENV, "--timesteps", "100", "--n-trials", "0"], "--n-trials")
    refused(capsys, [*tune, "--env", TINY_ENV, "--timesteps", "100", "--heartbeat-interval", "0"], "--heartbeat-interval")
    refused(capsys, [*tune, "--env", TINY_ENV, "--timesteps", "100", "--sampler-seed", "-2"], "--sampler-seed")
    refused(capsys, [*tune, "--env", TINY_ENV, "--timesteps", "100", "--threads", "0"], "--threads")
    assert not storage.exists()


def test_evaluate_beliefs_and_plot_check_their_flags(tmp_path: Path, capsys) -> None:
    model = tmp_path / "model.zip"
    DSSLAC("LatentPolicy", HazardPointEnv(), learning_starts=10, policy_kwargs={"z1_dim": 4, "z2_dim": 8}).save(model)
    not_a_zip = tmp_path / "notes.zip"
    not_a_zip.write_text("not a model\n")
    for command in ("evaluate", "beliefs"):
        refused(capsys, [command, str(not_a_zip), "--env", TINY_ENV], "MODEL", "not a zip file")
        refused(capsys, [command, str(tmp_path / "nothing.zip"), "--env", TINY_ENV], "MODEL", "no such file")
        refused(capsys, [command, str(model)], "--env")  # outside a run folder
        refused(capsys, [command, str(model), "--env", "SafetyGym/Nope-v0"], "--env SafetyGym/Nope-v0")
        refused(capsys, [command, str(model), "--env", TINY_ENV, "--device", "gpu"], "--device gpu")
        refused(capsys, [command, str(model), "--env", TINY_ENV, "--seed", "-1"], "--seed")
    refused(capsys, ["evaluate", str(model), "--env", TINY_ENV, "--episodes", "0"], "--episodes")
    refused(capsys, ["evaluate", str(model), "--env", TINY_ENV, "--video-episodes", "-1"], "--video-episodes")
    refused(capsys, ["evaluate", str(model), "--env", TINY_ENV, "--video", "agent.avi"], "--video", ".mp4 or .gif")
    refused(capsys, ["beliefs", str(model), "--env", TINY_ENV, "--frames", "0"], "--frames")
    refused(capsys, ["beliefs", str(model), "--env", TINY_ENV, "--steps", "0"], "--steps")
    refused(capsys, ["plot", str(tmp_path / "nope")], "nope")
    refused(capsys, ["plot", str(tmp_path), "--out", str(not_a_zip)], "--out")
    refused(capsys, ["nonsense"], "nonsense")


def test_the_python_api_checks_what_sb3_leaves_to_the_first_update() -> None:
    for keywords, name in (({"tau": "abc"}, "tau"), ({"batch_size": "abc"}, "batch_size"), ({"batch_size": 0}, "batch_size")):
        with pytest.raises(ValueError, match=rf"^{name} must be"):
            DSSLAC("LatentPolicy", HazardPointEnv(), **keywords)
    with pytest.raises(ValueError, match="batch_size must be an integer"):
        DSSLAC("LatentPolicy", HazardPointEnv(), batch_size=64.0)
    # Schedules, train-frequency tuples and the entropy coefficient's forms pass
    keywords = {"learning_rate": lambda progress: 1e-4, "train_freq": (1, "episode"), "ent_coef": "auto_0.1"}
    keywords["buffer_size"] = 100
    DSSLAC("LatentPolicy", HazardPointEnv(), policy_kwargs=SMALL_POLICY, **keywords)


def test_check_algorithm_names_the_flag_and_the_valid_policy_keywords() -> None:
    sources = {"policy_kwargs": "--hyperparams policy_kwargs"}
    with pytest.raises(InputError, match=r"--hyperparams policy_kwargs z1dim: .*did you mean z1_dim"):
        check_algorithm(DSSLAC, "LatentPolicy", {"policy_kwargs": {"z1dim": 4}}, sources, {})
    with pytest.raises(InputError, match=r"--hyperparams policy_kwargs hidden_units: hidden_units must be a list of int"):
        check_algorithm(DSSLAC, "LatentPolicy", {"policy_kwargs": {"hidden_units": ["a"]}}, sources, {})
    check_algorithm(DSSLAC, "LatentPolicy", {"policy_kwargs": {"hidden_units": [8, 8]}}, sources, {})


def test_the_error_line_is_one_line_without_sb3_s_prefix() -> None:
    assert error_line(ValueError("Error: the file x wasn't\na zip-file")) == "error: the file x wasn't a zip-file"


def test_every_preset_passes_the_checks() -> None:
    for name, hyperparams in PRESETS.items():
        check_algorithm(DSSLAC, "LatentPolicy", hyperparams, {name: f"--preset {name}" for name in hyperparams}, {})


def test_train_help_describes_every_preset(capsys) -> None:
    assert set(PRESET_SUMMARIES) == set(PRESETS)
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name in PRESETS:
        assert f"{name}: {' '.join(PRESET_SUMMARIES[name].split())}" in text
    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "tune with Optuna (docs/cli.md)." in text


def test_the_zoo_stops_bad_input_before_its_log_folder(tmp_path: Path, capsys, monkeypatch) -> None:
    pytest.importorskip("rl_zoo3")
    from sb3_dsslac.app.zoo import main as zoo

    monkeypatch.setattr(sys, "argv", ["zoo"])
    config = tmp_path / "tiny.yml"
    config.write_text(yaml.safe_dump({PG1: {"policy": "LatentPolicy", "n_timesteps": 100, "tau": 0.01}}))
    common = ["--algo", "dsslac", "-conf", str(config), "-f", str(tmp_path / "logs")]
    for flags, named in (
        (["--env", "SafetyGym/Nope-v0"], ["--env SafetyGym/Nope-v0"]),
        (["--env", PG1, "--hyperparams", "tau:'abc'"], ["--hyperparams tau"]),
        (["--env", PG1, "--hyperparams", "no_such_key:1"], ["--hyperparams no_such_key", "valid: "]),
        (["--env", PG1, "--env-kwargs", "bogus:1"], ["--env-kwargs bogus"]),
        (["--env", PG1, "--device", "gpu"], ["--device gpu"]),
    ):
        assert zoo(["train", *common, *flags]) == 2
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("error: ") and all(name in lines[0] for name in named), lines
    assert not (tmp_path / "logs").exists()


def test_the_zoo_enjoys_only_a_model_that_is_there(tmp_path: Path, capsys, monkeypatch) -> None:
    pytest.importorskip("rl_zoo3")
    from sb3_dsslac.app.zoo import main as zoo

    monkeypatch.setattr(sys, "argv", ["zoo"])
    run = tmp_path / "logs" / "dsslac" / "SafetyGym-PointGoal1-v0_1"
    run.mkdir(parents=True)
    common = ["--algo", "dsslac", "--env", PG1, "-f", str(tmp_path / "logs"), "--no-render"]
    for flags, named in (
        (["-f", str(tmp_path / "none")], [str(tmp_path / "none" / "dsslac"), "python -m sb3_dsslac.zoo train"]),
        (["--exp-id", "2"], ["SafetyGym-PointGoal1-v0_2", "not found"]),
        (["--exp-id", "1"], [str(run / "SafetyGym-PointGoal1-v0.zip")]),  # the folder without its model
        (["--exp-id", "1", "--load-best"], ["best_model.zip"]),
    ):
        assert zoo(["enjoy", *common, *flags]) == 2
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("error: no dsslac model to enjoy") and all(n in lines[0] for n in named)


def test_resume_refuses_the_flags_it_would_ignore(capsys, no_training, tmp_path) -> None:
    error = refused(capsys, ["train", "--resume", str(tmp_path), "--seed", "3", "--threads", "2"], "--seed", "--threads")
    assert "config.yaml" in error
    refused(capsys, ["train", "--resume", str(tmp_path), "--hyperparams", "tau=0.01"], "--hyperparams")


def test_evaluate_and_beliefs_refuse_an_env_the_model_does_not_fit(tmp_path: Path, capsys) -> None:
    model = tmp_path / "pixels.zip"
    env = HazardPointEnv(obs_type="pixels", size=32)
    DSSLAC("LatentPolicy", env, learning_starts=10, policy_kwargs={"z1_dim": 4, "z2_dim": 8}).save(model)
    refused(capsys, ["evaluate", str(model), "--env", TINY_ENV], "--env", "--obs-type pixels")  # the env's state
    smaller = ["--env", TINY_ENV, "--env-kwargs", "size=16"]
    refused(capsys, ["evaluate", str(model), *smaller, "--obs-type", "pixels"], "16x16", "32x32", "width=32 height=32")
    refused(capsys, ["beliefs", str(model), *smaller, "--out", str(tmp_path / "b.png")], "16x16", "32x32")
    for command in ("evaluate", "beliefs"):
        refused(capsys, [command, str(model), "--env", TINY_ENV, "--env-kwargs", "colour=red"], "--env-kwargs colour")
    assert not (tmp_path / "b.png").exists()
    # the keywords reach the env: the model runs where its frames fit
    assert (
        main(["evaluate", str(model), "--env", TINY_ENV, "--obs-type", "pixels", "--env-kwargs", "size=32", "--episodes", "1"])
        == 0
    )
