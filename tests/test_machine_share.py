"""The machine lock of the parallel test run (tests/machine_share.py): shared holders run side
by side, an exclusive holder runs alone and is not starved by shared ones queueing behind it."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT
from tests.machine_share import MachineLock

HOLD = """
import sys, time
from pathlib import Path
sys.path.insert(0, {root!r})
from tests.machine_share import MachineLock
with MachineLock(Path({folder!r})).hold(exclusive={exclusive}):
    print("held", flush=True)
    time.sleep({seconds})
"""


def _holder(folder: Path, exclusive: bool, seconds: float) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLD.format(
        root=str(REPO_ROOT), folder=str(folder), exclusive=exclusive, seconds=seconds)],
        stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def test_shared_holders_do_not_wait_for_each_other(tmp_path: Path) -> None:
    other = _holder(tmp_path, exclusive=False, seconds=2.0)
    t0 = time.monotonic()
    with MachineLock(tmp_path).hold(exclusive=False):
        assert time.monotonic() - t0 < 1.0
    other.wait(10)


def test_an_exclusive_holder_waits_for_the_shared_one_and_then_runs_alone(tmp_path: Path
                                                                         ) -> None:
    shared = _holder(tmp_path, exclusive=False, seconds=1.0)
    t0 = time.monotonic()
    with MachineLock(tmp_path).hold(exclusive=True):
        waited = time.monotonic() - t0
        assert shared.poll() is not None or waited >= 0.8  # it ran only once the other ended
        # a shared holder arriving now queues until the exclusive one is done
        late = subprocess.Popen([sys.executable, "-c", HOLD.format(
            root=str(REPO_ROOT), folder=str(tmp_path), exclusive=False, seconds=0.0)],
            stdout=subprocess.PIPE, text=True)
        time.sleep(1.0)
        assert late.poll() is None  # still waiting at the turnstile
    assert late.stdout is not None and late.stdout.readline().strip() == "held"
    late.wait(10)
    shared.wait(10)
    assert waited >= 0.8


def test_a_parallel_worker_shares_the_runs_lock_folder(request) -> None:
    """Under pytest-xdist the controller made the folder before the workers started."""
    from tests.machine_share import worker_lock

    if not hasattr(request.config, "workerinput"):
        pytest.skip("a serial run: there is no lock to share (run with -n 2 to check it)")
    lock = worker_lock()
    assert lock is not None and lock.folder.is_dir()
