"""Sequence replay buffer for DS-SLAC: every frame is stored once, windows are rebuilt by index arithmetic."""

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import BaseBuffer, ReplayBuffer
from stable_baselines3.common.vec_env import VecNormalize

from sb3_dsslac.common.env_info import cost_from_info


def _channels_last(frames: np.ndarray) -> np.ndarray:
    """Images (..., C, H, W) as (..., H, W, C): a view."""
    return np.moveaxis(frames, -3, -1)


def _channels_first(frames: np.ndarray) -> np.ndarray:
    """Images (..., H, W, C) as (..., C, H, W): a view."""
    return np.moveaxis(frames, -1, -3)


class SequenceBatch(NamedTuple):
    """
    A batch of ``B`` windows of ``L = sequence_length`` consecutive transitions of one episode each.

    :param observations: (B, L+1, *obs_shape) frames in the stored dtype (uint8 for images, float32 otherwise); images
        (C, H, W) with channels-last strides where the buffer stores them so (``set_channels_last_frames``)
    :param actions: (B, L, action_dim) float32 buffer actions (scaled to [-1, 1] by SB3)
    :param rewards: (B, L) float32
    :param costs: (B, L) float32, from ``info["cost"]``
    :param terminated: (B, L) float32, 1.0 where the transition ended its episode by a true termination
    :param episode_start_index: with a burn-in of ``K`` frames (``L`` then counts them: the fields span ``K`` + the
        trained transitions), the index in the window of its episode's first frame, clamped to [-1, ``K``]: -1 where
        the episode began before the window, ``K`` where the trained part starts the episode (B,) int64; the frames
        before it are another episode's or unwritten, and the burn-in restarts there. None without a burn-in
    :param stored_belief: with stored beliefs (``store_beliefs``), the acting filter's z2 after the frame before the
        window, where that frame is of the window's episode (``episode_start_index`` -1; zeros elsewhere) (B, Z2)
    :param stored_action: the action that left that frame (B, A)
    """

    observations: th.Tensor
    actions: th.Tensor
    rewards: th.Tensor
    costs: th.Tensor
    terminated: th.Tensor
    episode_start_index: th.Tensor | None = None
    stored_belief: th.Tensor | None = None
    stored_action: th.Tensor | None = None

    def rows(self, part: slice) -> "SequenceBatch":
        """The windows ``part`` of the batch (a slice of its first dim), every field cut alike."""
        return SequenceBatch(*(None if field is None else field[part] for field in self))

    def without_burn_in(self, frames: int) -> "SequenceBatch":
        """The batch without its first ``frames`` frames and transitions (the burn-in): the trained windows."""
        fields = (self.observations, self.actions, self.rewards, self.costs, self.terminated)
        return SequenceBatch(*(field[:, frames:] for field in fields))


class SequenceReplayBuffer(ReplayBuffer):
    """
    Replay buffer of frames stored once, sampled as windows of ``sequence_length`` transitions.

    Sampling runs on ``device``: :meth:`sample_indices` draws the windows of a whole training burst at once (one small
    upload), and :meth:`gather` cuts them out of the stored arrays with tensor indexing, so an update never loops over
    the batch in Python nor copies frames from the host. On the CPU the tensors are views of the host arrays; on a
    GPU the buffer keeps a device copy of every stored array (frames included: 2.46 GB for 200k 64x64 frames), brought
    up to date with the records written since the last sampling, so each burst uploads each new frame once.

    Each env owns a ring of ``buffer_size // n_envs`` records. Record ``k`` holds frame ``o_k`` and the fields of the
    transition leaving it (action, reward, cost, terminated). An episode of ``T`` steps uses ``T + 1`` records: its
    last record holds the final (terminal or truncated) frame and no transition. A window is ``sequence_length + 1``
    consecutive records of one episode, so windows never cross episode boundaries and episodes shorter than
    ``sequence_length`` steps give none.

    Images are stored (C, H, W), or (H, W, C) after ``set_channels_last_frames(True)``: a channels-last model then
    reads the sampled frames without a transpose.

    :param buffer_size: Number of frame slots over all envs (each env gets ``buffer_size // n_envs``)
    :param observation_space: Box observation space (uint8 spaces are stored as uint8, others as float32)
    :param action_space: Box action space
    :param device: PyTorch device of the sampled tensors
    :param n_envs: Number of parallel environments
    :param optimize_memory_usage: Must be False: frames are already stored once
    :param handle_timeout_termination: If True, a time-limit truncation (``info["TimeLimit.truncated"]``)
        is not a termination
    :param sequence_length: Number of transitions ``L`` per window (``L + 1`` frames)
    :param burn_in: Number of frames ``K`` before each window that come with it for the learner to filter without
        gradient (``DSSLAC``'s ``burn_in``): the windows are drawn as without them (uniformly over the stored windows of
        ``L`` transitions) and then reach back ``K`` records, so a sampled window spans ``K + L`` transitions, its
        ``episode_start_index`` marking where its episode began if that is within them
    """

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    costs: np.ndarray
    terminated: np.ndarray
    episode_ids: np.ndarray
    episode_steps: np.ndarray
    beliefs: np.ndarray

    _STORAGE = ("observations", "actions", "rewards", "costs", "terminated", "episode_ids", "episode_steps", "beliefs")
    _SAMPLED = ("observations", "actions", "rewards", "costs", "terminated", "beliefs")

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: th.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        sequence_length: int = 10,
        burn_in: int = 0,
    ) -> None:
        if not isinstance(observation_space, spaces.Box):
            raise ValueError(
                f"SequenceReplayBuffer supports only Box observation spaces (images or vectors), got {observation_space}"
            )
        if not isinstance(action_space, spaces.Box):
            raise ValueError(f"SequenceReplayBuffer supports only Box (continuous) action spaces, got {action_space}")
        if optimize_memory_usage:
            raise ValueError(
                "SequenceReplayBuffer already stores every frame once; optimize_memory_usage=True is not supported"
            )
        if sequence_length < 1:
            raise ValueError(f"sequence_length must be >= 1, got {sequence_length}")
        if burn_in < 0:
            raise ValueError(f"burn_in must be >= 0, got {burn_in}")
        # Skip ReplayBuffer.__init__: it would allocate per-transition observations and next_observations
        BaseBuffer.__init__(self, buffer_size, observation_space, action_space, device, n_envs=n_envs)
        self.buffer_size = buffer_size // n_envs
        if self.buffer_size < burn_in + sequence_length + 1:
            raise ValueError(
                f"buffer_size={buffer_size} gives {self.buffer_size} slots per env for n_envs={n_envs}, fewer than the "
                f"{burn_in + sequence_length + 1} frames of one window (sequence_length={sequence_length}, burn_in={burn_in})"
            )
        self.optimize_memory_usage = False
        self.handle_timeout_termination = handle_timeout_termination
        self.sequence_length = sequence_length
        self.burn_in = burn_in
        self.frame_dtype = np.uint8 if observation_space.dtype == np.uint8 else np.float32
        self.channels_last_frames = False

        shape = (self.buffer_size, self.n_envs)
        self.observations = np.zeros((*shape, *self.obs_shape), dtype=self.frame_dtype)
        self.actions = np.zeros((*shape, self.action_dim), dtype=np.float32)
        self.rewards = np.zeros(shape, dtype=np.float32)
        self.costs = np.zeros(shape, dtype=np.float32)
        self.terminated = np.zeros(shape, dtype=np.float32)
        # Episode id (unique per episode, increasing) and step within the episode of each record; -1 / 0 when unwritten
        self.episode_ids = np.full(shape, -1, dtype=np.int64)
        self.episode_steps = np.zeros(shape, dtype=np.int64)
        # The acting filter's z2 after each record's frame, with ``store_beliefs`` (no columns without)
        self.beliefs = np.zeros((*shape, 0), dtype=np.float32)
        self._pending_beliefs: np.ndarray | None = None
        self._device_copy: dict[str, th.Tensor] | None = None  # device copies of the _SAMPLED arrays (GPU only)
        self._init_counters()

    def _init_counters(self) -> None:
        self._n_records = np.zeros(self.n_envs, dtype=np.int64)  # records written so far by each env (monotone)
        self._episode_start = np.ones(self.n_envs, dtype=bool)  # the next `add` of that env opens an episode
        self._next_episode_id = 0
        self._n_windows = 0  # number of valid windows currently in the buffer
        self._n_records_on_device = np.zeros(self.n_envs, dtype=np.int64)  # records already in the device copy
        self.pos = 0
        self.full = False

    @property
    def nbytes(self) -> int:
        """Bytes held by all host storage arrays."""
        return sum(getattr(self, name).nbytes for name in self._STORAGE)

    def reset(self) -> None:
        """Forget every stored record (the arrays are kept)."""
        self.episode_ids.fill(-1)
        self.episode_steps.fill(0)
        self._init_counters()

    def set_channels_last_frames(self, channels_last: bool) -> None:
        """
        Store images (H, W, C) (``channels_last``) or (C, H, W) from now on, moving the frames stored so far; sampled
        frames stay (C, H, W) tensors either way, with the strides of the stored order. No-op for vector observations.
        """
        if len(self.obs_shape) != 3 or channels_last == self.channels_last_frames:
            return
        n_rows = min(int(self._n_records.max()), self.buffer_size)
        frames = (_channels_last if channels_last else _channels_first)(self.observations[:n_rows])
        # The unwritten rows stay untouched zero pages
        self.observations = np.zeros((self.buffer_size, self.n_envs, *frames.shape[2:]), dtype=self.frame_dtype)
        self.observations[:n_rows] = frames
        self.channels_last_frames = channels_last
        self._device_copy = None

    @property
    def stores_beliefs(self) -> bool:
        """Whether records keep the acting filter's belief (``store_beliefs``)."""
        return self.beliefs.shape[-1] > 0

    def store_beliefs(self, belief_dim: int) -> None:
        """
        Keep the acting filter's z2 (``belief_dim`` floats) with every record from now on, noted by ``note_beliefs``
        before each ``add``: a window with a burn-in then also brings the belief after the frame before it, where the
        learner's burn-in starts (R2D2's stored state). Only with a burn-in; the records stored so far get zeros.
        """
        if self.burn_in == 0:
            raise ValueError("stored beliefs start a burn-in: they need burn_in >= 1")
        if belief_dim != self.beliefs.shape[-1]:
            self.beliefs = np.zeros((self.buffer_size, self.n_envs, belief_dim), dtype=np.float32)
            self._device_copy = None

    def note_beliefs(self, beliefs: np.ndarray) -> None:
        """The beliefs (n_envs, belief_dim) of the frames the next ``add``'s actions were taken from."""
        self._pending_beliefs = np.asarray(beliefs, dtype=np.float32).reshape(self.n_envs, -1)

    def refresh_beliefs(
        self, belief_step: Callable[[th.Tensor, th.Tensor, th.Tensor, th.Tensor], th.Tensor], max_rows: int = 4096
    ) -> int:
        """
        Filter every stored episode again and keep the new beliefs in place of the stored ones, which the acting filter
        wrote when each frame was acted from, with the latent model of that time (the warm-up's with an untrained one).
        All stored episodes step together, their step 0 first; a record whose episode's earlier records the ring has
        overwritten is continued from its predecessor's stored belief.

        :param belief_step: ``(frames (N, *obs_shape) as stored (uint8 images), z2_prev (N, Z2), action_prev (N, A),
            episode_start (N,) bool) -> z2 (N, Z2)``, on ``self.device``: the acting filter's step
        :param max_rows: records filtered per call of ``belief_step``
        :return: the number of beliefs written
        """
        if not self.stores_beliefs:
            raise ValueError("this buffer stores no beliefs to refresh: call store_beliefs first")
        written = self.episode_ids >= 0
        refreshed = 0
        for step in range(int(self.episode_steps[written].max(initial=-1)) + 1):
            slots, envs = np.nonzero(written & (self.episode_steps == step))
            previous = (slots - 1) % self.buffer_size
            if step > 0:  # continue only where the previous record is still this episode's
                kept = self.episode_ids[previous, envs] == self.episode_ids[slots, envs]
                kept &= self.episode_steps[previous, envs] == step - 1
                slots, envs, previous = slots[kept], envs[kept], previous[kept]
            for part in range(0, len(slots), max_rows):
                rows = slice(part, part + max_rows)
                frames = self.observations[slots[rows], envs[rows]]
                n_rows = len(frames)
                opens = th.full((n_rows,), step == 0, dtype=th.bool, device=self.device)
                if step == 0:
                    z2_prev = th.zeros(n_rows, self.beliefs.shape[-1], device=self.device)
                    action_prev = th.zeros(n_rows, self.action_dim, device=self.device)
                else:
                    z2_prev = th.as_tensor(self.beliefs[previous[rows], envs[rows]], device=self.device)
                    action_prev = th.as_tensor(self.actions[previous[rows], envs[rows]], device=self.device)
                frames = _channels_first(frames) if self.channels_last_frames else frames
                z2 = belief_step(th.as_tensor(frames, device=self.device), z2_prev, action_prev, opens)
                self.beliefs[slots[rows], envs[rows]] = z2.float().cpu().numpy()
                refreshed += n_rows
        if self._device_copy is not None:
            self._device_copy["beliefs"].copy_(th.from_numpy(self.beliefs))
        return refreshed

    def _windows_valid(self, starts: np.ndarray, envs: np.ndarray, length: int) -> np.ndarray:
        """Whether records at slots ``starts .. starts + length`` (mod ring) of ``envs`` are steps of one episode."""
        # ids equal at both ends: one episode; step difference == length: no unwritten slot and no wrap past the head
        ends = (starts + length) % self.buffer_size
        same_episode = self.episode_ids[starts, envs] == self.episode_ids[ends, envs]
        return same_episode & (self.episode_steps[ends, envs] - self.episode_steps[starts, envs] == length)

    def _write_records(self, envs: np.ndarray, frames: np.ndarray, episode_ids: np.ndarray, steps: np.ndarray) -> None:
        """Append one record (frame, no transition yet) to the ring of each env in ``envs`` (distinct indices)."""
        slots = self._n_records[envs] % self.buffer_size
        overwrite = self._n_records[envs] >= self.buffer_size
        if overwrite.any():
            # The oldest record leaves the ring, and with it the only window that could still start there
            self._n_windows -= int(self._windows_valid(slots[overwrite], envs[overwrite], self.sequence_length).sum())
        self.observations[slots, envs] = _channels_last(frames) if self.channels_last_frames else frames
        self.episode_ids[slots, envs] = episode_ids
        self.episode_steps[slots, envs] = steps
        self.actions[slots, envs] = 0.0
        self.rewards[slots, envs] = 0.0
        self.costs[slots, envs] = 0.0
        self.terminated[slots, envs] = 0.0
        self._n_windows += int((steps >= self.sequence_length).sum())
        self._n_records[envs] += 1

    def add(
        self,
        obs: np.ndarray,
        next_obs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        done: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """
        Store one step of every env.

        :param obs: (n_envs, *obs_shape) observations the actions were taken from
        :param next_obs: (n_envs, *obs_shape) next observations (the terminal observation where ``done``)
        :param action: (n_envs, action_dim) buffer actions
        :param reward: (n_envs,) rewards
        :param done: (n_envs,) episode ends (termination or truncation)
        :param infos: one dict per env, each with the step cost in ``info["cost"]``
        """
        costs = [cost_from_info(info) for info in infos]  # read first: a missing cost must not leave a half-written step
        obs = np.asarray(obs).reshape((self.n_envs, *self.obs_shape))
        next_obs = np.asarray(next_obs).reshape((self.n_envs, *self.obs_shape))
        done = np.asarray(done, dtype=bool).reshape(self.n_envs)
        all_envs = np.arange(self.n_envs)

        # An env also opens an episode when `obs` is not the frame it stored last (e.g. the env was reset
        # between two `learn` calls): the interrupted episode then ends there like a truncation.
        current = (self._n_records - 1) % self.buffer_size
        stored = self.observations[current, all_envs]
        if self.channels_last_frames:
            stored = _channels_first(stored)
        moved = np.any(stored.reshape(self.n_envs, -1) != obs.astype(self.frame_dtype).reshape(self.n_envs, -1), axis=1)
        starting = np.flatnonzero(self._episode_start | moved)
        if len(starting) > 0:
            new_ids = self._next_episode_id + np.arange(len(starting))
            self._next_episode_id += len(starting)
            self._write_records(starting, obs[starting], new_ids, np.zeros(len(starting), dtype=np.int64))

        current = (self._n_records - 1) % self.buffer_size
        timeouts = np.array([info.get("TimeLimit.truncated", False) for info in infos], dtype=bool)
        terminated = done & ~timeouts if self.handle_timeout_termination else done
        self.actions[current, all_envs] = np.asarray(action).reshape(self.n_envs, self.action_dim)
        self.rewards[current, all_envs] = np.asarray(reward).reshape(self.n_envs)
        self.costs[current, all_envs] = costs
        self.terminated[current, all_envs] = terminated
        if self.stores_beliefs:
            if self._pending_beliefs is None:
                raise ValueError("this buffer stores the acting filter's beliefs: call note_beliefs before each add")
            self.beliefs[current, all_envs] = self._pending_beliefs
            self._pending_beliefs = None
        self._write_records(all_envs, next_obs, self.episode_ids[current, all_envs], self.episode_steps[current, all_envs] + 1)
        self._episode_start = done.copy()

        most_records = int(self._n_records.max())
        self.full = most_records >= self.buffer_size
        self.pos = most_records % self.buffer_size

    def can_sample(self) -> bool:
        """Whether at least one valid window is stored."""
        return self._n_windows > 0

    def _sample_starts(self, batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        """Draw ``batch_size`` (start slot, env) pairs uniformly over valid windows, each of shape (batch_size,)."""
        n_rows = min(int(self._n_records.max()), self.buffer_size)
        n_candidates = n_rows * self.n_envs
        # Rejection sampling, sized from the known fraction of valid candidates, for at most two rounds
        n_draws = int(2 * batch_size * n_candidates / self._n_windows) + 16
        accepted: list[np.ndarray] = []
        n_accepted = 0
        for _ in range(2):
            if n_draws >= n_candidates or n_accepted >= batch_size:
                break
            flat = np.random.randint(0, n_candidates, size=n_draws)
            flat = flat[self._windows_valid(flat // self.n_envs, flat % self.n_envs, self.sequence_length)]
            if self.burn_in > 0:
                flat = flat[self._burn_in_stored(flat // self.n_envs, flat % self.n_envs)]
            accepted.append(flat)
            n_accepted += len(flat)
        if n_accepted < batch_size:
            # Few valid windows (or bad luck): enumerate them all
            valid = self.valid_windows(self.sequence_length, n_rows)
            if self.burn_in > 0:
                valid = valid[self._burn_in_stored(valid // self.n_envs, valid % self.n_envs)]
            accepted.append(valid[np.random.randint(0, len(valid), size=batch_size - n_accepted)])
        flat = np.concatenate(accepted)[:batch_size]
        return flat // self.n_envs, flat % self.n_envs

    def _burn_in_frames(self, starts: np.ndarray, envs: np.ndarray) -> np.ndarray:
        """
        How many records before each window are of its episode, up to the ``burn_in`` ones and, with stored beliefs, the
        one before them, whose belief the burn-in starts from: min(step of its first frame, K (+ 1)).
        """
        return np.minimum(self.episode_steps[starts, envs], self.burn_in + int(self.stores_beliefs))

    def _burn_in_stored(self, starts: np.ndarray, envs: np.ndarray) -> np.ndarray:
        """
        Whether the records of each window's episode among the ``burn_in`` before it are still stored (the ring may
        have overwritten its oldest ones).
        """
        back = self._burn_in_frames(starts, envs)
        return self._windows_valid((starts - back) % self.buffer_size, envs, back + self.sequence_length)

    def valid_windows(self, length: int, n_rows: int | None = None) -> np.ndarray:
        """
        Every stored window of ``length`` transitions starting in the first ``n_rows`` slots (default: all), as flat
        indices ``start_slot * n_envs + env``, in storage order.
        """
        every = np.arange((self.buffer_size if n_rows is None else n_rows) * self.n_envs)
        return every[self._windows_valid(every // self.n_envs, every % self.n_envs, length)]

    def _count_steps(self) -> int:
        """Number of stored transitions (records followed by a record of the same episode)."""
        return len(self.valid_windows(1))

    def stored_observations(self) -> np.ndarray:
        """Every frame written so far, (n_frames, *obs_shape), in storage order."""
        stored = self.observations[self.episode_ids >= 0]
        return _channels_first(stored) if self.channels_last_frames else stored

    def _stored_tensors(self) -> dict[str, th.Tensor]:
        """
        The sampled arrays as tensors on ``self.device``: views of the host arrays on the CPU, else the device copy as
        of the last :meth:`_sync_device_copy` (made then if there is none yet).
        """
        if self.device.type == "cpu":
            return {name: th.from_numpy(getattr(self, name)) for name in self._SAMPLED}
        if self._device_copy is None:
            self._sync_device_copy()
        assert self._device_copy is not None
        return self._device_copy

    def _sync_device_copy(self) -> None:
        """On a GPU, make the device copy, or bring it up to date with the records written since the last sync."""
        if self.device.type == "cpu":
            return
        if self._device_copy is None:
            self._device_copy = {name: th.from_numpy(getattr(self, name)).to(self.device) for name in self._SAMPLED}
            self._n_records_on_device = self._n_records.copy()
        elif not np.array_equal(self._n_records, self._n_records_on_device):  # every `add` writes a record
            self._upload_new_records()

    def _upload_new_records(self) -> None:
        """Copy the slots written since the last upload (and the record before them, whose transition fields change
        on the next ``add``) to the device copy: at most two contiguous chunks per array."""
        assert self._device_copy is not None
        first = max(int(self._n_records_on_device.min()) - 1, 0)
        end = int(self._n_records.max())
        if end - first >= self.buffer_size:
            chunks = [(0, self.buffer_size)]
        else:
            start, stop = first % self.buffer_size, end % self.buffer_size
            chunks = [(start, stop)] if start <= stop else [(start, self.buffer_size), (0, stop)]
        for name, tensor in self._device_copy.items():
            for start, stop in chunks:
                if stop > start:
                    tensor[start:stop].copy_(th.from_numpy(getattr(self, name)[start:stop]))
        self._n_records_on_device = self._n_records.copy()

    def sample_indices(self, n_batches: int, batch_size: int) -> th.Tensor:
        """
        Draw the windows of ``n_batches`` batches at once, uniformly over valid windows, and bring the device copy up
        to date. Pass each ``[k]`` to :meth:`gather`; they stay valid until the next ``add``.

        :return: (n_batches, batch_size, 2) int64 tensor of (start slot, env) on ``self.device``; with a burn-in,
            (n_batches, batch_size, 3): the index of the episode's first frame in the window (``SequenceBatch``) third
        """
        if not self.can_sample():
            raise ValueError(
                f"Cannot sample: the buffer stores {self._count_steps()} steps but no episode has "
                f"{self.sequence_length} consecutive stored steps; a window needs sequence_length={self.sequence_length} "
                f"steps ({self.sequence_length + 1} frames) of one episode, and shorter episodes give no window"
            )
        starts, envs = self._sample_starts(n_batches * batch_size)
        self._sync_device_copy()  # upload the new records once per burst, not inside the updates
        columns = [starts, envs]
        if self.burn_in > 0:  # K - step, in [-1, K]: -1 where the frame before the burn-in is of the episode too
            columns.append(self.burn_in - np.minimum(self.episode_steps[starts, envs], self.burn_in + 1))
        indices = np.stack(columns, axis=-1).reshape(n_batches, batch_size, len(columns))
        return th.as_tensor(indices).to(self.device)

    def gather(self, indices: th.Tensor) -> SequenceBatch:
        """
        Cut the windows ``indices`` (B, 2) of :meth:`sample_indices` out of the stored arrays, on ``self.device``.
        Frames keep their stored dtype (uint8 images): the policy converts them to floats on the device. With a burn-in
        of ``K`` frames each window reaches ``K`` records further back (``K + L`` transitions).
        """
        stored = self._stored_tensors()
        length = self.burn_in + self.sequence_length
        offsets = th.arange(-self.burn_in, self.sequence_length + 1, device=indices.device)
        slots = (indices[:, :1] + offsets) % self.buffer_size  # (B, K+L+1)
        rows = slots * self.n_envs + indices[:, 1:2]  # rows of the (slot, env)-flattened arrays

        def take(name: str, flat_rows: th.Tensor, length: int) -> th.Tensor:
            # index_select of whole rows: several times faster than advanced indexing, on the CPU too
            tensor = stored[name]
            flat = tensor.view(self.buffer_size * self.n_envs, *tensor.shape[2:])
            return flat.index_select(0, flat_rows).view(len(indices), length, *tensor.shape[2:])

        observations = take("observations", rows.view(-1), length + 1)
        if self.channels_last_frames:  # (B, L+1, H, W, C) -> (B, L+1, C, H, W), channels-last
            observations = observations.permute(0, 1, 4, 2, 3)
        transition_rows = rows[:, :-1].reshape(-1)  # flattened once for the four transition fields
        batch = SequenceBatch(
            observations=observations,
            actions=take("actions", transition_rows, length),
            rewards=take("rewards", transition_rows, length),
            costs=take("costs", transition_rows, length),
            terminated=take("terminated", transition_rows, length),
            episode_start_index=indices[:, 2] if self.burn_in > 0 else None,
        )
        if self.stores_beliefs:  # the record before the burn-in: its belief and action, where it is of the episode
            before = (rows[:, 0] - self.n_envs) % (self.buffer_size * self.n_envs)
            of_episode = (indices[:, 2] == -1).unsqueeze(-1)
            belief = take("beliefs", before, 1).squeeze(1)
            action = take("actions", before, 1).squeeze(1)
            batch = batch._replace(stored_belief=belief * of_episode, stored_action=action * of_episode)
        return batch

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> SequenceBatch:  # type: ignore[override]
        """
        Sample windows of ``sequence_length`` transitions (``sequence_length + 1`` frames), uniformly over valid windows.

        :param batch_size: Number of windows ``B``
        :param env: VecNormalize to normalise observations (returned as float32) and rewards, as SB3 does
        :return: the batch on ``self.device``
        """
        batch = self.gather(self.sample_indices(1, batch_size)[0])
        if env is None:
            return batch
        observations = self._normalize_obs(batch.observations.cpu().numpy(), env)
        rewards = self._normalize_reward(batch.rewards.cpu().numpy(), env)
        return batch._replace(
            observations=th.as_tensor(observations).to(self.device), rewards=th.as_tensor(rewards).to(self.device)
        )

    def __getstate__(self) -> dict[str, Any]:
        """Pickle only the slots written so far, so an early checkpoint is not the size of the full buffer."""
        state = self.__dict__.copy()
        state["_device_copy"] = None  # rebuilt from the host arrays at the next sample
        n_rows = min(int(self._n_records.max()), self.buffer_size)
        for name in self._STORAGE:
            state[name] = state[name][:n_rows]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.channels_last_frames = False  # buffers pickled before frames could be stored channels-last
        self.burn_in = 0  # and before windows could bring a burn-in
        self._pending_beliefs = None
        if "beliefs" not in state:  # or records their beliefs
            state["beliefs"] = np.zeros((*state["rewards"].shape, 0), dtype=np.float32)
        self.__dict__.update(state)
        for name in self._STORAGE:
            stored = state[name]
            if len(stored) < self.buffer_size:
                array = np.full((self.buffer_size, *stored.shape[1:]), -1 if name == "episode_ids" else 0, dtype=stored.dtype)
                array[: len(stored)] = stored
                setattr(self, name, array)
