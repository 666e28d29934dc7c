"""The command line end to end on a tiny env: train, resume after a kill, plot, evaluate with a video, bad input."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch as th
import yaml

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.cli import main
from sb3_dsslac.app.rollouts import side_by_side
from sb3_dsslac.app.runs import TrainConfig, find_checkpoint, load_config, parse_hyperparams, train
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import small_model

TINY_ENV = "tests.registered_envs:HazardPoint-v0"  # 30-step episodes, action_repeat 1
TINY_FLAGS = [
    "--learning-starts=40",
    "--latent-pretrain-steps=3",
    "--batch-size=8",
    "--latent-batch-size=4",
    "--sequence-length=3",
    "--train-freq=10",
    "--gradient-steps=2",
    "--n-quantiles=8",
    "--threads=1",
    "--hyperparams",
    "buffer_size=2000",
    "policy_kwargs={z1_dim: 4, z2_dim: 8, feature_dim: 16, hidden_units: [32, 32], n_cosines: 8, cost_critic_hidden_dim: 32}",
]


@pytest.fixture(scope="module", autouse=True)
def restore_torch_threads():
    """--threads sets torch's threads for the process: give the other test modules theirs back."""
    threads = th.get_num_threads()
    yield
    th.set_num_threads(threads)


def run_train(out: Path, *flags: str) -> int:
    return main(
        [
            "train",
            "--env",
            TINY_ENV,
            "--out",
            str(out),
            "--quiet",
            "--no-progress-bar",
            "--eval-episodes=2",
            *flags,
            *TINY_FLAGS,
        ]
    )


def progress_steps(run_dir: Path) -> list[int]:
    return pd.read_csv(run_dir / "progress.csv")["time/total_timesteps"].astype(int).tolist()


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "tiny"
    assert run_train(out, "--sim-steps=120", "--eval-every=40", "--checkpoint-every=60") == 0
    return out


def test_train_writes_the_run_folder(trained_run: Path) -> None:
    for name in ("config.yaml", "progress.csv", "evaluations.npz", "model.zip", "best_model.zip"):
        assert (trained_run / name).is_file(), name
    assert list(trained_run.glob("events.out.tfevents.*"))
    config = yaml.safe_load((trained_run / "config.yaml").read_text())
    assert config["sim_steps"] == 120 and config["eval_deterministic"] is False
    assert config["resolved"]["eval_env"] == "separate env, seed 10000, stochastic policy"
    assert config["resolved"]["dsslac"]["episode_length"] == 30
    evaluations = np.load(trained_run / "evaluations.npz")
    assert evaluations["timesteps"].tolist() == [40, 80, 120]
    assert evaluations["costs"].shape == (3, 2)
    # Only the newest checkpoint is kept, with its replay buffer and the marker written last
    assert sorted(path.name for path in (trained_run / "checkpoints").iterdir()) == [
        "dsslac_120_steps.json",
        "dsslac_120_steps.zip",
        "dsslac_replay_buffer_120_steps.pkl",
    ]
    assert DSSLAC.load(trained_run / "model.zip").num_timesteps == 120


def test_train_with_several_envs_keeps_the_evaluation_grid(tmp_path: Path) -> None:
    out = tmp_path / "two_envs"
    assert run_train(out, "--sim-steps=120", "--eval-every=40", "--checkpoint-every=60", "--n-envs=2") == 0
    assert np.load(out / "evaluations.npz")["timesteps"].tolist() == [40, 80, 120]
    assert yaml.safe_load((out / "config.yaml").read_text())["n_envs"] == 2
    model = DSSLAC.load(out / "model.zip")
    assert model.num_timesteps == 120 and model._n_updates == 2 * len(range(50, 121, 10))


class Killed(Exception):
    """Stands in for the process being killed."""


def test_resume_after_a_kill_continues_from_the_last_checkpoint(tmp_path: Path, monkeypatch) -> None:
    out = tmp_path / "run"
    original_train = DSSLAC.train

    def train_then_die(self: DSSLAC, gradient_steps: int, batch_size: int) -> None:
        if self.num_timesteps >= 75:
            raise Killed
        original_train(self, gradient_steps, batch_size)

    monkeypatch.setattr(DSSLAC, "train", train_then_die)
    with pytest.raises(Killed):
        run_train(out, "--sim-steps=100", "--eval-every=30", "--checkpoint-every=50")
    monkeypatch.undo()
    assert not (out / "model.zip").exists()
    assert find_checkpoint(out).timesteps == 50  # type: ignore[union-attr]
    before = np.load(out / "evaluations.npz")
    assert before["timesteps"].tolist() == [30, 60]
    assert progress_steps(out) == [30, 60]

    assert main(["train", "--resume", str(out), "--no-progress-bar"]) == 0
    assert DSSLAC.load(out / "model.zip").num_timesteps == 100
    after = np.load(out / "evaluations.npz")
    # The evaluation before the checkpoint is kept as it was; the later ones are redone on the same grid
    assert after["timesteps"].tolist() == [30, 60, 90]
    np.testing.assert_array_equal(after["results"][0], before["results"][0])
    assert progress_steps(out) == [30, 60, 90]
    assert find_checkpoint(out).timesteps == 100  # type: ignore[union-attr]
    # Resuming a finished run from its last checkpoint changes nothing
    assert main(["train", "--resume", str(out), "--no-progress-bar"]) == 0
    assert progress_steps(out) == [30, 60, 90]


def test_resume_needs_a_checkpoint(tmp_path: Path, capsys) -> None:
    out = tmp_path / "run"
    assert run_train(out, "--sim-steps=20", "--eval-every=20", "--checkpoint-every=1000") == 0
    assert main(["train", "--resume", str(out)]) == 2
    assert "No checkpoint" in capsys.readouterr().err


def test_plot_writes_curves_and_the_score_table(trained_run: Path, tmp_path: Path, capsys) -> None:
    assert main(["plot", str(trained_run), str(trained_run), "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "| task | runs |" in printed
    assert (tmp_path / "curves.png").stat().st_size > 10_000
    table = pd.read_csv(tmp_path / "scores.csv")
    evaluations = np.load(trained_run / "evaluations.npz")
    assert table.loc[0, "task"] == TINY_ENV and table.loc[0, "runs"] == 2
    assert table.loc[0, "Jr"] == pytest.approx(evaluations["results"][-1].mean())
    assert np.isnan(table.loc[0, "Jr_bar"])  # no PPO reference for this env
    assert (tmp_path / "scores.md").read_text().startswith("| task |")


def test_train_evaluates_with_the_thesis_protocol_unless_told(tmp_path: Path, monkeypatch, capsys) -> None:
    import sb3_dsslac.common.evaluation

    asked = []
    original = sb3_dsslac.common.evaluation.evaluate_policy_with_cost

    def spy(model, env, n_eval_episodes, deterministic):
        asked.append(deterministic)
        return original(model, env, n_eval_episodes, deterministic)

    monkeypatch.setattr(sb3_dsslac.common.evaluation, "evaluate_policy_with_cost", spy)
    for name, flags, deterministic in (
        ("default", [], False),
        ("old_flag", ["--stochastic-eval"], False),
        ("deterministic", ["--deterministic-eval"], True),
    ):
        asked.clear()
        assert run_train(tmp_path / name, "--sim-steps=20", "--eval-every=20", "--checkpoint-every=1000", *flags) == 0
        assert asked == [deterministic], name
        config = yaml.safe_load((tmp_path / name / "config.yaml").read_text())
        assert config["eval_deterministic"] is deterministic
        assert config["resolved"]["eval_env"].endswith(("deterministic" if deterministic else "stochastic") + " policy")
    # evaluate follows the protocol of the model's run unless told
    capsys.readouterr()
    assert main(["evaluate", str(tmp_path / "deterministic" / "model.zip"), "--episodes", "1"]) == 0
    assert capsys.readouterr().out.startswith("policy: deterministic\n")
    # A run folder from before the field existed was evaluated deterministically
    config_path = tmp_path / "default" / "config.yaml"
    saved = yaml.safe_load(config_path.read_text())
    del saved["eval_deterministic"]
    config_path.write_text(yaml.safe_dump(saved))
    assert load_config(tmp_path / "default").eval_deterministic is True


def test_evaluate_says_which_policy(trained_run: Path, capsys, monkeypatch) -> None:
    import sb3_dsslac.app.cli

    used = []
    original = sb3_dsslac.app.cli.evaluate
    monkeypatch.setattr(
        sb3_dsslac.app.cli,
        "evaluate",
        lambda *args, **kwargs: used.append(kwargs["deterministic"]) or original(*args, **kwargs),
    )
    for flags, deterministic in (([], False), (["--deterministic"], True), (["--stochastic"], False)):
        assert main(["evaluate", str(trained_run / "model.zip"), "--episodes", "1", *flags]) == 0
        assert capsys.readouterr().out.splitlines()[0] == f"policy: {'deterministic' if deterministic else 'stochastic'}"
        assert used[-1] is deterministic


def test_evaluate_prints_episodes(trained_run: Path, capsys) -> None:
    assert main(["evaluate", str(trained_run / "model.zip"), "--episodes", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()[1:]
    assert lines[0].split() == ["episode", "reward", "cost", "length"]
    assert [line.split()[0] for line in lines[1:5]] == ["0", "1", "2", "mean"]
    assert all(line.split()[3] == "30" for line in lines[1:4])
    assert lines[5].startswith("episodes within the budget 25: ")


def test_evaluate_writes_a_video_of_both_views(tmp_path: Path, capsys) -> None:
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v3 as iio

    model = small_model(HazardPointEnv(obs_type="pixels"))
    model.save(tmp_path / "pixels.zip")
    video = tmp_path / "agent.mp4"
    flags = ["--env", TINY_ENV, "--obs-type", "pixels", "--episodes", "2", "--video", str(video)]
    assert main(["evaluate", str(tmp_path / "pixels.zip"), *flags]) == 0
    assert f"video: {video}" in capsys.readouterr().out
    frames = iio.imread(video, index=None)
    # The first episode only (30 steps); the 32x32 observation left of the 32x32 render
    assert frames.shape == (30, 32, 64, 3)


def test_side_by_side_upscales_the_first_person_view() -> None:
    observation = np.full((64, 64, 3), 7, np.uint8)
    frame = side_by_side(observation, np.zeros((256, 256, 3), np.uint8))
    assert frame.shape == (256, 512, 3)
    assert (frame[:, :256] == 7).all() and (frame[:, 256:] == 0).all()
    assert side_by_side(np.zeros(4, np.float32), np.zeros((8, 8, 3), np.uint8)).shape == (8, 8, 3)


def test_bad_input_gives_clear_errors(tmp_path: Path, capsys) -> None:
    assert main(["train", "--env", "NoSuchEnv-v0", "--out", str(tmp_path / "x"), "--sim-steps=10"]) == 2
    assert "--env NoSuchEnv-v0: no registered env" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert main(["train", "--resume", str(tmp_path / "missing")]) == 2
    assert "No run folder" in capsys.readouterr().err
    assert main(["plot", str(tmp_path)]) == 2
    assert "is not a run folder" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "nothing.zip"), "--env", TINY_ENV]) == 2
    with pytest.raises(ValueError, match="Unknown preset"):
        TrainConfig(env=TINY_ENV, preset="gpu")


def test_hyperparams_read_exponent_floats_as_python_does() -> None:
    # YAML 1.1 alone reads "1e-6" as a string, which then failed deep inside the model
    parsed = parse_hyperparams(["lagrange_init=1e-6", "a=3E+2", "b=2.5e-4", "c=7", "d=1_000", "e=e5", "f={lr: 1e-3}"])
    assert parsed == {"lagrange_init": 1e-6, "a": 300.0, "b": 2.5e-4, "c": 7, "d": 1000, "e": "e5", "f": {"lr": 1e-3}}
    assert isinstance(parsed["lagrange_init"], float) and isinstance(parsed["c"], int)
    assert yaml.safe_load("x: 1e-6")["x"] == "1e-6"  # the plain loader is untouched


def test_train_refuses_to_overwrite_a_run(trained_run: Path) -> None:
    with pytest.raises(FileExistsError, match="resume"):
        train(TrainConfig(env=TINY_ENV, sim_steps=10), trained_run)


def test_pixels_safety_gym_run(tmp_path: Path, capsys) -> None:
    """
    A few steps of the real pixel task through the command line at 32x32 (``--env-kwargs``): sim steps become agent
    steps (action repeat 2), and ``evaluate`` and ``beliefs`` make the run's own 32x32 env.
    """
    # About 5 s: the real pixel task rendered, trained and evaluated through the whole command
    out = tmp_path / "pg1"
    flags = ["--sim-steps=120", "--eval-every=120", "--eval-episodes=1", "--checkpoint-every=120", "--preset=cpu"]
    assert (
        main(
            [
                "train",
                "--env",
                "SafetyGym/PointGoal1-v0",
                "--out",
                str(out),
                "--quiet",
                "--no-progress-bar",
                *flags,
                "--env-kwargs",
                "width=32",
                "height=32",
                "--learning-starts=40",
                "--latent-pretrain-steps=2",
                "--train-freq=20",
                "--gradient-steps=1",
                "--threads=1",
            ]
        )
        == 0
    )
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["resolved"]["action_repeat"] == 2 and config["resolved"]["agent_steps"] == 60
    assert config["env_kwargs"] == {"width": 32, "height": 32}
    assert config["resolved"]["observation_space"] == "Box(0, 255, (32, 32, 3), uint8)"
    evaluations = np.load(out / "evaluations.npz")
    assert evaluations["timesteps"].tolist() == [60]
    assert evaluations["ep_lengths"].tolist() == [[500]]
    capsys.readouterr()
    assert main(["evaluate", str(out / "model.zip"), "--episodes=1"]) == 0
    assert "episodes within the budget 25: " in capsys.readouterr().out
    assert main(["beliefs", str(out / "model.zip"), "--steps=6", "--frames=3", "--out", str(tmp_path / "b.png")]) == 0
    assert (tmp_path / "b.png").read_bytes()[:4] == b"\x89PNG"


def test_presets_carry_their_env_keywords() -> None:
    assert TrainConfig(env=TINY_ENV, preset="cpu_pixels32").env_kwargs == {"width": 32, "height": 32, "action_repeat": 4}
    assert TrainConfig(env=TINY_ENV, preset="cpu_pixels32", env_kwargs={"width": 64, "height": 64}).env_kwargs == {
        "width": 64,
        "height": 64,
        "action_repeat": 4,
    }
    assert TrainConfig(env=TINY_ENV, preset="cpu_pixels").env_kwargs == {}
    with pytest.raises(ValueError, match="env_kwargs must be a mapping"):
        TrainConfig(env=TINY_ENV, env_kwargs=["width=32"])  # type: ignore[arg-type]


def test_train_help_names_the_presets_env_keywords(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    assert "cpu_pixels32 sets width=32 height=32 action_repeat=4" in " ".join(capsys.readouterr().out.split())
