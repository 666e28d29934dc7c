"""The model of a run's newest checkpoint with its replay buffer, as the diagnostics that replay a run's windows read it."""

from pathlib import Path

import torch as th

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.checkpoints import Checkpoint, find_checkpoint


def checkpoint_model(run: Path) -> tuple[DSSLAC, Checkpoint]:
    """
    The model of ``run``'s newest complete checkpoint on the CPU, its replay buffer loaded, with torch on one thread.

    :raises SystemExit: naming ``run`` where it has no complete checkpoint
    """
    checkpoint = find_checkpoint(run)
    if checkpoint is None:
        raise SystemExit(f"No checkpoint (model and replay buffer) in {run}")
    th.set_num_threads(1)
    model = DSSLAC.load(checkpoint.model, device="cpu")
    model.load_replay_buffer(checkpoint.replay_buffer)
    return model, checkpoint
