"""Cost-aware evaluation: per-episode rewards, costs and lengths, and an EvalCallback that keeps the best safe model."""

import os
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv

from sb3_dsslac.lagrange import cost_from_info


class EpisodeResults(NamedTuple):
    """Per-episode results of an evaluation, each of shape (n_eval_episodes,)."""

    rewards: np.ndarray
    costs: np.ndarray
    lengths: np.ndarray


def evaluate_policy_with_cost(
    model: BaseAlgorithm, env: gym.Env | VecEnv, n_eval_episodes: int = 10, deterministic: bool = True
) -> EpisodeResults:
    """
    Run ``n_eval_episodes`` episodes with SB3's ``evaluate_policy`` (so recurrent state goes through ``predict``)
    and sum ``info["cost"]`` over each episode.

    Evaluation uses its own filter state and never touches the model's training rollout or replay buffer.

    :param model: the agent
    :param env: the evaluation env (a VecEnv or a single env); must report ``info["cost"]``
    :param n_eval_episodes: episodes to run
    :param deterministic: act with the policy's mean (and the filter's means)
    :return: per-episode undiscounted rewards, costs and lengths (agent steps), in the order episodes finished
    """
    running: dict[int, float] = {}
    finished: list[float] = []

    def add_cost(locals_: dict[str, Any], _globals: dict[str, Any]) -> None:
        env_index, info = locals_["i"], locals_["info"]
        running[env_index] = running.get(env_index, 0.0) + cost_from_info(info)
        # Count an episode exactly when evaluate_policy does (a Monitor's episode end, or any done without Monitor)
        if locals_["done"] and (not locals_["is_monitor_wrapped"] or "episode" in info):
            finished.append(running.pop(env_index))

    rewards, lengths = evaluate_policy(
        model,
        env,
        n_eval_episodes=n_eval_episodes,
        deterministic=deterministic,
        callback=add_cost,
        return_episode_rewards=True,
        warn=False,
    )
    return EpisodeResults(np.asarray(rewards, dtype=float), np.asarray(finished, dtype=float), np.asarray(lengths))


class CostEvalCallback(EvalCallback):
    """
    ``EvalCallback`` that also measures the episode cost: records ``eval/mean_cost`` and ``eval/std_cost``, writes
    ``costs`` into ``evaluations.npz`` and keeps the best model feasibility-first (first under ``cost_limit``,
    then the highest mean reward; among infeasible evaluations, the lowest mean cost).

    :param eval_env: the evaluation env; must report ``info["cost"]``
    :param cost_limit: the episode cost budget that decides feasibility
    :param kwargs: the keywords of ``EvalCallback`` (``n_eval_episodes``, ``eval_freq``, ``log_path``, ...)
    """

    def __init__(self, eval_env: gym.Env | VecEnv, cost_limit: float = 25.0, **kwargs: Any):
        super().__init__(eval_env, **kwargs)
        self.cost_limit = cost_limit
        self.evaluations_costs: list[np.ndarray] = []
        self.last_mean_cost = np.inf
        self.best_score: tuple[int, float] = (0, -np.inf)

    def _on_step(self) -> bool:
        if self.eval_freq <= 0 or self.n_calls % self.eval_freq != 0:
            return True
        results = evaluate_policy_with_cost(self.model, self.eval_env, self.n_eval_episodes, self.deterministic)
        mean_reward, std_reward = float(results.rewards.mean()), float(results.rewards.std())
        mean_cost, std_cost = float(results.costs.mean()), float(results.costs.std())
        self.evaluations_timesteps.append(self.num_timesteps)
        self.evaluations_results.append(results.rewards)
        self.evaluations_length.append(results.lengths)
        self.evaluations_costs.append(results.costs)
        if self.log_path is not None:
            np.savez(
                self.log_path,
                timesteps=self.evaluations_timesteps,
                results=self.evaluations_results,
                ep_lengths=self.evaluations_length,
                costs=self.evaluations_costs,
            )
        self.last_mean_reward, self.last_mean_cost = mean_reward, mean_cost
        if self.verbose >= 1:
            print(
                f"Eval num_timesteps={self.num_timesteps}, episode_reward={mean_reward:.2f} +/- {std_reward:.2f}, "
                f"episode_cost={mean_cost:.2f} +/- {std_cost:.2f} (budget {self.cost_limit:g})"
            )
        self.logger.record("eval/mean_reward", mean_reward)
        self.logger.record("eval/mean_cost", mean_cost)
        self.logger.record("eval/std_cost", std_cost)
        self.logger.record("eval/mean_ep_length", float(results.lengths.mean()))
        self.logger.record("time/total_timesteps", self.num_timesteps, exclude="tensorboard")
        self.logger.dump(self.num_timesteps)

        continue_training = True
        score = (1, mean_reward) if mean_cost <= self.cost_limit else (0, -mean_cost)
        if score > self.best_score:
            self.best_score = score
            self.best_mean_reward = mean_reward
            if self.best_model_save_path is not None:
                self.model.save(os.path.join(self.best_model_save_path, "best_model"))
            if self.callback_on_new_best is not None:
                continue_training = self.callback_on_new_best.on_step()
        if self.callback is not None:
            continue_training = continue_training and self._on_event()
        return continue_training
