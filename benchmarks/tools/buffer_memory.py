"""
Memory and speed of ``SequenceReplayBuffer`` at the thesis size: 200,000 slots of 3x64x64 uint8 frames, 2-d actions.

Fills the buffer once with 500-step episodes of random frames, then times ``sample(32)`` and ``sample(64)``.

    PYTHONPATH=. python benchmarks/tools/buffer_memory.py [--size 200000] [--sequence-length 10] [--episode-length 500]
"""

import argparse
import time

import numpy as np
from gymnasium import spaces

from sb3_dsslac.common.buffers import SequenceReplayBuffer

FRAME_SHAPE = (3, 64, 64)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=200_000, help="frame slots")
    parser.add_argument("--sequence-length", type=int, default=10)
    parser.add_argument("--episode-length", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=200, help="timed calls per batch size")
    args = parser.parse_args()

    obs_space = spaces.Box(0, 255, shape=FRAME_SHAPE, dtype=np.uint8)
    act_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
    buffer = SequenceReplayBuffer(args.size, obs_space, act_space, device="cpu", sequence_length=args.sequence_length)

    frame_bytes = int(np.prod(FRAME_SHAPE))
    raw = args.size * frame_bytes
    print(f"SequenceReplayBuffer: {args.size:,} slots of {FRAME_SHAPE} uint8, 2-d actions, L={args.sequence_length}")
    for name in buffer._STORAGE:
        array = getattr(buffer, name)
        print(f"  {name:<14} {array.dtype!s:<8} {array.shape!s:<28} {array.nbytes:>15,} B")
    print(f"  {'total':<51} {buffer.nbytes:>15,} B ({buffer.nbytes / 1e9:.3f} GB)")
    print(f"  raw frames {args.size:,} x {frame_bytes:,} B = {raw:,} B ({raw / 1e9:.3f} GB); ratio {buffer.nbytes / raw:.4f}")

    # One pass over the ring: an episode of T steps takes T + 1 slots
    rng = np.random.default_rng(0)
    pool = rng.integers(0, 256, size=(257, 1, *FRAME_SHAPE), dtype=np.uint8)
    n_episodes = args.size // (args.episode_length + 1)
    start = time.perf_counter()
    for _ in range(n_episodes):
        for t in range(args.episode_length):
            done = np.array([t == args.episode_length - 1])
            infos = [{"cost": float(rng.random() < 0.1), "TimeLimit.truncated": bool(done[0])}]
            buffer.add(pool[t % 257], pool[(t + 1) % 257], rng.uniform(-1, 1, (1, 2)), rng.random(1), done, infos)
    elapsed = time.perf_counter() - start
    n_steps = n_episodes * args.episode_length
    print(f"filled {n_episodes} episodes x {args.episode_length} steps: {elapsed:.1f} s, {1e6 * elapsed / n_steps:.1f} us/add")

    np.random.seed(0)
    for batch_size in (32, 64):
        buffer.sample(batch_size)  # warm-up
        start = time.perf_counter()
        for _ in range(args.repeats):
            buffer.sample(batch_size)
        mean_us = 1e6 * (time.perf_counter() - start) / args.repeats
        print(f"sample({batch_size}): {mean_us:,.0f} us mean over {args.repeats} calls")


if __name__ == "__main__":
    main()
