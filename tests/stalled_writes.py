"""
Writes of ``sb3_dsslac.common.atomic`` made to stall or fail on purpose, to test what a kill or a full disk does to a
run: the N-th file (from 1) whose name matches a glob is opened through a writer that stops after its first chunk (so
that a SIGKILL lands while the file is being written) or that fails as a full disk or an unwritable folder does.

As a script (``python -m tests.stalled_writes``), it runs command lines, each in a child forked from it once it has
imported everything (so a run starts in milliseconds, not seconds), each child a process that a test can SIGKILL.
"""

import builtins
import errno
import fnmatch
import io
import json
import os
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sb3_dsslac.common import atomic


def final_name(partial: str | Path) -> str:
    """The name of the file that ``atomic_file`` writes through the temporary file ``partial`` (``.NAME.PID.partial``)."""
    return Path(partial).name.removeprefix(".").removesuffix(atomic.PARTIAL_SUFFIX).rsplit(".", 1)[0]


class _StallingWriter(io.BufferedWriter):
    """Puts its first chunk on disk, touches ``signal`` and waits to be killed."""

    signal: Path

    def write(self, data: Any) -> int:
        written = super().write(data)
        self.flush()
        self.signal.touch()
        time.sleep(600)
        return written


class _FullDiskWriter(io.BufferedWriter):
    """Fails at its first write as a full disk does."""

    def write(self, data: Any) -> int:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _open_nth(pattern: str, occurrence: int, open_it: Callable[[str], Any]) -> Callable[..., Any]:
    """``open`` for ``common.atomic``: the ``occurrence``-th file matching ``pattern`` through ``open_it``."""
    seen = 0

    def opener(file: str, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        nonlocal seen
        if fnmatch.fnmatch(final_name(file), pattern):
            seen += 1
            if seen == occurrence:
                return open_it(file)
        return builtins.open(file, mode, *args, **kwargs)

    return opener


def stalling_open(pattern: str, occurrence: int, signal: Path) -> Callable[..., Any]:
    """``open`` for ``common.atomic`` that stalls in the ``occurrence``-th file matching ``pattern``, touching ``signal``."""

    def open_stalling(file: str) -> _StallingWriter:
        writer = _StallingWriter(io.FileIO(file, "w"))
        writer.signal = signal
        return writer

    return _open_nth(pattern, occurrence, open_stalling)


def failing_open(pattern: str, occurrence: int, code: int) -> Callable[..., Any]:
    """
    ``open`` for ``common.atomic`` that fails on the ``occurrence``-th file matching ``pattern`` with ``code``: a full
    disk (ENOSPC) at its first write, an unwritable folder (EACCES) when it is made.
    """

    def open_failing(file: str) -> _FullDiskWriter:
        if code != errno.ENOSPC:
            raise OSError(code, os.strerror(code), file)
        return _FullDiskWriter(io.FileIO(file, "w"))

    return _open_nth(pattern, occurrence, open_failing)


def serve() -> None:
    """
    Run command lines, one per line of stdin, each in a forked child: a line is the JSON list ``[LOG, GLOB, N, SIGNAL,
    *argv]``; the child writes its output to LOG and, unless GLOB is empty, stalls in the N-th write of a file matching
    GLOB after touching SIGNAL. The reply is two lines: the child's pid, and when it ends, its exit status (minus the
    signal number when killed).
    """
    from sb3_dsslac.app.cli import main

    for line in sys.stdin:
        log, glob, occurrence, signal_file, *argv = json.loads(line)
        pid = os.fork()
        if pid == 0:
            status = 1
            try:
                output = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
                os.dup2(output, 1)
                os.dup2(output, 2)
                if glob:
                    atomic.open = stalling_open(glob, occurrence, Path(signal_file))  # type: ignore[attr-defined]
                status = main(argv)
            except BaseException:
                traceback.print_exc()
            finally:
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(status)
        print(pid, flush=True)
        print(os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]), flush=True)


if __name__ == "__main__":
    serve()
