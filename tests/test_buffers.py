import pickle
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from stable_baselines3 import SAC
from stable_baselines3.common.save_util import load_from_pkl, save_to_pkl
from stable_baselines3.common.vec_env import DummyVecEnv

from sb3_dsslac.common.buffers import SequenceBatch, SequenceReplayBuffer

VEC_SPACE = spaces.Box(-np.inf, np.inf, shape=(3,), dtype=np.float32)
ACT_SPACE = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)


def frame(env: int, episode: int, step: int) -> np.ndarray:
    return np.array([env, episode, step], dtype=np.float32)


def reward_of(env: int, episode: int, step: int) -> float:
    return 10_000.0 * env + 100.0 * episode + step


def cost_of(env: int, episode: int, step: int) -> float:
    return 0.5 * step + env


class ScriptedEnvs:
    """Lock-step envs whose frames, actions, rewards and costs encode (env, episode, step)."""

    def __init__(self, plans: list[list[tuple[int, bool, bool]]]) -> None:
        # plans[e]: episodes of env e as (n_steps, terminated, cut) where `cut` means reset without `done`
        self.plans = plans
        self.n_envs = len(plans)
        self.episode = [0] * self.n_envs
        self.step_in_episode = [0] * self.n_envs
        self.records: list[list[tuple[int, int]]] = [[] for _ in plans]  # (episode, step) of each record, in write order
        self.ends: dict[tuple[int, int], tuple[int, bool]] = {}  # (env, episode) -> (n_steps, terminated)

    def plan(self, env: int) -> tuple[int, bool, bool]:
        episodes = self.plans[env]
        return episodes[self.episode[env] % len(episodes)]

    def step(self, buffer: SequenceReplayBuffer) -> None:
        obs, next_obs, actions, rewards, dones, infos = [], [], [], [], [], []
        for env in range(self.n_envs):
            episode, step = self.episode[env], self.step_in_episode[env]
            length, is_terminated, cut = self.plan(env)
            if step == 0:
                self.records[env].append((episode, 0))
            obs.append(frame(env, episode, step))
            next_obs.append(frame(env, episode, step + 1))
            actions.append(frame(env, episode, step) / 1000.0)
            rewards.append(reward_of(env, episode, step))
            self.records[env].append((episode, step + 1))
            ended = step + 1 == length
            dones.append(ended and not cut)
            infos.append({"cost": cost_of(env, episode, step), "TimeLimit.truncated": ended and not is_terminated})
            if ended:
                self.ends[(env, episode)] = (length, is_terminated and not cut)
                self.episode[env] += 1
                self.step_in_episode[env] = 0
            else:
                self.step_in_episode[env] += 1
        if buffer.stores_beliefs:  # a "belief" of each frame acted from: the frame + 0.5
            buffer.note_beliefs(np.stack(obs) + 0.5)
        buffer.add(np.stack(obs), np.stack(next_obs), np.stack(actions), np.array(rewards), np.array(dones), infos)

    def expected_windows(self, slots: int, length: int) -> set[tuple[int, int, int]]:
        """(env, episode, first step) of every window the buffer should still hold."""
        windows = set()
        for env, records in enumerate(self.records):
            kept = records[-slots:]
            for i in range(len(kept) - length):
                (ep0, s0), (ep1, s1) = kept[i], kept[i + length]
                if ep0 == ep1 and s1 - s0 == length:
                    windows.add((env, ep0, s0))
        return windows


def check_window(batch: SequenceBatch, b: int, envs: ScriptedEnvs, length: int) -> tuple[int, int, int]:
    obs = batch.observations[b].numpy()
    env, episode, first = (int(v) for v in obs[0])
    steps = first + np.arange(length + 1)
    np.testing.assert_array_equal(obs, np.stack([frame(env, episode, s) for s in steps]))
    np.testing.assert_array_equal(batch.actions[b].numpy(), np.stack([frame(env, episode, s) / 1000.0 for s in steps[:-1]]))
    np.testing.assert_array_equal(batch.rewards[b].numpy(), [reward_of(env, episode, s) for s in steps[:-1]])
    np.testing.assert_array_equal(batch.costs[b].numpy(), [cost_of(env, episode, s) for s in steps[:-1]])
    n_steps, is_terminated = envs.ends.get((env, episode), (-1, False))
    expected_terminated = [float(is_terminated and s + 1 == n_steps) for s in steps[:-1]]
    np.testing.assert_array_equal(batch.terminated[b].numpy(), expected_terminated)
    if expected_terminated[-1]:
        # The last frame of a terminal window is the terminal observation
        np.testing.assert_array_equal(obs[-1], frame(env, episode, n_steps))
    return env, episode, first


episode_st = st.tuples(st.integers(1, 9), st.booleans(), st.integers(0, 5).map(lambda x: x == 0))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    plans=st.lists(st.lists(episode_st, min_size=1, max_size=6), min_size=1, max_size=3),
    length=st.integers(1, 4),
    extra_slots=st.integers(0, 20),
    n_steps=st.integers(1, 80),
    seed=st.integers(0, 2**16),
)
def test_windows_stay_inside_one_episode(plans, length, extra_slots, n_steps, seed):
    n_envs = len(plans)
    slots = length + 1 + extra_slots
    buffer = SequenceReplayBuffer(slots * n_envs, VEC_SPACE, ACT_SPACE, device="cpu", n_envs=n_envs, sequence_length=length)
    envs = ScriptedEnvs(plans)
    for _ in range(n_steps):
        envs.step(buffer)
    expected = envs.expected_windows(slots, length)
    assert buffer.can_sample() == bool(expected)
    if not expected:
        with pytest.raises(ValueError, match="no episode has"):
            buffer.sample(4)
        return
    np.random.seed(seed)
    batch = buffer.sample(64)
    assert batch.observations.shape == (64, length + 1, 3)
    assert batch.actions.shape == (64, length, 3)
    assert batch.rewards.shape == batch.costs.shape == batch.terminated.shape == (64, length)
    assert all(t.dtype == th.float32 for t in batch[:5]) and batch.episode_start_index is None
    sampled = {check_window(batch, b, envs, length) for b in range(64)}
    assert sampled <= expected


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    plans=st.lists(st.lists(episode_st, min_size=1, max_size=6), min_size=1, max_size=3),
    length=st.integers(1, 4),
    burn_in=st.integers(1, 5),
    stored=st.booleans(),
    extra_slots=st.integers(0, 20),
    n_steps=st.integers(1, 80),
    seed=st.integers(0, 2**16),
)
def test_burn_in_reaches_back_into_the_episode(plans, length, burn_in, stored, extra_slots, n_steps, seed):
    """
    With a burn-in of K frames the windows are those without it whose episode's records among the K before them (and
    the one before those, with stored beliefs) are still stored; each comes with those K records, the index of its
    episode's first frame where that is among them (-1 before them), and with stored beliefs the belief and action of
    the record before them where it is of the episode.
    """
    n_envs = len(plans)
    slots = burn_in + length + 1 + extra_slots
    buffer = SequenceReplayBuffer(
        slots * n_envs, VEC_SPACE, ACT_SPACE, device="cpu", n_envs=n_envs, sequence_length=length, burn_in=burn_in
    )
    if stored:
        buffer.store_beliefs(3)
    envs = ScriptedEnvs(plans)
    for _ in range(n_steps):
        envs.step(buffer)
    reachable = set()
    for env, records in enumerate(envs.records):
        kept = records[-slots:]
        for i in range(len(kept) - length):
            (ep0, s0), (ep1, s1) = kept[i], kept[i + length]
            back = min(s0, burn_in + stored)
            if ep0 == ep1 and s1 - s0 == length and i >= back:
                reachable.add((env, ep0, s0))
    if not reachable:
        return
    np.random.seed(seed)
    batch = buffer.sample(64)
    assert batch.observations.shape == (64, burn_in + length + 1, 3)
    assert batch.actions.shape == (*batch.rewards.shape[:2], 3) == (64, burn_in + length, 3)
    trained = batch.without_burn_in(burn_in)
    for b in range(64):
        env, episode, first = check_window(trained, b, envs, length)
        assert (env, episode, first) in reachable
        start_index = int(batch.episode_start_index[b])
        assert start_index == max(burn_in - first, -1)
        for index in range(max(start_index, 0), burn_in):
            step = first - burn_in + index
            np.testing.assert_array_equal(batch.observations[b, index].numpy(), frame(env, episode, step))
            np.testing.assert_array_equal(batch.actions[b, index].numpy(), frame(env, episode, step) / 1000.0)
        if not stored:
            assert batch.stored_belief is None and batch.stored_action is None
        elif start_index == -1:
            before = frame(env, episode, first - burn_in - 1)
            np.testing.assert_array_equal(batch.stored_belief[b].numpy(), before + 0.5)
            np.testing.assert_array_equal(batch.stored_action[b].numpy(), before / 1000.0)
        else:
            assert not batch.stored_belief[b].any() and not batch.stored_action[b].any()


def counting_step(frames: th.Tensor, z2_prev: th.Tensor, action_prev: th.Tensor, opens: th.Tensor) -> th.Tensor:
    """A belief that counts the steps it continued, the frame's step, and the step of the frame its action left."""
    counted = th.where(opens, th.zeros_like(z2_prev[:, 0]), z2_prev[:, 0] + 1)
    previous_step = th.where(opens, th.full_like(counted, -1.0), action_prev[:, 2] * 1000.0)
    return th.stack([counted, frames[:, 2], previous_step], dim=1)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    plans=st.lists(st.lists(episode_st, min_size=1, max_size=6), min_size=1, max_size=3),
    extra_slots=st.integers(0, 20),
    n_steps=st.integers(1, 80),
)
def test_refreshed_beliefs_filter_every_stored_episode_again(plans, extra_slots, n_steps):
    """
    Each stored record's belief becomes the step's of its predecessor's refreshed one (an episode's first frame opens
    one); a record whose predecessor the ring overwrote keeps its stored belief, and its successors continue from it.
    A device copy (the GPU path) gets the new beliefs.
    """
    n_envs, slots = len(plans), 6 + extra_slots
    buffer = SequenceReplayBuffer(
        slots * n_envs, VEC_SPACE, ACT_SPACE, device="cpu", n_envs=n_envs, sequence_length=2, burn_in=1
    )
    buffer.store_beliefs(3)
    envs = ScriptedEnvs(plans)
    for _ in range(n_steps):
        envs.step(buffer)
    before = buffer.beliefs.copy()
    # as on a GPU: a device copy of the sampled arrays, whose beliefs the refresh brings up to date
    buffer._device_copy = {name: th.from_numpy(getattr(buffer, name).copy()) for name in buffer._SAMPLED}
    refreshed = buffer.refresh_beliefs(counting_step, max_rows=2)
    np.testing.assert_array_equal(buffer._device_copy["beliefs"].numpy(), buffer.beliefs)
    expected_count = 0
    for env, records in enumerate(envs.records):
        kept = records[-slots:]
        first_slot = len(records) - len(kept)
        expected: list[np.ndarray] = []
        for i, (episode, step) in enumerate(kept):
            slot = (first_slot + i) % slots
            if step == 0:
                value = np.array([0.0, step, -1.0])
            elif i > 0 and kept[i - 1] == (episode, step - 1):
                value = np.array([expected[-1][0] + 1, step, step - 1])
            else:
                value = before[slot, env]
                expected_count -= 1
            expected.append(value)
            expected_count += 1
            np.testing.assert_allclose(buffer.beliefs[slot, env], value, err_msg=f"env {env} episode {episode} step {step}")
    assert refreshed == expected_count


def test_stored_beliefs_need_a_burn_in_and_a_belief_for_every_add() -> None:
    with pytest.raises(ValueError, match="burn_in >= 1"):
        SequenceReplayBuffer(40, VEC_SPACE, ACT_SPACE, device="cpu", sequence_length=3).store_beliefs(3)
    buffer = SequenceReplayBuffer(40, VEC_SPACE, ACT_SPACE, device="cpu", sequence_length=3, burn_in=2)
    buffer.store_beliefs(3)
    envs = ScriptedEnvs([[(9, False, False)]])
    envs.step(buffer)
    with pytest.raises(ValueError, match="note_beliefs"):
        buffer.add(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(1), np.zeros(1), [{"cost": 0.0}])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    plans=st.lists(st.lists(episode_st, min_size=1, max_size=6), min_size=1, max_size=3),
    extra_slots=st.integers(0, 12),
    bursts=st.lists(st.integers(0, 30), min_size=1, max_size=6),
    stored=st.booleans(),
)
def test_device_copy_tracks_the_host_arrays(plans, extra_slots, bursts, stored):
    # The GPU path: a device copy brought up to date before each sampling must equal the host arrays, through ring
    # wrap-arounds and the transition fields that the next `add` writes into an already uploaded record (the stored
    # beliefs among them).
    n_envs, length = len(plans), 2
    buffer = SequenceReplayBuffer(
        (length + 2 + extra_slots) * n_envs,
        VEC_SPACE,
        ACT_SPACE,
        device="cpu",
        n_envs=n_envs,
        sequence_length=length,
        burn_in=1,
    )
    if stored:
        buffer.store_beliefs(3)
    buffer._device_copy = {name: th.from_numpy(getattr(buffer, name).copy()) for name in buffer._SAMPLED}
    envs = ScriptedEnvs(plans)
    for n_steps in bursts:
        for _ in range(n_steps):
            envs.step(buffer)
        buffer._upload_new_records()
        for name, tensor in buffer._device_copy.items():
            np.testing.assert_array_equal(tensor.numpy(), getattr(buffer, name), err_msg=name)


def test_indices_for_a_burst_gather_the_same_windows_as_sample():
    envs = ScriptedEnvs([[(7, False, False)], [(5, True, False)]])
    buffer = SequenceReplayBuffer(2 * 40, VEC_SPACE, ACT_SPACE, device="cpu", n_envs=2, sequence_length=3)
    for _ in range(60):
        envs.step(buffer)
    np.random.seed(3)
    indices = buffer.sample_indices(5, 16)
    assert indices.shape == (5, 16, 2) and indices.dtype == th.int64
    np.random.seed(3)
    starts, env_ids = buffer._sample_starts(5 * 16)
    np.testing.assert_array_equal(indices.reshape(-1, 2).numpy(), np.stack([starts, env_ids], axis=-1))
    for k in range(5):
        batch = buffer.gather(indices[k])
        for b in range(16):
            check_window(batch, b, envs, 3)


def test_sampling_is_uniform_over_windows():
    # Env 0: one long episode; env 1: many episodes of exactly L steps (one window each, low valid fraction)
    length = 3
    envs = ScriptedEnvs([[(200, False, False)], [(length, True, False)]])
    buffer = SequenceReplayBuffer(2 * 200, VEC_SPACE, ACT_SPACE, device="cpu", n_envs=2, sequence_length=length)
    for _ in range(120):
        envs.step(buffer)
    expected = envs.expected_windows(200, length)
    np.random.seed(0)
    # Small batches go through rejection sampling, a huge one through enumerating the valid windows
    for batches in ([buffer.sample(32) for _ in range(1000)], [buffer.sample(32_000)]):
        keys = np.concatenate([batch.observations[:, 0].numpy() for batch in batches]).astype(int)
        _, counts = np.unique(keys, axis=0, return_counts=True)
        assert len(counts) == len(expected)
        # Each window ~ Binomial(n, 1/len(expected)); allow 6 standard deviations
        mean = len(keys) / len(expected)
        assert np.all(np.abs(counts - mean) < 6 * np.sqrt(mean))


def test_windows_overwritten_by_short_episodes_are_gone():
    length = 4
    buffer = SequenceReplayBuffer(30, VEC_SPACE, ACT_SPACE, device="cpu", sequence_length=length)
    envs = ScriptedEnvs([[(10, True, False)] + [(2, True, False)] * 20])
    for _ in range(10):
        envs.step(buffer)
    assert buffer.can_sample()
    for _ in range(16):  # 8 two-step episodes write 24 records: the first 5 frames of the 10-step episode are lost
        envs.step(buffer)
    assert buffer.can_sample()
    np.random.seed(0)
    assert {int(s) for s in buffer.sample(200).observations[:, 0, 2]} == {5, 6}
    for _ in range(2):  # one more: only the frames of steps 8, 9, 10 remain, too few for a window
        envs.step(buffer)
    assert not buffer.can_sample()
    with pytest.raises(ValueError, match="stores 20 steps"):
        buffer.sample(1)


def test_truncation_is_not_termination():
    length = 2
    buffer = SequenceReplayBuffer(20, VEC_SPACE, ACT_SPACE, device="cpu", sequence_length=length)
    envs = ScriptedEnvs([[(2, False, False), (2, True, False)]])
    for _ in range(4):
        envs.step(buffer)
    np.random.seed(0)
    batch = buffer.sample(50)
    episodes = batch.observations[:, 0, 1].numpy()
    assert set(episodes) == {0.0, 1.0}
    np.testing.assert_array_equal(batch.terminated[episodes == 0].numpy(), 0.0)
    np.testing.assert_array_equal(batch.terminated[episodes == 1].numpy(), np.tile([0.0, 1.0], ((episodes == 1).sum(), 1)))

    # Without timeout handling a truncation counts as a termination
    buffer = SequenceReplayBuffer(
        20, VEC_SPACE, ACT_SPACE, device="cpu", sequence_length=length, handle_timeout_termination=False
    )
    envs = ScriptedEnvs([[(2, False, False)]])
    for _ in range(2):
        envs.step(buffer)
    np.testing.assert_array_equal(buffer.sample(5).terminated.numpy(), np.tile([0.0, 1.0], (5, 1)))


def test_episode_uses_one_extra_frame():
    buffer = SequenceReplayBuffer(100, VEC_SPACE, ACT_SPACE, device="cpu", sequence_length=2)
    envs = ScriptedEnvs([[(5, True, False)]])
    for _ in range(10):  # two episodes of 5 steps
        envs.step(buffer)
    assert buffer.pos == 12
    assert not buffer.full
    np.testing.assert_array_equal(buffer.episode_ids[:13].ravel(), [0] * 6 + [1] * 6 + [-1])


def test_missing_cost_raises():
    buffer = SequenceReplayBuffer(20, VEC_SPACE, ACT_SPACE, device="cpu", sequence_length=2)
    obs = np.zeros((1, 3), dtype=np.float32)
    with pytest.raises(ValueError, match=r"info\['cost'\]"):
        buffer.add(obs, obs, np.zeros((1, 3)), np.zeros(1), np.zeros(1), [{}])


@pytest.mark.parametrize(
    ("obs_space", "act_space", "kwargs", "match"),
    [
        (spaces.Dict({"a": VEC_SPACE}), ACT_SPACE, {}, "only Box observation"),
        (VEC_SPACE, spaces.Discrete(3), {}, "only Box"),
        (
            VEC_SPACE,
            ACT_SPACE,
            {"optimize_memory_usage": True, "handle_timeout_termination": False},
            "stores every frame once",
        ),
        (VEC_SPACE, ACT_SPACE, {"sequence_length": 0}, "sequence_length must be >= 1"),
        (VEC_SPACE, ACT_SPACE, {"sequence_length": 10, "n_envs": 2}, "fewer than the 11 frames"),
    ],
)
def test_invalid_configuration_raises(obs_space, act_space, kwargs, match):
    with pytest.raises(ValueError, match=match):
        SequenceReplayBuffer(20, obs_space, act_space, device="cpu", **kwargs)


def test_sample_before_enough_data_raises():
    buffer = SequenceReplayBuffer(20, VEC_SPACE, ACT_SPACE, device="cpu", sequence_length=3)
    with pytest.raises(ValueError, match="stores 0 steps"):
        buffer.sample(2)
    envs = ScriptedEnvs([[(2, True, False)]])
    for _ in range(4):  # two 2-step episodes: 4 steps, but no 3 consecutive
        envs.step(buffer)
    assert not buffer.can_sample()
    with pytest.raises(ValueError, match=r"stores 4 steps.*sequence_length=3"):
        buffer.sample(2)


def filled_buffer(n_steps: int, slots: int = 40, burn_in: int = 0) -> tuple[SequenceReplayBuffer, ScriptedEnvs]:
    buffer = SequenceReplayBuffer(2 * slots, VEC_SPACE, ACT_SPACE, device="cpu", n_envs=2, sequence_length=3, burn_in=burn_in)
    if burn_in > 0:
        buffer.store_beliefs(3)
    envs = ScriptedEnvs([[(7, True, False), (4, False, False)], [(9, False, False)]])
    for _ in range(n_steps):
        envs.step(buffer)
    return buffer, envs


def assert_same_samples(a: SequenceReplayBuffer, b: SequenceReplayBuffer, seed: int = 3) -> None:
    np.random.seed(seed)
    batch_a = a.sample(32)
    np.random.seed(seed)
    batch_b = b.sample(32)
    for x, y in zip(batch_a, batch_b, strict=True):
        assert (x is None and y is None) or th.equal(x, y)


@pytest.mark.parametrize("n_steps", [15, 100])  # before and after the ring wraps
@pytest.mark.parametrize("burn_in", [0, 2])
def test_pickle_round_trip(tmp_path, n_steps, burn_in):
    buffer, envs = filled_buffer(n_steps, burn_in=burn_in)
    restored = pickle.loads(pickle.dumps(buffer))
    assert_same_samples(buffer, restored)
    save_to_pkl(tmp_path / "buffer.pkl", buffer)
    from_file = load_from_pkl(tmp_path / "buffer.pkl")
    assert_same_samples(buffer, from_file)
    # Both keep accepting the same stream
    twin = ScriptedEnvs(envs.plans)
    twin.__dict__.update(pickle.loads(pickle.dumps(envs.__dict__)))
    for _ in range(30):
        envs.step(buffer)
        twin.step(from_file)
    assert_same_samples(buffer, from_file)
    for name in SequenceReplayBuffer._STORAGE:
        np.testing.assert_array_equal(getattr(buffer, name), getattr(from_file, name))


def test_pickle_of_partly_filled_buffer_is_small():
    buffer, _ = filled_buffer(5, slots=2000)
    assert len(pickle.dumps(buffer)) < buffer.nbytes / 20


def test_reset_forgets_everything():
    buffer, _ = filled_buffer(30)
    buffer.reset()
    assert not buffer.can_sample() and buffer.pos == 0 and not buffer.full
    _, envs = filled_buffer(0)
    for _ in range(30):
        envs.step(buffer)
    fresh, _ = filled_buffer(30)
    assert_same_samples(buffer, fresh)


def test_memory_of_image_frames():
    obs_space = spaces.Box(0, 255, shape=(3, 64, 64), dtype=np.uint8)
    capacity = 2000
    buffer = SequenceReplayBuffer(capacity, obs_space, spaces.Box(-1, 1, (2,)), device="cpu", sequence_length=10)
    assert buffer.observations.dtype == np.uint8
    assert not hasattr(buffer, "next_observations")
    assert buffer.nbytes <= 1.05 * capacity * 12288


def test_image_frames_are_sampled_as_uint8():
    obs_space = spaces.Box(0, 255, shape=(3, 8, 8), dtype=np.uint8)
    buffer = SequenceReplayBuffer(30, obs_space, spaces.Box(-1, 1, (2,)), device="cpu", n_envs=1, sequence_length=2)
    frames = np.arange(6, dtype=np.uint8)[:, None, None, None] * np.ones((1, 3, 8, 8), dtype=np.uint8)
    for t in range(5):
        done = np.array([t == 4])
        buffer.add(frames[t : t + 1], frames[t + 1 : t + 2], np.zeros((1, 2)), np.zeros(1), done, [{"cost": 0.0}])
    batch = buffer.sample(20)
    assert batch.observations.dtype == th.uint8
    first = batch.observations[:, 0, 0, 0, 0]
    np.testing.assert_array_equal(batch.observations[:, :, 0, 0, 0].numpy(), first[:, None].numpy() + np.arange(3))


def image_buffer(channels_last_from: int | None, n_steps: int = 40) -> SequenceReplayBuffer:
    """Distinct (3, 4, 5) frames of 2 envs, episodes of 7 steps, stored channels-last from step ``channels_last_from``."""
    obs_space = spaces.Box(0, 255, shape=(3, 4, 5), dtype=np.uint8)
    buffer = SequenceReplayBuffer(60, obs_space, spaces.Box(-1, 1, (2,)), device="cpu", n_envs=2, sequence_length=3)
    pixels = np.arange(2 * 60).reshape(2, 3, 4, 5)
    for t in range(n_steps):
        if t == channels_last_from:
            buffer.set_channels_last_frames(True)
        obs, next_obs = ((pixels + 7 * (s % 8)) % 256 for s in (t, t + 1))
        done = np.full(2, t % 7 == 6)
        buffer.add(obs, next_obs, np.zeros((2, 2)), np.zeros(2), done, [{"cost": 0.0}] * 2)
    return buffer


@pytest.mark.parametrize("channels_last_from", [0, 15])  # before the first frame, and moving the frames stored so far
def test_channels_last_frames_sample_the_same_windows(channels_last_from):
    plain, channels_last = image_buffer(None), image_buffer(channels_last_from)
    assert channels_last.observations.shape[-3:] == (4, 5, 3)
    assert_same_samples(plain, channels_last)
    np.testing.assert_array_equal(channels_last.stored_observations(), plain.stored_observations())
    frames = channels_last.sample(8).observations.view(-1, 3, 4, 5)  # as the encoder reads them: no copy
    assert frames.is_contiguous(memory_format=th.channels_last)
    assert_same_samples(plain, pickle.loads(pickle.dumps(channels_last)))
    channels_last.set_channels_last_frames(False)
    assert channels_last.observations.shape[-3:] == (3, 4, 5)
    assert_same_samples(plain, channels_last)


def test_buffers_pickled_before_channels_last_frames_load_as_channels_first():
    buffer = image_buffer(None)
    del buffer.__dict__["channels_last_frames"]  # as pickled by the versions before the attribute
    restored = pickle.loads(pickle.dumps(buffer))
    assert restored.channels_last_frames is False
    assert_same_samples(image_buffer(None), restored)


class CountingEnv(gym.Env):
    """Observation = (env id, episode, step); ends by termination every 13 steps or a time limit at 9 (odd episodes)."""

    observation_space = VEC_SPACE
    action_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)

    def __init__(self, env_id: int) -> None:
        self.env_id = env_id
        self.episode = -1
        self.t = 0

    def _obs(self) -> np.ndarray:
        return frame(self.env_id, self.episode, self.t)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self.episode += 1
        self.t = 0
        return self._obs(), {}

    def step(self, action):
        self.t += 1
        terminated = self.t == 13
        truncated = self.episode % 2 == 1 and self.t == 9
        return self._obs(), float(self.t), terminated, truncated, {"cost": float(self.t % 2)}


def assert_consecutive(batch: SequenceBatch) -> None:
    obs = batch.observations.numpy()
    np.testing.assert_array_equal(obs[:, :, :2], np.repeat(obs[:, :1, :2], obs.shape[1], axis=1))
    np.testing.assert_array_equal(obs[:, :, 2], obs[:, :1, 2] + np.arange(obs.shape[1]))
    np.testing.assert_array_equal(batch.rewards.numpy(), obs[:, 1:, 2])
    np.testing.assert_array_equal(batch.costs.numpy(), obs[:, 1:, 2] % 2)
    np.testing.assert_array_equal(batch.terminated.numpy(), obs[:, 1:, 2] == 13)


def test_sb3_off_policy_integration(tmp_path):
    def make_model() -> SAC:
        env = DummyVecEnv([lambda: CountingEnv(0), lambda: CountingEnv(1)])
        kwargs = {"sequence_length": 4}
        return SAC("MlpPolicy", env, buffer_size=400, learning_starts=10_000, replay_buffer_class=SequenceReplayBuffer,
                   replay_buffer_kwargs=kwargs, device="cpu", seed=0)  # fmt: skip

    model = make_model()
    buffer = model.replay_buffer
    assert isinstance(buffer, SequenceReplayBuffer) and buffer.buffer_size == 200
    model.learn(100)
    assert_consecutive(buffer.sample(256))
    model.save_replay_buffer(tmp_path / "rb.pkl")

    other = make_model()
    other.load_replay_buffer(tmp_path / "rb.pkl")
    assert other.replay_buffer.device == other.device
    # The fresh env restarts its episode counter mid-episode of the stored data: windows must not join them
    other.learn(300)
    batch = other.replay_buffer.sample(512)
    assert_consecutive(batch)
    assert other.replay_buffer.full
