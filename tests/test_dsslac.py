"""DSSLAC on tiny envs: learning loop, logging, filter state, save/load and bad input."""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import configure

from sb3_dsslac import DSSLAC, LagrangeCallback, LatentPolicy, SequenceReplayBuffer
from sb3_dsslac.engine.bursts import record_burst
from tests.synthetic_envs import HazardPointEnv

DATA = Path(__file__).parent / "data"

SMALL_POLICY = dict(z1_dim=4, z2_dim=8, feature_dim=16, hidden_units=(32, 32), n_cosines=8, cost_critic_hidden_dim=32)
SMALL = dict(
    buffer_size=2_000,
    learning_starts=40,
    latent_pretrain_steps=3,
    batch_size=8,
    latent_batch_size=4,
    sequence_length=3,
    train_freq=10,
    gradient_steps=2,
    n_quantiles=8,
    policy_kwargs=SMALL_POLICY,
    seed=0,
)


def small_model(env: gym.Env, **overrides) -> DSSLAC:
    return DSSLAC("LatentPolicy", env, **{**SMALL, **overrides})


@pytest.mark.parametrize("obs_type", ["state", "pixels"])
def test_learn_logs_every_key(obs_type: str, tmp_path) -> None:
    model = small_model(HazardPointEnv(obs_type=obs_type))
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(100, log_interval=1)
    assert isinstance(model.policy, LatentPolicy)
    assert isinstance(model.replay_buffer, SequenceReplayBuffer)
    assert model.latent_pretrained
    assert model._n_updates == 2 * 6  # bursts after steps 50, 60, ..., 100
    header = (tmp_path / "progress.csv").read_text().splitlines()[0].split(",")
    expected = {
        "rollout/ep_cost_mean",
        "rollout/cost_rate",
        "train/kl",
        "train/kl_max",
        "train/prior_std_min",
        "train/posterior_std_min",
        "train/z_abs_max",
        "train/reconstruction_abs_max",
        "train/image_loss",
        "train/reward_loss",
        "train/cost_loss",
        "train/critic_loss",
        "train/cost_critic_loss",
        "train/actor_loss",
        "train/ent_coef",
        "train/lagrange_multiplier",
        "train/cost_value",
        "time/sim_steps",
    }
    assert expected <= set(header)


def test_burst_extremes_hold_until_the_logger_writes(tmp_path) -> None:
    logger = configure(str(tmp_path), ["csv"])
    record_burst(logger, {"kl": 40.0, "kl_max": 1e12, "prior_std_min": 1e-5})
    record_burst(logger, {"kl": 45.0, "kl_max": 50.0, "prior_std_min": 0.3})
    logged = logger.name_to_value
    # A spike in an earlier burst is kept; a mean is the last burst's
    assert (logged["train/kl"], logged["train/kl_max"], logged["train/prior_std_min"]) == (45.0, 1e12, 1e-5)
    logger.dump(1)
    record_burst(logger, {"kl": 42.0, "kl_max": 48.0, "prior_std_min": 0.2})
    assert (logged["train/kl_max"], logged["train/prior_std_min"]) == (48.0, 0.2)


def test_discount_polyak_factor_and_batch_sizes_changed_on_the_model_reach_the_updates() -> None:
    model = small_model(HazardPointEnv())
    model.learn(50)
    critic, target = model.policy.critic, model.policy.critic_target
    model.tau, model.gamma, model.batch_size, model.latent_batch_size = 0.0, 0.5, 5, 3
    weights, targets = [p.clone() for p in critic.parameters()], [p.clone() for p in target.parameters()]
    model.learn(10, reset_num_timesteps=False)  # one burst
    step = model.updates.step
    assert (step.config.gamma, step.config.tau, step.config.batch_size, step.config.latent_batch_size) == (0.5, 0.0, 5, 3)
    assert any(not th.equal(p, q) for p, q in zip(critic.parameters(), weights, strict=True))
    assert all(th.equal(p, q) for p, q in zip(target.parameters(), targets, strict=True))  # tau 0: targets stay


def test_pretraining_runs_once_across_resumed_learns(monkeypatch) -> None:
    model = small_model(HazardPointEnv())
    calls = []
    original = model._pretrain_latent
    monkeypatch.setattr(model, "_pretrain_latent", lambda: calls.append(1) or original())
    model.learn(60)
    model.learn(40, reset_num_timesteps=False)
    assert calls == [1]
    assert model.num_timesteps == 100


def test_warmup_actions_advance_the_training_filter() -> None:
    model = small_model(HazardPointEnv(), learning_starts=1_000)
    model.learn(7)
    z2, previous_action, memory = model._last_filter_state
    assert z2.shape == (1, SMALL_POLICY["z2_dim"]) and th.count_nonzero(z2) > 0
    assert memory.shape == (1, 0)  # no actor-critic memory by default
    # The filter's previous action is the random action the buffer stored for the last step
    record = model.replay_buffer
    assert model._last_episode_starts.tolist() == [False]
    assert np.abs(previous_action.cpu().numpy()).max() <= 1.0
    assert record.can_sample()


def test_evaluation_leaves_the_training_filter_alone() -> None:
    model = small_model(HazardPointEnv(obs_type="pixels"))
    model.learn(50)
    before = [t.clone() for t in model._last_filter_state]
    eval_env = HazardPointEnv(obs_type="pixels")
    _, lengths = evaluate_policy(model, eval_env, n_eval_episodes=2, return_episode_rewards=True)
    assert lengths == [30, 30]
    after = model._last_filter_state
    assert all(th.equal(a, b) for a, b in zip(before, after, strict=True))


def test_eval_callback_runs_during_learning(tmp_path) -> None:
    eval_env = HazardPointEnv(obs_type="pixels")
    callback = EvalCallback(eval_env, eval_freq=45, n_eval_episodes=1, log_path=str(tmp_path), verbose=0)
    model = small_model(HazardPointEnv(obs_type="pixels"))
    model.learn(90, callback=callback)
    evaluations = np.load(tmp_path / "evaluations.npz")
    assert evaluations["results"].shape == (2, 1)
    assert np.all(evaluations["ep_lengths"] == 30)


def test_predict_carries_the_filter_state() -> None:
    model = small_model(HazardPointEnv(obs_type="pixels"))
    env = HazardPointEnv(obs_type="pixels")
    obs, _ = env.reset(seed=1)
    action, state = model.predict(obs, deterministic=True)
    assert action.shape == (2,) and env.action_space.contains(action.astype(np.float32))
    assert state[0].shape == (1, SMALL_POLICY["z2_dim"])
    obs, *_ = env.step(action)
    continued, _ = model.predict(obs, state=state, episode_start=np.array([False]), deterministic=True)
    restarted, _ = model.predict(obs, state=state, episode_start=np.array([True]), deterministic=True)
    fresh, _ = model.predict(obs, deterministic=True)
    np.testing.assert_allclose(restarted, fresh, rtol=1e-6)
    assert not np.allclose(continued, restarted)


def test_lagrange_callback_raises_multiplier_over_budget_and_lowers_it_under() -> None:
    always_unsafe = HazardPointEnv()
    always_unsafe.hazard_radius = 10.0  # every step costs 1, far over a budget of 1 per 30-step episode
    model = small_model(always_unsafe, cost_limit=1.0, lagrange_learning_rate=1e-2, learning_starts=20, gradient_steps=1)
    start = model.lagrange_multiplier
    model.learn(60)
    assert model.lagrange_multiplier > start

    never_unsafe = HazardPointEnv()
    never_unsafe.hazard_radius = 0.0
    model = small_model(never_unsafe, cost_limit=20.0, lagrange_learning_rate=1e-2, learning_starts=20, gradient_steps=1)
    model.learn(60)
    assert model.lagrange_multiplier < start


def test_cost_target_below_the_limit_moves_the_multiplier_and_leaves_the_limit_to_the_evaluations() -> None:
    always_unsafe = HazardPointEnv()
    always_unsafe.hazard_radius = 10.0  # 30 per 30-step episode: under a limit of 40, over a target of 10
    settings = {"lagrange_learning_rate": 1e-2, "learning_starts": 20, "gradient_steps": 1}
    free = small_model(always_unsafe, cost_limit=40.0, **settings)
    start = free.lagrange_multiplier
    free.learn(60)
    assert free.lagrange_multiplier < start
    held = small_model(always_unsafe, cost_limit=40.0, cost_target=10.0, **settings)
    held.learn(60)
    assert held.lagrange_multiplier > start
    assert held.cost_limit == 40.0 and held.cost_budget_per_step == pytest.approx(10.0 / 30)
    with pytest.raises(ValueError, match="cost_target"):
        small_model(HazardPointEnv(), cost_limit=25.0, cost_target=30.0)


def test_learn_attaches_exactly_one_lagrange_callback() -> None:
    model = small_model(HazardPointEnv())
    callback = model._init_callback(None)
    assert sum(isinstance(c, LagrangeCallback) for c in callback.callbacks) == 1
    mine = LagrangeCallback()
    callback = model._init_callback([mine])
    assert [c for c in callback.callbacks if isinstance(c, LagrangeCallback)] == [mine]


def test_save_load_round_trip(tmp_path) -> None:
    env = HazardPointEnv(obs_type="pixels")
    model = small_model(env)
    model.learn(60)
    model.lagrange_raw.fill_(0.7)
    path = tmp_path / "model.zip"
    model.save(path)
    loaded = DSSLAC.load(path, env=HazardPointEnv(obs_type="pixels"))

    obs = np.stack([HazardPointEnv(obs_type="pixels").reset(seed=s)[0] for s in range(3)])
    z2 = np.random.default_rng(0).normal(size=(3, SMALL_POLICY["z2_dim"])).astype(np.float32)
    state = (z2, np.zeros((3, 2), np.float32))
    starts = np.array([True, False, False])
    expected, expected_state = model.predict(obs, state=state, episode_start=starts, deterministic=True)
    actual, actual_state = loaded.predict(obs, state=state, episode_start=starts, deterministic=True)
    np.testing.assert_array_equal(expected, actual)
    np.testing.assert_array_equal(expected_state[0], actual_state[0])

    assert loaded.lagrange_multiplier == pytest.approx(model.lagrange_multiplier)
    assert th.equal(loaded.log_ent_coef.cpu(), model.log_ent_coef.cpu())
    assert loaded.latent_pretrained and loaded.num_timesteps == 60
    for name in ("latent_optimizer", "actor_optimizer", "critic_optimizer", "cost_critic_optimizer"):
        saved, restored = getattr(model.policy, name).state_dict(), getattr(loaded.policy, name).state_dict()
        assert saved["state"].keys() == restored["state"].keys() and len(saved["state"]) > 0
        for key in saved["state"]:
            assert th.equal(saved["state"][key]["exp_avg"], restored["state"][key]["exp_avg"])
    steps = [m.ent_coef_optimizer.state_dict()["state"][0]["step"] for m in (model, loaded)]
    assert steps[0] == steps[1] > 0


def test_a_model_and_buffer_saved_before_the_package_had_folders_load_and_train_on() -> None:
    """Saved by the flat layout, whose pickles name ``sb3_dsslac.policies``, ``.buffers`` and ``.timing``."""
    expected = np.load(DATA / "dsslac_flat_layout_predictions.npz")
    model = DSSLAC.load(DATA / "dsslac_flat_layout.zip", env=HazardPointEnv(obs_type="pixels"))
    state = (expected["z2"], np.zeros((3, 2), np.float32))
    actions, next_state = model.predict(expected["obs"], state=state, episode_start=expected["starts"], deterministic=True)
    np.testing.assert_allclose(actions, expected["actions"], atol=1e-5)
    np.testing.assert_allclose(next_state[0], expected["z2_next"], atol=1e-5)
    assert model.lagrange_raw.item() == pytest.approx(0.7) and model.time_account.summary()

    model.load_replay_buffer(DATA / "dsslac_flat_layout_buffer.pkl")
    assert isinstance(model.replay_buffer, SequenceReplayBuffer) and model.replay_buffer.size() > 0
    model.learn(20, reset_num_timesteps=False)
    assert model.num_timesteps == 80


def test_replay_buffer_save_load(tmp_path) -> None:
    model = small_model(HazardPointEnv())
    model.learn(45)
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    other = small_model(HazardPointEnv())
    other.load_replay_buffer(tmp_path / "buffer.pkl")
    assert isinstance(other.replay_buffer, SequenceReplayBuffer)
    assert other.replay_buffer.nbytes == model.replay_buffer.nbytes


def test_frames_are_stored_in_the_layout_of_the_convolutions(tmp_path, monkeypatch) -> None:
    narrow = {**SMALL_POLICY, "image_channels": (4, 8, 8, 16)}
    monkeypatch.setattr(th.backends.cpu, "get_cpu_capability", lambda: "AVX512")  # narrow widths on x86: channels-last
    model = small_model(HazardPointEnv(obs_type="pixels", size=64), policy_kwargs=narrow)
    assert model.policy.latent.channels_last and model.replay_buffer.channels_last_frames
    model.learn(45)
    assert model._n_updates > 0
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    monkeypatch.setattr(th.backends.cpu, "get_cpu_capability", lambda: "DEFAULT")  # NCHW
    other = small_model(HazardPointEnv(obs_type="pixels", size=64), policy_kwargs=narrow)
    assert not other.policy.latent.channels_last
    other.load_replay_buffer(tmp_path / "buffer.pkl")
    assert not other.replay_buffer.channels_last_frames
    np.testing.assert_array_equal(other.replay_buffer.stored_observations(), model.replay_buffer.stored_observations())


class DiscreteHazardEnv(HazardPointEnv):
    def __init__(self) -> None:
        super().__init__()
        self.action_space = spaces.Discrete(4)


class DictHazardEnv(HazardPointEnv):
    def __init__(self) -> None:
        super().__init__()
        self.observation_space = spaces.Dict({"state": self.observation_space})


def test_bad_spaces_are_rejected_with_the_fix() -> None:
    with pytest.raises(ValueError, match="continuous Box action space"):
        small_model(DiscreteHazardEnv())
    with pytest.raises(ValueError, match="obs_type='pixels' or obs_type='state'"):
        small_model(DictHazardEnv())


def test_a_frame_smaller_than_the_conv_encoder_takes_is_rejected_when_the_model_is_built() -> None:
    with pytest.raises(ValueError, match=r"Unsupported image shape \(3, 16, 16\).*at least 32x32 pixels"):
        small_model(HazardPointEnv(obs_type="pixels", size=16))


def test_env_without_cost_fails_at_the_first_step() -> None:
    model = small_model(HazardPointEnv(report_cost=False))
    with pytest.raises(ValueError, match=r"info\['cost'\]"):
        model.learn(5)


def test_env_without_time_limit_needs_episode_length() -> None:
    endless = HazardPointEnv()
    endless.max_episode_steps = None
    with pytest.raises(ValueError, match="episode_length"):
        small_model(endless)
    assert small_model(endless, episode_length=40).cost_budget_per_step == pytest.approx(25.0 / 40)
    limited = gym.wrappers.TimeLimit(HazardPointEnv(max_episode_steps=1_000), max_episode_steps=20)
    assert small_model(limited).cost_budget_per_step == pytest.approx(25.0 / 20)


@pytest.mark.parametrize(
    ("network", "ent_coef", "loss"),
    [("critic", "auto", "critic_loss"), ("critic", 0.1, "critic_loss"), ("latent", "auto", "latent_loss")],
)
def test_nan_loss_stops_training_and_names_the_loss(network: str, ent_coef, loss: str) -> None:
    model = small_model(HazardPointEnv(), ent_coef=ent_coef)
    model.learn(45)
    with th.no_grad():
        next(getattr(model.policy, network).parameters()).fill_(float("nan"))
    with pytest.raises(RuntimeError, match=f"DS-SLAC's {loss} became NaN or inf at update {model._n_updates} "):
        model.train(gradient_steps=3, batch_size=8)


def test_nan_action_stops_training_before_the_env_sees_it() -> None:
    # The last update of a burst can leave the weights NaN (or huge) with every loss of that burst finite: the next
    # action is the first place it shows, and it must fail with the checkpoint advice, not inside the env
    model = small_model(HazardPointEnv())
    model.learn(60)  # past learning_starts: the actor acts
    with th.no_grad():
        next(model.policy.actor.parameters()).fill_(float("nan"))
    with pytest.raises(RuntimeError, match=f"action became NaN or inf at timestep 60 \\(after update {model._n_updates}\\)"):
        model.learn(10, reset_num_timesteps=False)


def test_nan_in_the_latent_pretraining_names_the_latent_loss() -> None:
    model = small_model(HazardPointEnv(), learning_starts=1000)
    model.learn(50)
    with th.no_grad():
        next(model.policy.latent.parameters()).fill_(float("nan"))
    with pytest.raises(RuntimeError, match="latent_loss became NaN or inf at update 0 "):
        model.train(gradient_steps=1, batch_size=8)


def test_vector_observations_are_standardised_from_the_warmup_data(tmp_path) -> None:
    model = small_model(HazardPointEnv())
    assert th.equal(model.policy.preprocess(th.ones(2, 4)), th.ones(2, 4))  # identity before the pre-training
    model.learn(50)  # the pre-training runs after the rollout that ends at step 50
    stored = model.replay_buffer.stored_observations()
    assert stored.shape[1:] == (4,) and len(stored) >= 50
    np.testing.assert_allclose(model.policy.observation_mean.numpy(), stored.mean(axis=0), rtol=1e-5, atol=1e-6)
    fixed_mean = model.policy.observation_mean.clone()
    model.learn(30, reset_num_timesteps=False)
    assert th.equal(model.policy.observation_mean, fixed_mean)  # set once, not drifting
    standardised = model.policy.preprocess(th.as_tensor(stored[:, None]))
    assert standardised[:, 0, :2].std(dim=0).numpy() == pytest.approx([1.0, 1.0], rel=0.05)  # positions; hazard is fixed
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip")
    assert th.equal(loaded.policy.observation_std, model.policy.observation_std)


def test_images_are_only_scaled() -> None:
    model = small_model(HazardPointEnv(obs_type="pixels"))
    model.learn(45)
    frames = th.full((1, 3, 32, 32), 255, dtype=th.uint8)
    assert model.policy.observation_mean.numel() == 0
    assert th.equal(model.policy.preprocess(frames), th.ones(1, 3, 32, 32))


def test_narrow_image_channels_train_and_are_saved_with_the_model(tmp_path) -> None:
    policy_kwargs = {**SMALL_POLICY, "image_channels": (4, 8, 8, 16)}
    model = small_model(HazardPointEnv(obs_type="pixels"), policy_kwargs=policy_kwargs)
    model.learn(50)
    assert model._n_updates > 0
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip")
    assert loaded.policy.image_channels == (4, 8, 8, 16)
    assert loaded.policy.latent.encoder[0].out_channels == 4
    observation = np.asarray(model.env.reset())
    actions, _ = model.predict(observation, deterministic=True)
    np.testing.assert_allclose(loaded.predict(observation, deterministic=True)[0], actions, rtol=1e-5)
