"""
DS-SLAC for Stable-Baselines3: safe reinforcement learning from pixels with a distributional cost critic.

The folders are the layers, each importing only those before it: ``nn`` (torch networks), ``common`` (the SB3 pieces),
``engine`` (the updates), ``dsslac.py`` and ``presets.py`` (the algorithm), ``app`` (command line, tuning, zoo, plots).
"""

import sys

from sb3_dsslac.common import buffers, policies, timing
from sb3_dsslac.common.buffers import SequenceReplayBuffer
from sb3_dsslac.common.evaluation import CostEvalCallback, evaluate_policy_with_cost
from sb3_dsslac.common.lagrange import LagrangeCallback
from sb3_dsslac.common.policies import LatentPolicy
from sb3_dsslac.dsslac import DSSLAC
from sb3_dsslac.presets import PRESETS, preset_env_kwargs, preset_hyperparams
from sb3_dsslac.version import __version__

# Models and replay buffers saved before the package had folders name these modules' classes by their old paths
for _module in (buffers, policies, timing):
    sys.modules.setdefault(f"sb3_dsslac.{_module.__name__.rsplit('.', 1)[1]}", _module)

__all__ = [
    "DSSLAC",
    "PRESETS",
    "CostEvalCallback",
    "LagrangeCallback",
    "LatentPolicy",
    "SequenceReplayBuffer",
    "__version__",
    "evaluate_policy_with_cost",
    "preset_env_kwargs",
    "preset_hyperparams",
]
