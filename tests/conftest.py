import os

import torch

# Headless rendering for every test: Mesa's EGL works on CPU-only machines.
os.environ.setdefault("MUJOCO_GL", "egl")

# The test networks are tiny: one intra-op thread is faster, and two threads stall badly when the other core is busy.
torch.set_num_threads(1)
