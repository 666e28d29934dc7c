"""Cost-aware evaluation: per-episode rewards, costs and lengths, and an EvalCallback that keeps the best safe model."""

import os
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv

from sb3_dsslac.common.atomic import atomic_file
from sb3_dsslac.common.env_info import cost_from_info
from sb3_dsslac.common.timing import measured


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


def eval_policy_name(deterministic: bool) -> str:
    """How an evaluation acted: "deterministic" (the filter's means and the mean action) or "stochastic" (sampled)."""
    return "deterministic" if deterministic else "stochastic"


class CostEvalCallback(EvalCallback):
    """
    ``EvalCallback`` that also measures the episode cost: records ``eval/mean_cost`` and ``eval/std_cost``, writes
    ``costs`` into ``evaluations.npz`` and keeps the best model feasibility-first (first under ``cost_limit``,
    then the highest mean reward; among infeasible evaluations, the lowest mean cost). Both files are written whole or
    not at all (``common.atomic``), so a run killed while it writes them keeps the earlier ones.

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
        with measured(self.model, "evaluation"):
            return self._evaluate()

    def _evaluate(self) -> bool:
        """Evaluate, log, write ``evaluations.npz`` and keep the best model; whether training continues."""
        results = evaluate_policy_with_cost(self.model, self.eval_env, self.n_eval_episodes, self.deterministic)
        mean_reward, std_reward = float(results.rewards.mean()), float(results.rewards.std())
        mean_cost, std_cost = float(results.costs.mean()), float(results.costs.std())
        self.evaluations_timesteps.append(self.num_timesteps)
        self.evaluations_results.append(results.rewards)
        self.evaluations_length.append(results.lengths)
        self.evaluations_costs.append(results.costs)
        if self.log_path is not None:
            # EvalCallback's log_path is <folder>/evaluations: np.savez adds the suffix to a name, not to an open file
            with atomic_file(f"{self.log_path}.npz") as file:
                np.savez(
                    file,
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
                with atomic_file(os.path.join(self.best_model_save_path, "best_model.zip")) as file:
                    self.model.save(file)
            if self.callback_on_new_best is not None:
                continue_training = self.callback_on_new_best.on_step()
        if self.callback is not None:
            continue_training = continue_training and self._on_event()
        return continue_training

    def restore(self, log_path: str, max_timesteps: int) -> None:
        """
        Take back the evaluations of an earlier run from its ``evaluations.npz`` (the rows at or before
        ``max_timesteps``), so that a resumed run appends to them and keeps its best-model score.

        :param log_path: the ``evaluations.npz`` written by this callback in the earlier run
        :param max_timesteps: the agent steps of the checkpoint the run resumes from
        """
        with np.load(log_path) as data:
            keep = data["timesteps"] <= max_timesteps
            self.evaluations_timesteps = data["timesteps"][keep].tolist()
            self.evaluations_results = list(data["results"][keep])
            self.evaluations_length = list(data["ep_lengths"][keep])
            self.evaluations_costs = list(data["costs"][keep])
        for rewards, costs in zip(self.evaluations_results, self.evaluations_costs, strict=True):
            mean_reward, mean_cost = float(np.mean(rewards)), float(np.mean(costs))
            score = (1, mean_reward) if mean_cost <= self.cost_limit else (0, -mean_cost)
            if score > self.best_score:
                self.best_score, self.best_mean_reward = score, mean_reward
            self.last_mean_reward, self.last_mean_cost = mean_reward, mean_cost


# Unconstrained PPO's final (episode reward, episode cost) on the Safety-Gym tasks (As et al., 2022), the reference
# of the thesis's normalised scores (Eq. 5.1).
PPO_REFERENCE: dict[str, tuple[float, float]] = {
    "PointGoal1": (17.476, 76.439),
    "PointGoal2": (14.748, 206.961),
    "CarGoal1": (13.039, 65.783),
    "PointButton1": (18.715, 136.594),
    "PointPush1": (1.544, 61.822),
    "DoggoGoal1": (1.086, 83.328),
}
# DS-SLAC's normalised (Jr_bar, Jc_bar) in the thesis's Table 5.1 (1M simulator steps; 2M for DoggoGoal1).
THESIS_DSSLAC_SCORES: dict[str, tuple[float, float]] = {
    "PointGoal1": (1.237, 0.0),
    "CarGoal1": (1.555, 0.0),
    "DoggoGoal1": (0.577, 0.0),
    "PointGoal2": (0.014, 0.045),
}
# LAMBDA's normalised (Jr_bar, Jc_bar) in the same table (As et al., 2022; 1M simulator steps, 2M for DoggoGoal1).
THESIS_LAMBDA_SCORES: dict[str, tuple[float, float]] = {
    "PointGoal1": (1.077, 0.0),
    "CarGoal1": (1.284, 0.0),
    "DoggoGoal1": (5.400, 0.0),
    "PointGoal2": (0.902, 0.0),
}


def normalised_scores(
    mean_reward: float, mean_cost: float, ppo_reward: float, ppo_cost: float, cost_limit: float = 25.0
) -> tuple[float, float]:
    """
    The thesis's normalised episode reward and cost (Eq. 5.1) against an unconstrained PPO reference:
    ``Jr_bar = Jr / Jr_PPO`` and ``Jc_bar = max(0, Jc - d) / max(1e-6, Jc_PPO - d)``.

    :param mean_reward: Jr, the mean undiscounted episode reward
    :param mean_cost: Jc, the mean episode cost
    :param ppo_reward: Jr_PPO
    :param ppo_cost: Jc_PPO
    :param cost_limit: d, the episode cost budget
    :return: (Jr_bar, Jc_bar); Jc_bar is 0 for any policy within the budget
    """
    return mean_reward / ppo_reward, max(0.0, mean_cost - cost_limit) / max(1e-6, ppo_cost - cost_limit)
