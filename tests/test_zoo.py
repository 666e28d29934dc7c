"""rl-zoo3 with DS-SLAC: the shipped hyperparameter files, the -optimize sampler, and a tiny train then enjoy."""

import inspect
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import optuna
import pytest
import yaml

from sb3_dsslac import DSSLAC
from sb3_dsslac.common.policies import SHARED_POLICY_KEYWORDS
from sb3_dsslac.presets import PRESETS

REPO = Path(__file__).resolve().parents[1]
SG6 = ["PointGoal1", "PointGoal2", "CarGoal1", "PointButton1", "PointPush1", "DoggoGoal1"]
TINY = {
    "policy": "LatentPolicy",
    "n_timesteps": 200,
    "buffer_size": 2000,
    "learning_starts": 100,
    "latent_pretrain_steps": 2,
    "batch_size": 8,
    "latent_batch_size": 4,
    "sequence_length": 3,
    "train_freq": 50,
    "gradient_steps": 1,
    "n_quantiles": 8,
    "policy_kwargs": "dict(z1_dim=4, z2_dim=8, feature_dim=16, hidden_units=[32, 32], n_cosines=8, cost_critic_hidden_dim=32)",
}


def test_the_thesis_file_is_table_5_2_on_the_sg6_tasks() -> None:
    config = yaml.safe_load((REPO / "hyperparams" / "dsslac.yml").read_text())
    defaults = {name: parameter.default for name, parameter in inspect.signature(DSSLAC.__init__).parameters.items()}
    # Keywords that default to None take the reference's value; the thesis preset adds the step-size milestone
    defaults.update(SHARED_POLICY_KEYWORDS, **PRESETS["thesis"])
    for task in SG6:
        hyperparams = dict(config[f"SafetyGym/{task}-v0"])
        # 1M simulator steps (2M for DoggoGoal1) at action repeat 2
        assert hyperparams.pop("n_timesteps") == (1_000_000 if task == "DoggoGoal1" else 500_000)
        assert hyperparams.pop("policy") == "LatentPolicy"
        assert hyperparams == {name: defaults[name] for name in hyperparams}, task


def test_the_cpu_file_is_the_cpu_preset() -> None:
    config = yaml.safe_load((REPO / "hyperparams" / "dsslac_cpu.yml").read_text())
    for task in SG6:
        hyperparams = dict(config[f"SafetyGym/{task}-v0"])
        del hyperparams["n_timesteps"], hyperparams["policy"]
        hyperparams["policy_kwargs"] = eval(hyperparams["policy_kwargs"])  # the zoo evaluates this string too
        assert hyperparams == PRESETS["cpu"], task


def test_the_zoo_sampler_and_its_converter_agree() -> None:
    pytest.importorskip("rl_zoo3")
    from sb3_dsslac.app.zoo import convert_zoo_params, sample_zoo_params

    trial = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0)).ask()
    sampled = sample_zoo_params(trial, n_actions=2, n_envs=1, additional_args={})
    assert 0.95 <= sampled["gamma"] < 1.0 and sampled["batch_size"] in (16, 32, 64, 128)
    assert convert_zoo_params(trial.params) == sampled


def test_zoo_trains_and_enjoys_dsslac_with_cost(tmp_path: Path) -> None:
    # About 12 s: rl-zoo3's train and enjoy, each its own process importing the zoo, torch and MuJoCo
    pytest.importorskip("rl_zoo3")
    (tmp_path / "tiny.yml").write_text(yaml.safe_dump({"SafetyGym/PointGoal1-v0": TINY}))
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    common = ["--algo", "dsslac", "--env", "SafetyGym/PointGoal1-v0", "-f", str(tmp_path / "logs"), "--device", "cpu"]
    common += ["--env-kwargs", "obs_type:'state'"]

    def zoo(*flags: str) -> str:
        command = [sys.executable, "-m", "sb3_dsslac.zoo", *flags, *common]
        done = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
        return done.stdout

    trained = zoo("train", "-conf", str(tmp_path / "tiny.yml"), "--eval-freq", "100", "--eval-episodes", "1", "--seed", "0")
    assert "mean_cost" in trained and "episode_cost=" in trained
    run = tmp_path / "logs" / "dsslac" / "SafetyGym-PointGoal1-v0_1"
    for name in ("SafetyGym-PointGoal1-v0.zip", "best_model.zip", "SafetyGym-PointGoal1-v0/config.yml"):
        assert (run / name).is_file(), name
    evaluations = np.load(run / "evaluations.npz")
    assert evaluations["timesteps"].tolist() == [100, 200] and evaluations["costs"].shape == (2, 1)
    assert DSSLAC.load(run / "SafetyGym-PointGoal1-v0.zip").num_timesteps == 200

    enjoyed = zoo("enjoy", "--exp-id", "1", "-n", "600", "--no-render")
    assert "Episode Length 500" in enjoyed and "Mean reward:" in enjoyed
