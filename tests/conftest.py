import os

# Headless rendering for every test: Mesa's EGL works on CPU-only machines.
os.environ.setdefault("MUJOCO_GL", "egl")
