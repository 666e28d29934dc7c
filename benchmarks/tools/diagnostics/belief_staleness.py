"""
How stale are a run's stored beliefs (``stored_beliefs=True``)? Each record keeps the z2 that the acting filter reached
when the frame was acted from, with the latent model of that time; the burn-in of a sampled window starts from it. On a
run's newest checkpoint this re-filters every stored episode with the checkpoint's model
(``SequenceReplayBuffer.refresh_beliefs``) and prints, by the age of the records, the mean distance |stored - refreshed|
of z2, beside the floor that the filter's sampling noise alone gives (two refreshes with different noise), and the
distance that is left after a window's burn-in from the stored belief against one from the refreshed belief (the same
frames and noise). Also how long one refresh takes, the cost of ``belief_refresh_interval``.

    python benchmarks/tools/diagnostics/belief_staleness.py runs/<run>    # a run with stored beliefs and a checkpoint
"""

import argparse
import itertools
import sys
import time
from pathlib import Path

# The benchmarks' shared modules (machine.py) sit one folder up
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
import torch as th
from machine import cpu_model
from run_checkpoint import checkpoint_model

from sb3_dsslac.common.buffers import SequenceReplayBuffer
from sb3_dsslac.common.policies import LatentPolicy


def refreshed_beliefs(policy: LatentPolicy, buffer: SequenceReplayBuffer, seed: int) -> tuple[np.ndarray, float]:
    """The buffer's beliefs re-filtered by ``policy`` with noise ``seed`` (the buffer left as it was), and the seconds."""
    stored = buffer.beliefs.copy()
    th.manual_seed(seed)
    start = time.perf_counter()
    with th.no_grad():
        buffer.refresh_beliefs(lambda *inputs: policy.belief_step(*inputs, deterministic=False)[1])
    seconds = time.perf_counter() - start
    refreshed, buffer.beliefs = buffer.beliefs, stored
    return refreshed, seconds


def burned_in(policy: LatentPolicy, buffer: SequenceReplayBuffer, beliefs: np.ndarray, slots: np.ndarray, frames: int):
    """z2 after ``frames`` frames filtered from the belief of the record before them, for windows opening at ``slots``."""
    th.manual_seed(1)
    z2 = th.as_tensor(beliefs[slots - frames - 1, 0])
    action = th.as_tensor(buffer.actions[slots - frames - 1, 0])
    with th.no_grad():
        for back in range(frames, 0, -1):
            observations = buffer.observations[slots - back, 0]
            if buffer.channels_last_frames:
                observations = np.moveaxis(observations, -1, -3)
            episode_start = th.zeros(len(slots), dtype=th.bool)
            _, z2 = policy.belief_step(th.as_tensor(observations), z2, action, episode_start, deterministic=False)
            action = th.as_tensor(buffer.actions[slots - back, 0])
    return z2.numpy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a run folder with a checkpoint (model and replay buffer)")
    parser.add_argument("--age-bins", type=int, default=5, help="groups of records by when they were written")
    parser.add_argument("--windows", type=int, default=4000, help="windows whose burn-in is compared")
    args = parser.parse_args()
    model, checkpoint = checkpoint_model(args.run)
    buffer = model.replay_buffer
    if not model.stored_beliefs or buffer.n_envs != 1 or buffer.full:
        raise SystemExit("This tool reads runs with stored_beliefs=True, one env and a buffer that has not wrapped")
    policy = model.policy
    policy.set_training_mode(False)
    print(f"{checkpoint.model} ({checkpoint.timesteps} agent steps, burn_in={model.burn_in}), {cpu_model()}, 1 thread")

    refreshed, seconds = refreshed_beliefs(policy, buffer, seed=0)
    again, _ = refreshed_beliefs(policy, buffer, seed=1)
    ids, steps = buffer.episode_ids[:, 0], buffer.episode_steps[:, 0]
    acted_from = np.flatnonzero((ids >= 0) & (np.roll(ids, -1) == ids))  # records followed by one of their episode
    size = np.linalg.norm(refreshed[acted_from, 0], axis=1).mean()
    records, dimension = int((ids >= 0).sum()), buffer.beliefs.shape[-1]
    print(f"one refresh of {records} records: {seconds:.1f} s; mean |z2| {size:.2f} (dimension {dimension})")

    rng = np.random.default_rng(0)
    windows = rng.choice(acted_from[steps[acted_from] > model.burn_in + 1], args.windows)
    from_stored = burned_in(policy, buffer, buffer.beliefs, windows, model.burn_in)
    from_refreshed = burned_in(policy, buffer, refreshed, windows, model.burn_in)
    print()
    print(f"| records (agent steps) | |stored - refreshed| | noise floor | after a {model.burn_in}-frame burn-in |")
    print("|---|---:|---:|---:|")
    edges = np.linspace(0, acted_from.max() + 1, args.age_bins + 1).astype(int)
    for low, high in itertools.pairwise(edges):
        rows = acted_from[(acted_from >= low) & (acted_from < high)]
        stale = np.linalg.norm(buffer.beliefs[rows, 0] - refreshed[rows, 0], axis=1).mean()
        floor = np.linalg.norm(again[rows, 0] - refreshed[rows, 0], axis=1).mean()
        in_bin = (windows >= low) & (windows < high)
        left = np.linalg.norm(from_stored[in_bin] - from_refreshed[in_bin], axis=1).mean()
        print(f"| {low}-{high} | {stale:.2f} | {floor:.2f} | {left:.2f} |")


if __name__ == "__main__":
    main()
