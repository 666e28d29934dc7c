"""
How DS-SLAC acts in its training envs: a latent filter carried from step to step, random actions during the warm-up,
and each env's running episode cost, logged beside SB3's rollout logs. A mixin of ``DSSLAC`` (SB3's rollout hooks).
"""

from collections import deque
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.type_aliases import MaybeCallback, RolloutReturn, TrainFreq
from stable_baselines3.common.utils import safe_mean
from stable_baselines3.common.vec_env import VecEnv

from sb3_dsslac.common.buffers import SequenceReplayBuffer
from sb3_dsslac.common.env_info import check_observations_finite, cost_from_info
from sb3_dsslac.common.policies import LatentPolicy
from sb3_dsslac.common.timing import TimeAccount
from sb3_dsslac.nn.numerics import raise_if_action_not_finite


class FilteredRollouts(OffPolicyAlgorithm):
    """
    An SB3 off-policy algorithm that acts on a belief (``DSSLAC``'s base): the training envs' filter state
    ``(z2, previous action)`` and running episode costs live here, restart with fresh episodes, and are never saved.
    """

    policy: LatentPolicy
    time_account: TimeAccount
    action_repeat: int
    total_cost: float
    ep_cost_buffer: deque[float]
    _last_filter_state: tuple[th.Tensor, th.Tensor, th.Tensor] | None
    _episode_costs: np.ndarray

    def _init_rollout_state(self) -> None:
        """No filter state and no episode costs yet (``__init__``, and a loaded model, whose rollout state is not saved)."""
        self.total_cost = 0.0
        self._last_filter_state = None
        self._episode_costs = np.zeros(0)
        self.ep_cost_buffer = deque(maxlen=self._stats_window_size)

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, BaseCallback]:
        envs_reset = reset_num_timesteps or self._last_obs is None
        if reset_num_timesteps:
            self._init_rollout_state()
        result = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        assert self.env is not None
        if envs_reset or self._last_filter_state is None or len(self._episode_costs) != self.env.num_envs:
            # Fresh episodes (or a run resumed without its rollout state): every filter restarts at the next frame
            self._last_filter_state = None
            self._last_episode_starts = np.ones(self.env.num_envs, dtype=bool)
            self._episode_costs = np.zeros(self.env.num_envs)
        return result

    def _sample_action(
        self, learning_starts: int, action_noise: ActionNoise | None = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """
        Advance the training envs' latent filter on the last observation and act: ``tanh(N(0, 2^2))`` random actions
        during the warm-up (they advance the filter too), the stochastic actor afterwards. No action noise.
        """
        assert self._last_obs is not None and isinstance(self._last_obs, np.ndarray)
        check_observations_finite(self._last_obs, self._env_at_this_step)
        if self._last_filter_state is None:
            self._last_filter_state = self.policy.initial_state(n_envs)
        observation = th.as_tensor(self._last_obs, device=self.device)
        episode_start = th.as_tensor(self._last_episode_starts, dtype=th.bool, device=self.device)
        self.policy.set_training_mode(False)
        with th.inference_mode():
            z2_prev, action_prev, memory_prev = self._last_filter_state
            z, z2 = self.policy.belief_step(observation, z2_prev, action_prev, episode_start, deterministic=False)
            actor_input, memory = self.policy.acting_input(z, action_prev, memory_prev, episode_start)
            if self.num_timesteps < learning_starts:
                scaled_action = th.tanh(2.0 * th.randn(n_envs, self.policy.action_dim, device=self.device))
            else:
                scaled_action = self.policy.actor(actor_input)
        self._last_filter_state = (z2, scaled_action, memory)
        buffer_action = scaled_action.cpu().numpy()
        raise_if_action_not_finite(buffer_action, self.num_timesteps, self._n_updates)
        return self.policy.unscale_action(buffer_action), buffer_action

    def _env_at_this_step(self, index: int) -> str:
        """The words that name training env ``index`` (its wrappers and id) and the agent step, for an error."""
        assert self.env is not None
        return f"Training env {index} ({self.env.env_method('__str__', indices=[index])[0]}) at timestep {self.num_timesteps}"

    def collect_rollouts(
        self,
        env: VecEnv,
        callback: BaseCallback,
        train_freq: TrainFreq,
        replay_buffer: ReplayBuffer,
        action_noise: ActionNoise | None = None,
        learning_starts: int = 0,
        log_interval: int | None = None,
    ) -> RolloutReturn:
        """SB3's ``collect_rollouts``, its time counted as acting (callbacks that measure their own excepted)."""
        with self.time_account.measure("acting"):
            return super().collect_rollouts(
                env, callback, train_freq, replay_buffer, action_noise, learning_starts, log_interval
            )

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        for index in np.flatnonzero(dones):  # a last observation, stored but never filtered: checked here
            terminal = infos[index].get("terminal_observation")
            if isinstance(terminal, np.ndarray):
                check_observations_finite(terminal[None], lambda _, index=index: self._env_at_this_step(int(index)))
        costs = np.array([cost_from_info(info) for info in infos])
        self._episode_costs += costs
        self.total_cost += float(costs.sum())
        for idx in np.flatnonzero(dones):
            self.ep_cost_buffer.append(float(self._episode_costs[idx]))
            self._episode_costs[idx] = 0.0
        if isinstance(replay_buffer, SequenceReplayBuffer) and replay_buffer.stores_beliefs:
            assert self._last_filter_state is not None
            replay_buffer.note_beliefs(self._last_filter_state[0].cpu().numpy())  # z2 after the frame acted from
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        self._last_episode_starts = np.array(dones, dtype=bool)

    def dump_logs(self) -> None:
        """SB3's logs, with the episode costs, the simulator steps and the time account; its time counted as logging."""
        with self.time_account.measure("logging"):
            for name, seconds in self.time_account.summary().items():
                self.logger.record(f"time/{name}_s", round(seconds, 1))
            sim_steps = self.num_timesteps * self.action_repeat
            if len(self.ep_cost_buffer) > 0:
                self.logger.record("rollout/ep_cost_mean", safe_mean(list(self.ep_cost_buffer)))
            self.logger.record("rollout/cost_rate", self.total_cost / max(sim_steps, 1))
            self.logger.record("time/sim_steps", sim_steps)
            if hasattr(super(), "dump_logs"):
                super().dump_logs()
            else:  # SB3 before 2.6 names it _dump_logs
                super()._dump_logs()

    _dump_logs = dump_logs  # the name SB3 before 2.6 calls
