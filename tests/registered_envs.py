"""Registers the tiny ``HazardPoint-v0`` test env with Gymnasium, so the command line can make it by id:
``--env tests.registered_envs:HazardPoint-v0`` (also from a subprocess)."""

import gymnasium as gym

if "HazardPoint-v0" not in gym.registry:
    gym.register(id="HazardPoint-v0", entry_point="tests.synthetic_envs:HazardPointEnv")
