"""Helpers for commands that start, watch and stop OS processes on this machine.

One place for what the demo, the benchmarks, the fault harness, the scripts and the tests all
need: a free loopback TCP port (:func:`free_port`), the resident memory of a process
(:func:`rss_mib`, :class:`RssSampler`) and stopping processes the way a service manager does
(:func:`stop_process`, :func:`stop_processes`: SIGTERM, then SIGKILL after a timeout).
"""

from __future__ import annotations

import logging
import signal
import socket
import subprocess
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Final

log = logging.getLogger(__name__)

#: the exit code :func:`stop_processes` reports for a process it had to SIGKILL
KILLED_EXIT_CODE: Final = -int(signal.SIGKILL)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (the OS picked it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def rss_mib(pid: int | None = None) -> float:
    """Resident set size in MiB of process ``pid`` (default: this process), from Linux
    ``/proc/<pid>/status``. Without ``/proc`` this process's *peak* RSS is returned instead
    (``getrusage``); for another process it raises :class:`OSError`. :class:`RuntimeError` when
    the status file has no ``VmRSS`` line (a zombie)."""
    try:
        text = Path(f"/proc/{'self' if pid is None else pid}/status").read_text()
    except OSError:
        if pid is not None:
            raise
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    for line in text.splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for process {'self' if pid is None else pid}")


class RssSampler:
    """Samples a process's RSS every ``period_s`` in a thread while in a ``with`` block;
    ``peak_mib`` is the largest seen (MiB). Stops quietly when the process goes away."""

    def __init__(self, pid: int, period_s: float = 0.05) -> None:
        self.pid = pid
        self.period_s = period_s
        self.peak_mib = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"rss-{pid}", daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            try:
                self.peak_mib = max(self.peak_mib, rss_mib(self.pid))
            except (OSError, RuntimeError):
                return

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join(2)


def stop_processes(procs: Sequence[subprocess.Popen], timeout_s: float = 20.0) -> list[int]:
    """SIGTERM to each process still running (in the given order), then wait for each up to
    ``timeout_s`` seconds and SIGKILL it if it is still there. Returns the exit codes in the
    same order (:data:`KILLED_EXIT_CODE` for a killed one)."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    codes: list[int] = []
    for proc in procs:
        try:
            codes.append(int(proc.wait(timeout=timeout_s)))
        except subprocess.TimeoutExpired:
            log.warning("process %d did not stop %.0f s after SIGTERM: killed", proc.pid,
                        timeout_s)
            proc.kill()
            proc.wait()
            codes.append(KILLED_EXIT_CODE)
    return codes


def stop_process(proc: subprocess.Popen, timeout_s: float = 30.0) -> int:
    """SIGTERM, then SIGKILL after ``timeout_s`` seconds; the exit code."""
    return stop_processes([proc], timeout_s)[0]


__all__ = [
    "KILLED_EXIT_CODE",
    "RssSampler",
    "free_port",
    "rss_mib",
    "stop_process",
    "stop_processes",
]
