"""DS-SLAC for Stable-Baselines3: safe reinforcement learning from pixels with a distributional cost critic."""

from sb3_dsslac.buffers import SequenceReplayBuffer
from sb3_dsslac.dsslac import DSSLAC
from sb3_dsslac.evaluation import CostEvalCallback, evaluate_policy_with_cost
from sb3_dsslac.lagrange import LagrangeCallback
from sb3_dsslac.policies import LatentPolicy
from sb3_dsslac.version import __version__

__all__ = [
    "DSSLAC",
    "CostEvalCallback",
    "LagrangeCallback",
    "LatentPolicy",
    "SequenceReplayBuffer",
    "__version__",
    "evaluate_policy_with_cost",
]
