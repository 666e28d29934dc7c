"""DSSLAC on the real safety_envs tasks: pixels through the 64x64 conv model, SB3 evaluation, state observations,
several tasks in subprocesses."""

from functools import partial

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import SubprocVecEnv

import safety_envs  # noqa: F401
from sb3_dsslac import DSSLAC
from sb3_dsslac.presets import preset_hyperparams
from tests.test_dsslac import SMALL


@pytest.fixture(scope="module")
def pixel_model() -> DSSLAC:
    env = gym.make("SafetyGym/PointGoal1-v0")
    model = DSSLAC("LatentPolicy", env, **{**SMALL, "learning_starts": 30, "train_freq": 15, "gradient_steps": 1})
    model.learn(45)
    return model


def test_pixel_model_uses_the_thesis_episode_and_budget(pixel_model: DSSLAC) -> None:
    assert pixel_model.observation_space.shape == (3, 64, 64)
    assert pixel_model.episode_length == 500 and pixel_model.action_repeat == 2
    assert pixel_model.cost_budget_per_step == pytest.approx(0.05)
    assert pixel_model.discounted_cost_budget == pytest.approx(9.184, abs=1e-3)
    assert pixel_model.latent_pretrained and pixel_model._n_updates == 1  # one burst, after the rollout that ends at 45 > 30


def test_evaluate_policy_on_pixels(pixel_model: DSSLAC) -> None:
    rewards, lengths = evaluate_policy(
        pixel_model, gym.make("SafetyGym/PointGoal1-v0"), n_eval_episodes=1, return_episode_rewards=True, warn=False
    )
    assert lengths == [500] and np.isfinite(rewards).all()


def test_eval_callback_on_pixels(tmp_path) -> None:
    callback = EvalCallback(gym.make("SafetyGym/PointGoal1-v0"), eval_freq=40, n_eval_episodes=1, log_path=str(tmp_path))
    model = DSSLAC("LatentPolicy", gym.make("SafetyGym/PointGoal1-v0"), **{**SMALL, "learning_starts": 30, "train_freq": 20})
    model.learn(40, callback=callback)
    evaluations = np.load(tmp_path / "evaluations.npz")
    assert evaluations["ep_lengths"].tolist() == [[500]]


def test_short_learn_on_state_observations() -> None:
    env = gym.make("SafetyGym/CarGoal1-v0", obs_type="state")
    model = DSSLAC("LatentPolicy", env, **SMALL)
    model.learn(60)
    assert model.observation_space.shape == env.observation_space.shape
    assert model._n_updates == 4


def test_subproc_envs_of_two_tasks_train_with_one_update_per_agent_step() -> None:
    # Two different tasks with the same spaces, each in its own process ("safety_envs:" imports the ids there)
    env = SubprocVecEnv([partial(gym.make, f"safety_envs:SafetyGym/{task}-v0") for task in ("PointGoal1", "PointButton1")])
    model = DSSLAC("LatentPolicy", env, **{**SMALL, "learning_starts": 30, "train_freq": 10, "gradient_steps": 10})
    model.learn(60)
    env.close()
    assert model.num_timesteps == 60
    assert model._n_updates == 30  # bursts after agent steps 40, 50 and 60
    buffer = model.replay_buffer
    assert (buffer.episode_ids[:, 0] >= 0).sum() == (buffer.episode_ids[:, 1] >= 0).sum() == 31  # 30 steps + reset frame


def test_cpu_pixels_preset_trains_the_narrow_conv_model_on_pointgoal1(tmp_path) -> None:
    # About 5 s: the real pixel task's renders and the preset's conv model. Eager updates: compiling them costs minutes
    # of CPU (tests/test_fast_path.py covers the compiled update)
    overrides = {"learning_starts": 40, "latent_pretrain_steps": 2, "train_freq": 20, "buffer_size": 2000}
    overrides["compile_updates"] = False
    hyperparams = preset_hyperparams("cpu_pixels", overrides)
    model = DSSLAC("LatentPolicy", gym.make("SafetyGym/PointGoal1-v0"), seed=0, **hyperparams)
    model.learn(80)
    assert model._n_updates == 2 * hyperparams["gradient_steps"]  # bursts after the rollouts ending at 60 and 80
    convolutions = [layer for layer in model.policy.latent.encoder.modules() if isinstance(layer, th.nn.Conv2d)]
    assert [layer.out_channels for layer in convolutions][:4] == [8, 16, 32, 64]
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip")
    assert loaded.policy.image_channels == (8, 16, 32, 64)
    assert loaded.policy.latent.encoder[0].out_channels == 8
