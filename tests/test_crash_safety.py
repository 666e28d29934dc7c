"""
Nothing lost on a crash: every file of a run folder is written whole or not at all, a run killed with SIGKILL while it
writes any of them (or at a random moment) resumes from its newest complete checkpoint, a checkpoint that does not
load is skipped with a warning, and a full disk stops a run with one error line and its checkpoint intact.
"""

import errno
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

import numpy as np
import pandas as pd
import pytest
import yaml

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.checkpoints import CHECKPOINT_DIR, checkpoint_files, complete_checkpoints, find_checkpoint
from sb3_dsslac.app.cli import main
from sb3_dsslac.common import atomic
from sb3_dsslac.common.atomic import PARTIAL_SUFFIX, atomic_file, write_atomic
from tests.stalled_writes import failing_open, final_name
from tests.test_cli import TINY_ENV, TINY_FLAGS

REPO = Path(__file__).resolve().parents[1]
# A pixel run of the tiny env: evaluations at 40, 80, 120 agent steps, a checkpoint every 20 (action repeat 1)
SIM_STEPS = 120
RUN_FLAGS = ["--sim-steps=120", "--eval-every=40", "--checkpoint-every=20", "--eval-episodes=1", "--obs-type=pixels"]
QUIET = ["--quiet", "--no-progress-bar"]


def train_argv(run_dir: Path, *flags: str) -> list[str]:
    return ["train", "--env", TINY_ENV, "--out", str(run_dir), *QUIET, *RUN_FLAGS, *flags, *TINY_FLAGS]


def resume_argv(run_dir: Path) -> list[str]:
    return ["train", "--resume", str(run_dir), *QUIET]


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


class Runner:
    """Command lines run in children forked from one ``python -m tests.stalled_writes`` (``serve``), each killable."""

    def __init__(self) -> None:
        environment = {**os.environ, "PYTHONPATH": str(REPO), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
        self.server = subprocess.Popen(
            [sys.executable, "-m", "tests.stalled_writes"],
            cwd=REPO,
            env=environment,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self.requests: IO[str] = self.server.stdin  # type: ignore[assignment]
        self.replies: IO[str] = self.server.stdout  # type: ignore[assignment]

    def kill_when(
        self,
        argv: list[str],
        log: Path,
        ready: Callable[[], bool],
        stall: tuple[str, int, Path] | None = None,
        may_finish: bool = False,
    ) -> None:
        """
        Run ``argv`` (stalled in the N-th write of a file matching GLOB, touching SIGNAL: ``stall``) and SIGKILL it as
        soon as ``ready()``; fail, with its output, if it ends first (unless ``may_finish`` and it ended well) or runs
        2 minutes.
        """
        glob, occurrence, signal_file = stall or ("", 0, "")
        self.requests.write(json.dumps([str(log), glob, occurrence, str(signal_file), *argv]) + "\n")
        self.requests.flush()
        pid, deadline = int(self.replies.readline()), time.monotonic() + 120.0
        while not ready():
            if not alive(pid) or time.monotonic() > deadline:
                if alive(pid):
                    os.kill(pid, signal.SIGKILL)
                status = int(self.replies.readline())
                if may_finish and status == 0:
                    return
                raise AssertionError(f"the run ended (status {status}) before the kill:\n{log.read_text()[-3000:]}")
            time.sleep(0.005)
        os.kill(pid, signal.SIGKILL)
        assert int(self.replies.readline()) == -signal.SIGKILL

    def close(self) -> None:
        self.requests.close()
        self.server.wait(timeout=60)


@pytest.fixture(scope="module")
def runner() -> Iterator[Runner]:
    runner = Runner()
    yield runner
    runner.close()


def partial_files(run_dir: Path) -> list[str]:
    """The final names of the files whose writing a kill cut short."""
    return sorted(
        final_name(path) for folder in (run_dir, run_dir / CHECKPOINT_DIR) for path in folder.glob(f".*{PARTIAL_SUFFIX}")
    )


def assert_every_file_whole(run_dir: Path) -> None:
    """Every file of the run folder that a later command reads is there whole or not there at all."""
    if (run_dir / "config.yaml").exists():
        assert yaml.safe_load((run_dir / "config.yaml").read_text())["sim_steps"] == SIM_STEPS
    progress = run_dir / "progress.csv"
    if progress.exists() and progress.stat().st_size:
        lines = progress.read_text().splitlines(keepends=True)
        assert all(len(line.split(",")) == len(lines[0].split(",")) for line in lines), "a progress.csv row is cut short"
    if (run_dir / "evaluations.npz").exists():
        with np.load(run_dir / "evaluations.npz") as evaluations:
            assert len(evaluations["timesteps"]) == len(evaluations["results"]) == len(evaluations["costs"])
    for name in ("model.zip", "best_model.zip"):
        if (run_dir / name).exists():
            assert zipfile.ZipFile(run_dir / name).testzip() is None, name
    if (run_dir / "time_account.json").exists():
        assert "wall" in json.loads((run_dir / "time_account.json").read_text())
    for checkpoint in complete_checkpoints(run_dir):
        assert zipfile.ZipFile(checkpoint.model).testzip() is None


def rows_up_to(run_dir: Path, timesteps: int) -> pd.DataFrame:
    path = run_dir / "progress.csv"
    if not path.is_file() or not path.stat().st_size:  # killed before its first row (a checkpoint can come first)
        return pd.DataFrame()
    progress = pd.read_csv(path)
    return progress[progress["time/total_timesteps"] <= timesteps].reset_index(drop=True)


def evaluations_up_to(run_dir: Path, timesteps: int) -> dict[str, np.ndarray]:
    if not (run_dir / "evaluations.npz").exists():
        return {}
    with np.load(run_dir / "evaluations.npz") as evaluations:
        keep = evaluations["timesteps"] <= timesteps
        return {name: evaluations[name][keep] for name in ("timesteps", "results", "costs")}


def assert_kept(run_dir: Path, rows: pd.DataFrame, evaluations: dict[str, np.ndarray], timesteps: int) -> None:
    """The rows of progress.csv and the evaluations up to the checkpoint a run resumed from are as they were."""
    if len(rows):
        pd.testing.assert_frame_equal(rows_up_to(run_dir, timesteps)[rows.columns], rows, check_dtype=False)
    after = evaluations_up_to(run_dir, timesteps)
    for name, values in evaluations.items():
        np.testing.assert_array_equal(after[name], values, err_msg=name)


def assert_finished(run_dir: Path) -> None:
    """
    The run reached its steps on the evaluation grid, with one evaluation row per grid step and no row redone out of
    order, and its model predicts. (An evaluation and an episode's end at the same step log two rows, as in SB3.)
    """
    model = DSSLAC.load(run_dir / "model.zip")
    assert model.num_timesteps == SIM_STEPS
    action, _ = model.predict(model.observation_space.sample(), deterministic=True)
    assert model.action_space.contains(action)
    assert np.load(run_dir / "evaluations.npz")["timesteps"].tolist() == [40, 80, 120]
    progress = pd.read_csv(run_dir / "progress.csv").dropna(subset=["time/total_timesteps"])
    steps = progress["time/total_timesteps"].tolist()
    assert steps == sorted(steps) and steps[-1] == SIM_STEPS, steps
    assert progress.dropna(subset=["eval/mean_reward"])["time/total_timesteps"].tolist() == [40, 80, 120], steps
    assert find_checkpoint(run_dir).timesteps == SIM_STEPS  # type: ignore[union-attr]
    assert partial_files(run_dir) == []
    assert_every_file_whole(run_dir)


# The files a run writes, each stalled in turn while a run (train, or train --resume) writes it and killed there:
# (command, file, which write of it, the newest complete checkpoint after the kill)
KILL_STAGES = [
    ("train", "config.yaml", 1, None),  # nothing to resume, and `train` into the folder again works
    ("train", "dsslac_replay_buffer_*_steps.pkl", 2, 20),  # the buffer at 40
    ("resume", "best_model.zip", 1, 20),  # the evaluation at 40 is the resumed run's first, so its best
    ("resume", "progress.csv", 1, 20),  # the rewrite that keeps the rows up to the checkpoint
    ("resume", "evaluations.npz", 1, 20),  # the evaluation at 40
    ("resume", "dsslac_*_steps.zip", 1, 20),  # the model of the checkpoint at 40
    ("resume", "dsslac_*_steps.json", 1, 20),  # the marker at 40, its model and buffer whole
    ("resume", "progress.csv", 2, 60),  # the rewrite that adds the columns of the first updates, at 80
    ("resume", "model.zip", 1, 120),  # the final model
    ("resume", "time_account.json", 1, 120),
]


def test_a_run_killed_while_writing_each_file_resumes(runner: Runner, tmp_path: Path) -> None:
    run_dir = tmp_path / "run"
    resumed_from = None
    kept_rows, kept_evaluations = pd.DataFrame(), {}
    for stage, (command, pattern, occurrence, newest) in enumerate(KILL_STAGES):
        signal_file, log = tmp_path / f"stalled_{stage}", tmp_path / f"log_{stage}.txt"
        argv = train_argv(run_dir) if command == "train" else resume_argv(run_dir)
        runner.kill_when(argv, log, signal_file.exists, stall=(pattern, occurrence, signal_file))
        # The kill landed while the file was being written: its temporary file is there, the file itself whole or absent
        written = [name for name in partial_files(run_dir) if Path(name).match(pattern)]
        assert written, f"stage {stage}: no half-written {pattern}"
        assert_every_file_whole(run_dir)
        if resumed_from is not None:
            assert_kept(run_dir, kept_rows, kept_evaluations, resumed_from)
        checkpoint = find_checkpoint(run_dir)
        assert (checkpoint and checkpoint.timesteps) == newest, f"stage {stage}: killed in the write of {pattern}"
        if checkpoint is None:
            assert not (run_dir / "config.yaml").exists()
            assert main(resume_argv(run_dir)) == 2  # "not a run folder": the next `train` starts it again
            continue
        resumed_from = checkpoint.timesteps
        kept_rows, kept_evaluations = rows_up_to(run_dir, resumed_from), evaluations_up_to(run_dir, resumed_from)
    assert resumed_from == SIM_STEPS
    assert main(resume_argv(run_dir)) == 0
    assert_kept(run_dir, kept_rows, kept_evaluations, resumed_from)
    assert_finished(run_dir)


def after(wait: float, began: Callable[[], bool]) -> Callable[[], bool]:
    """Whether ``wait`` seconds went by since ``began()`` first held."""
    clock: list[float] = []

    def ready() -> bool:
        if not clock and began():
            clock.append(time.monotonic())
        return bool(clock) and time.monotonic() - clock[0] >= wait

    return ready


def replaced(path: Path) -> Callable[[], bool]:
    """Whether ``path`` was replaced (``os.replace``) since this call."""
    inode = path.stat().st_ino
    return lambda: path.stat().st_ino != inode


@pytest.mark.parametrize("at_once", [True, False])
def test_a_run_killed_at_random_moments_resumes(runner: Runner, tmp_path: Path, at_once: bool) -> None:
    """
    Killed a random while after its first complete checkpoint, then again a random while after its resume began to
    train (its progress.csv rewritten), then resumed to the end. At these sizes a checkpoint is written every 0.1 s or so.
    ``at_once``: both kills as soon as they may come, the first before any row of progress.csv is written.
    """
    run_dir = tmp_path / "run"
    waits = [0.0, 0.0] if at_once else [random.uniform(0.0, 1.5), random.uniform(0.0, 1.0)]
    kept_rows, kept_evaluations, resumed_from = pd.DataFrame(), {}, 0
    for stage in range(2):
        if stage == 0:
            argv, ready = train_argv(run_dir), after(waits[0], lambda: find_checkpoint(run_dir) is not None)
        else:
            argv, ready = resume_argv(run_dir), after(waits[1], replaced(run_dir / "progress.csv"))
        runner.kill_when(argv, tmp_path / f"log_{stage}.txt", ready, may_finish=True)
        assert_every_file_whole(run_dir)
        assert_kept(run_dir, kept_rows, kept_evaluations, resumed_from)
        checkpoint = find_checkpoint(run_dir)
        assert checkpoint is not None and checkpoint.timesteps >= resumed_from, f"waits {waits}"
        resumed_from = checkpoint.timesteps
        kept_rows, kept_evaluations = rows_up_to(run_dir, resumed_from), evaluations_up_to(run_dir, resumed_from)
    assert main(resume_argv(run_dir)) == 0
    assert_kept(run_dir, kept_rows, kept_evaluations, resumed_from)
    assert_finished(run_dir)


def test_atomic_file_replaces_whole_or_leaves_the_old_file(tmp_path: Path, monkeypatch) -> None:
    path = tmp_path / "evaluations.npz"
    write_atomic(path, "old")
    with pytest.raises(RuntimeError), atomic_file(path) as file:
        file.write(b"half")
        raise RuntimeError("killed mid-write")
    assert path.read_text() == "old" and list(tmp_path.iterdir()) == [path]
    monkeypatch.setattr(atomic, "open", failing_open("evaluations.npz", 1, errno.ENOSPC), raising=False)
    with pytest.raises(OSError) as raised:
        write_atomic(path, "new")
    # The error names the file, not its temporary name
    assert raised.value.errno == errno.ENOSPC and raised.value.filename == str(path)
    assert path.read_text() == "old" and list(tmp_path.iterdir()) == [path]
    write_atomic(path, b"new")
    assert path.read_bytes() == b"new"


@pytest.mark.parametrize(
    ("pattern", "occurrence", "code", "kept"),
    [
        ("dsslac_replay_buffer_*_steps.pkl", 3, errno.ENOSPC, 40),  # the buffer of the checkpoint at 60
        ("evaluations.npz", 2, errno.EACCES, 60),  # the evaluation at 80
    ],
)
def test_a_full_disk_stops_the_run_with_one_line(tmp_path, monkeypatch, capsys, pattern, occurrence, code, kept) -> None:
    run_dir = tmp_path / "run"
    monkeypatch.setattr(atomic, "open", failing_open(pattern, occurrence, code), raising=False)
    assert main(train_argv(run_dir)) == 1
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and error.startswith("error: cannot write "), error
    assert os.strerror(code) in error and f"checkpoint at {kept} agent steps is complete" in error, error
    assert f"train --resume {run_dir}" in error
    assert find_checkpoint(run_dir).timesteps == kept  # type: ignore[union-attr]
    assert sorted(path.name for path in (run_dir / CHECKPOINT_DIR).iterdir()) == sorted(
        path.name for path in checkpoint_files(run_dir / CHECKPOINT_DIR, kept)
    )
    assert partial_files(run_dir) == []
    monkeypatch.undo()
    assert main(resume_argv(run_dir)) == 0
    assert_finished(run_dir)


def test_resume_skips_a_checkpoint_that_does_not_load(tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "run"
    assert main(train_argv(run_dir, "--sim-steps=40")) == 0
    folder = run_dir / CHECKPOINT_DIR
    model, buffer, _ = checkpoint_files(folder, 40)
    newer_model, newer_buffer, newer_marker = checkpoint_files(folder, 60)
    # A newer checkpoint with its marker whose model is damaged (its size kept) is named and skipped
    newer_model.write_bytes(b"\0" * model.stat().st_size)
    shutil.copy(buffer, newer_buffer)
    sizes = {"model_bytes": model.stat().st_size, "replay_buffer_bytes": buffer.stat().st_size}
    newer_marker.write_text(json.dumps({"timesteps": 60, **sizes}))
    capsys.readouterr()
    assert main(resume_argv(run_dir)) == 0
    warnings = capsys.readouterr().err.strip().splitlines()
    assert len(warnings) == 1 and warnings[0].startswith("warning: the checkpoint at 60 agent steps (dsslac_60_steps.zip)")
    assert DSSLAC.load(run_dir / "model.zip").num_timesteps == 40
    # A run folder written before markers, killed while writing its newer buffer (the crash of issue 58)
    for marker in folder.glob("*.json"):
        marker.unlink()
    shutil.copy(model, newer_model)
    newer_buffer.write_bytes(buffer.read_bytes()[: buffer.stat().st_size // 2])
    assert [checkpoint.timesteps for checkpoint in complete_checkpoints(run_dir)] == [60, 40]
    assert main(resume_argv(run_dir)) == 0
    assert "UnpicklingError" in capsys.readouterr().err
    # With none that loads: one error line that says what to do
    buffer.write_bytes(b"\0" * buffer.stat().st_size)
    assert main(resume_argv(run_dir)) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert [line.split(":")[0] for line in lines] == ["warning", "warning", "error"]
    assert "None of the 2 checkpoints" in lines[-1] and "start the run again with `train`" in lines[-1]


def test_tune_writes_its_trials_whole(tmp_path: Path, monkeypatch) -> None:
    import optuna

    from sb3_dsslac.app.hpo import write_trials

    study = optuna.create_study(study_name="s")
    study.optimize(lambda trial: trial.suggest_float("x", 0.0, 1.0), n_trials=2)
    path = write_trials(study, tmp_path / "out")
    assert path == tmp_path / "out" / "s_trials.csv" and len(pd.read_csv(path)) == 2
    study.optimize(lambda trial: trial.suggest_float("x", 0.0, 1.0), n_trials=1)
    monkeypatch.setattr(atomic, "open", failing_open("s_trials.csv", 1, errno.ENOSPC), raising=False)
    with pytest.raises(OSError, match="No space left"):
        write_trials(study, tmp_path / "out")
    assert len(pd.read_csv(path)) == 2 and sorted(path.parent.iterdir()) == [path]
