"""Cost-aware evaluation."""

import numpy as np
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_dsslac.common.evaluation import CostEvalCallback, evaluate_policy_with_cost
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import small_model


def always_unsafe_env() -> HazardPointEnv:
    env = HazardPointEnv(max_episode_steps=12)
    env.hazard_radius = 10.0
    return env


def test_costs_are_summed_per_episode_over_several_envs() -> None:
    model = small_model(HazardPointEnv())
    vec_env = DummyVecEnv([always_unsafe_env, always_unsafe_env])
    results = evaluate_policy_with_cost(model, vec_env, n_eval_episodes=4)
    np.testing.assert_array_equal(results.lengths, [12, 12, 12, 12])
    np.testing.assert_array_equal(results.costs, [12.0, 12.0, 12.0, 12.0])
    assert results.rewards.shape == (4,)


def test_monitor_wrapped_env_gives_the_same_costs() -> None:
    model = small_model(HazardPointEnv())
    results = evaluate_policy_with_cost(model, Monitor(always_unsafe_env()), n_eval_episodes=2)
    np.testing.assert_array_equal(results.costs, [12.0, 12.0])


def test_eval_callback_records_costs_and_keeps_the_best_feasible_model(tmp_path) -> None:
    callback = CostEvalCallback(
        always_unsafe_env(),
        cost_limit=5.0,
        eval_freq=45,
        n_eval_episodes=1,
        log_path=str(tmp_path),
        best_model_save_path=str(tmp_path),
        verbose=0,
    )
    model = small_model(HazardPointEnv())
    model.learn(90, callback=callback)
    evaluations = np.load(tmp_path / "evaluations.npz")
    np.testing.assert_array_equal(evaluations["costs"], [[12.0], [12.0]])
    assert evaluations["timesteps"].tolist() == [45, 90]
    # Never under the budget: the best score is the lowest cost, and a best model was saved
    assert callback.best_score == (0, -12.0)
    assert (tmp_path / "best_model.zip").exists()
    assert callback.last_mean_cost == 12.0
