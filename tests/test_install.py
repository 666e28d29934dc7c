"""The installed package as a new user gets it: every entry point of every extra starts, and no requirement is broken."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}


def run_python(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=REPO, env=ENV, capture_output=True, text=True)


@pytest.mark.parametrize(
    "command",
    [
        ["sb3_dsslac", "train"],
        ["sb3_dsslac", "evaluate"],
        ["sb3_dsslac", "tune"],
        ["sb3_dsslac", "plot"],
        ["sb3_dsslac", "beliefs"],
        ["sb3_dsslac.zoo", "train"],
        ["sb3_dsslac.zoo", "enjoy"],
    ],
    ids=" ".join,
)
def test_entry_points_start(command: list[str]) -> None:
    """Each command imports what it needs from the environment and prints its help (the zoo's through rl-zoo3's)."""
    result = run_python("-m", *command, "--help")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "usage:" in result.stdout


def test_zoo_train_does_not_load_the_hub_code() -> None:
    code = (
        "import sys\nfrom sb3_dsslac.app.zoo import main\n"
        "try:\n    main(['train', '--help'])\nexcept SystemExit:\n    pass\n"
        "print(sorted(name for name in ('rl_zoo3.enjoy', 'rl_zoo3.load_from_hub') if name in sys.modules))"
    )
    result = run_python("-c", code)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().splitlines()[-1] == "[]"


def test_no_broken_requirements() -> None:
    result = run_python("-m", "pip", "check")
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.skipif("DSSLAC_VENV" not in os.environ, reason="only `make test` says which environment the tests must run in")
def test_make_test_runs_in_the_project_environment() -> None:
    assert sys.prefix != sys.base_prefix, f"{sys.prefix} is the machine's own Python, not a virtual environment"
    assert Path(sys.prefix).resolve() == Path(os.environ["DSSLAC_VENV"]).resolve()
