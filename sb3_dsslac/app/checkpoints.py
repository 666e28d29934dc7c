"""
The checkpoints of a run folder: the model and its replay buffer, each written whole (``common.atomic``), then a marker
naming their sizes, written last: a checkpoint counts only once its marker is there. The older checkpoint goes only
after the newer one is complete, and a resume takes the newest complete checkpoint that loads.
"""

import json
import sys
from dataclasses import dataclass
from pathlib import Path

from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.type_aliases import GymEnv

from sb3_dsslac.common.atomic import atomic_file, remove_partial_files, write_atomic
from sb3_dsslac.common.timing import measured
from sb3_dsslac.dsslac import DSSLAC

CHECKPOINT_DIR = "checkpoints"
CHECKPOINT_PREFIX = "dsslac"


@dataclass
class Checkpoint:
    """A complete checkpoint of a run folder: model, replay buffer, and its agent steps."""

    model: Path
    replay_buffer: Path
    timesteps: int


def checkpoint_files(folder: Path, timesteps: int) -> tuple[Path, Path, Path]:
    """The model, the replay buffer and the marker of the checkpoint at ``timesteps`` agent steps in ``folder``."""
    return (
        folder / f"{CHECKPOINT_PREFIX}_{timesteps}_steps.zip",
        folder / f"{CHECKPOINT_PREFIX}_replay_buffer_{timesteps}_steps.pkl",
        folder / f"{CHECKPOINT_PREFIX}_{timesteps}_steps.json",
    )


def save_checkpoint(model: DSSLAC, folder: Path) -> Checkpoint:
    """
    Write the checkpoint of ``model`` at its agent steps into ``folder``: the model, the replay buffer, then the marker;
    then remove every other checkpoint of the folder and what killed writers left there.

    :raises OSError: a failed write (a full disk, no permission); the files of the new checkpoint are then removed, and
        the older checkpoint is still there, complete
    """
    model_path, buffer_path, marker_path = checkpoint_files(folder, model.num_timesteps)
    try:
        with atomic_file(model_path) as file:
            model.save(file)
        with atomic_file(buffer_path) as file:
            model.save_replay_buffer(file)
        sizes = {"model_bytes": model_path.stat().st_size, "replay_buffer_bytes": buffer_path.stat().st_size}
        write_atomic(marker_path, json.dumps({"timesteps": model.num_timesteps, **sizes}) + "\n")
    except BaseException:
        for path in (marker_path, model_path, buffer_path):
            path.unlink(missing_ok=True)
        raise
    kept = {model_path, buffer_path, marker_path}
    # Markers first: a kill while removing leaves no marker naming a half-removed checkpoint
    for path in sorted(set(folder.glob(f"{CHECKPOINT_PREFIX}_*")) - kept, key=lambda path: path.suffix != ".json"):
        path.unlink(missing_ok=True)
    remove_partial_files(folder)
    return Checkpoint(model_path, buffer_path, model.num_timesteps)


def _steps_in_names(folder: Path, suffix: str) -> list[int]:
    """The agent steps in the names of the ``dsslac_<N>_steps.<suffix>`` files of ``folder``."""
    names = (path.stem.removeprefix(f"{CHECKPOINT_PREFIX}_").removesuffix("_steps") for path in folder.glob(f"*.{suffix}"))
    return [int(steps) for steps in names if steps.isdigit()]


def _is_complete(folder: Path, timesteps: int) -> bool:
    """Whether the checkpoint's marker is there and its files have the sizes it names."""
    model_path, buffer_path, marker_path = checkpoint_files(folder, timesteps)
    try:
        sizes = json.loads(marker_path.read_text())
        return model_path.stat().st_size == sizes["model_bytes"] and buffer_path.stat().st_size == sizes["replay_buffer_bytes"]
    except (OSError, ValueError, KeyError, TypeError):
        return False


def complete_checkpoints(run_dir: str | Path) -> list[Checkpoint]:
    """
    The complete checkpoints of ``run_dir``, newest first: those whose marker is there and names the sizes of their
    files. In a run folder written before markers (none in it), every checkpoint with both files.
    """
    folder = Path(run_dir) / CHECKPOINT_DIR
    marked = _steps_in_names(folder, "json")
    if marked:
        steps = [timesteps for timesteps in marked if _is_complete(folder, timesteps)]
    else:
        steps = [timesteps for timesteps in _steps_in_names(folder, "zip") if checkpoint_files(folder, timesteps)[1].is_file()]
    return [Checkpoint(*checkpoint_files(folder, timesteps)[:2], timesteps) for timesteps in sorted(steps, reverse=True)]


def find_checkpoint(run_dir: str | Path) -> Checkpoint | None:
    """The newest complete checkpoint of ``run_dir`` (``complete_checkpoints``), or None."""
    return next(iter(complete_checkpoints(run_dir)), None)


def load_newest_checkpoint(run_dir: Path, env: GymEnv, device: str) -> DSSLAC:
    """
    The model of the newest complete checkpoint of ``run_dir`` that loads, with its replay buffer. One that does not
    (damaged, or written by another version) is named in one warning line on stderr, and the next older one is tried.

    :param run_dir: the run folder
    :param env: the training env of the resumed run
    :param device: the model's device
    :raises FileNotFoundError: no complete checkpoint, or none that loads, saying what to do
    """
    folder = run_dir / CHECKPOINT_DIR
    checkpoints = complete_checkpoints(run_dir)
    if not checkpoints:
        raise FileNotFoundError(
            f"No checkpoint (model and replay buffer) in {folder} to resume from: the run stopped before its first "
            "checkpoint; delete the folder and start it again with `train`"
        )
    for checkpoint in checkpoints:
        try:
            model = DSSLAC.load(checkpoint.model, env=env, device=device)
            model.load_replay_buffer(checkpoint.replay_buffer)
            return model
        except Exception as error:  # a damaged file fails in pickle, zipfile, torch or SB3, each with its own error
            reason = " ".join(str(error).split())[:200] or "no message"
            print(
                f"warning: the checkpoint at {checkpoint.timesteps} agent steps ({checkpoint.model.name}) does not load "
                f"({type(error).__name__}: {reason}); trying the next older one",
                file=sys.stderr,
            )
    raise FileNotFoundError(
        f"None of the {len(checkpoints)} checkpoints in {folder} loads (see the warnings): resume with the sb3_dsslac "
        f"version that wrote them (config.yaml names it), or delete the folder and start the run again with `train`"
    )


class LatestCheckpointCallback(BaseCallback):
    """
    A checkpoint of the model and its replay buffer every ``save_freq`` calls (``save_checkpoint``), the older one
    removed once the new one is complete.

    :param save_freq: calls (``env.step`` calls) between checkpoints
    :param folder: the run's checkpoint folder
    """

    def __init__(self, save_freq: int, folder: Path):
        super().__init__()
        self.save_freq = save_freq
        self.folder = folder

    def _init_callback(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            with measured(self.model, "checkpoints"):
                save_checkpoint(self.model, self.folder)  # type: ignore[arg-type]
        return True
