"""The machine shared between parallel test workers, and the tests that need it to themselves.

The suite runs in parallel (pytest-xdist). A few end-to-end tests run many services in real
time and measure what comes out (the demo as separate processes: ten services, four of them
rendering and running the CNN): with another worker's tests beside them on a 2-core machine
their detections arrive late and their accuracy figures move. Those tests carry the
``exclusive`` marker and take the machine for themselves: a readers-writer lock over the
workers, every other test holds it shared for its setup, call and teardown.

Two ``flock`` files in a folder the controller makes for the run: ``turnstile`` and ``machine``.
A shared holder passes the turnstile and takes ``machine`` shared; an exclusive one holds the
turnstile while it waits for ``machine`` exclusively and while it runs, so the other workers'
next tests queue at the turnstile instead of starving it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Final

#: the environment variable that hands the lock folder from the controller to the workers
LOCK_DIR_ENV: Final = "SMARTEDGE_TEST_MACHINE_LOCK"


def make_lock_dir() -> Path:
    """A fresh folder for the run's lock files, announced to the workers to be started."""
    path = Path(tempfile.mkdtemp(prefix="smartedge-tests-"))
    os.environ[LOCK_DIR_ENV] = str(path)
    return path


class MachineLock:
    """The readers-writer lock of the module docstring, over the files in ``folder``."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder

    def _open(self, name: str) -> int:
        return os.open(self.folder / name, os.O_RDWR | os.O_CREAT, 0o600)

    @contextlib.contextmanager
    def hold(self, exclusive: bool) -> Iterator[None]:
        turnstile, machine = self._open("turnstile"), self._open("machine")
        try:
            fcntl.flock(turnstile, fcntl.LOCK_EX)
            if exclusive:
                fcntl.flock(machine, fcntl.LOCK_EX)
            else:
                fcntl.flock(machine, fcntl.LOCK_SH)
                fcntl.flock(turnstile, fcntl.LOCK_UN)
            yield
        finally:
            os.close(machine)  # closing releases the locks
            os.close(turnstile)


def worker_lock() -> MachineLock | None:
    """The run's lock in a parallel worker; ``None`` in a serial run (nothing to share)."""
    folder = os.environ.get(LOCK_DIR_ENV)
    return MachineLock(Path(folder)) if folder else None
