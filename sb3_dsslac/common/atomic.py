"""
Files written whole or not at all: each is written under a temporary name in its own folder, flushed and fsync'd, then
renamed over the file (``os.replace``), so that a reader, or a run resumed after a crash, sees the old whole file or the
new whole file, never part of one.
"""

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

# The ending of the temporary files; a crash leaves them behind, and ``remove_partial_files`` removes them
PARTIAL_SUFFIX = ".partial"


def _partial_path(path: Path) -> Path:
    """The hidden temporary file that ``path`` is written to by this process before it is renamed to ``path``."""
    return path.with_name(f".{path.name}.{os.getpid()}{PARTIAL_SUFFIX}")


@contextlib.contextmanager
def atomic_file(path: str | Path) -> Iterator[BinaryIO]:
    """
    A binary file to write ``path`` through: it becomes ``path`` (replacing any older one) only when the block ends
    without an error; an error leaves ``path`` as it was and removes the temporary file.

    :param path: the file to write
    :raises OSError: a failed write (a full disk, no permission), naming ``path`` rather than the temporary file
    """
    path = Path(path)
    partial = _partial_path(path)
    try:
        with open(partial, "wb") as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        os.replace(partial, path)
    except BaseException as error:
        partial.unlink(missing_ok=True)
        if isinstance(error, OSError) and error.errno is not None:
            raise OSError(error.errno, error.strerror, str(path)) from error
        raise
    _fsync_folder(path.parent)


def write_atomic(path: str | Path, data: str | bytes) -> None:
    """Write ``data`` (text as UTF-8) to ``path`` whole or not at all (``atomic_file``)."""
    with atomic_file(path) as file:
        file.write(data.encode() if isinstance(data, str) else data)


def remove_partial_files(folder: str | Path) -> None:
    """Remove the temporary files that writers killed in ``atomic_file`` left in ``folder``."""
    for path in Path(folder).glob(f".*{PARTIAL_SUFFIX}"):
        path.unlink(missing_ok=True)


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable: without it, a power cut may lose the rename though the data was synced."""
    descriptor = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)
