"""The one service launcher: smartedge services as OS processes on this machine.

What the demo, the benchmarks, the fault harness, the scripts and the tests all need, in one
place: start a ``smartedge`` command as a process with its output in a log file
(:func:`start_service` → :class:`ServiceProcess`), wait until it listens on a port
(:meth:`ServiceProcess.wait_listening`, :func:`wait_listening`), stop it the way a service
manager does (SIGTERM, then SIGKILL after a timeout: :meth:`ServiceProcess.stop`,
:func:`stop_services`, and for any process :func:`stop_process`, :func:`stop_processes`), a free
loopback TCP port (:func:`free_port`) and the resident memory of a process (:func:`rss_mib`,
:class:`RssSampler`). Errors name the service and its log file.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Final

from protocol.errors import SmartedgeError

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


class LaunchError(SmartedgeError, RuntimeError):
    """A service did not start, exited early or never listened; the message names its log."""


def _listening(port: int, host: str = "127.0.0.1") -> bool:
    with socket.socket() as sock:
        return sock.connect_ex((host, port)) == 0


@dataclasses.dataclass
class ServiceProcess:
    """One ``smartedge`` command running as an OS process; stdout and stderr go to
    ``log_path`` (one file, in order)."""

    name: str
    argv: tuple[str, ...]
    log_path: Path
    popen: subprocess.Popen[bytes]

    @property
    def pid(self) -> int:
        return int(self.popen.pid)

    @property
    def returncode(self) -> int | None:
        return self.popen.poll()

    def running(self) -> bool:
        return self.popen.poll() is None

    def log_tail(self, max_chars: int = 3000) -> str:
        """The end of the log (what to show when the service misbehaved)."""
        try:
            return self.log_path.read_text(errors="replace")[-max_chars:]
        except OSError as exc:
            return f"(log {self.log_path} unreadable: {exc})"

    def wait_listening(self, port: int, timeout_s: float = 30.0, host: str = "127.0.0.1"
                       ) -> None:
        """Return once something accepts TCP connections on ``host:port``; :class:`LaunchError`
        (naming the log) when the process exits first or ``timeout_s`` passes."""
        wait_listening(port, timeout_s=timeout_s, host=host, process=self)

    def stop(self, timeout_s: float = 20.0) -> int:
        """SIGTERM, SIGKILL after ``timeout_s``; the exit code (:data:`KILLED_EXIT_CODE` when
        killed)."""
        return stop_process(self.popen, timeout_s)

    def kill(self) -> int:
        """SIGKILL (a crash, for fault tests); the exit code."""
        self.popen.kill()
        return int(self.popen.wait(timeout=10))


def start_service(argv: Sequence[str], log_path: Path, *, name: str | None = None,
                  log_level: str | None = None, cwd: Path | None = None,
                  env: Mapping[str, str] | None = None) -> ServiceProcess:
    """Start ``python -m smartedge [--log-level LEVEL] ARGV`` (this interpreter) with its output
    in ``log_path`` (made, with its folder) and ``PYTHONUNBUFFERED=1`` so the log is current.
    ``name`` (default: the subcommand) names it in errors; ``env`` adds to this environment."""
    log_path = Path(log_path)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "smartedge",
           *(("--log-level", log_level) if log_level else ()), *argv]
    with log_path.open("wb") as log:
        popen = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=cwd,
                                 env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
    return ServiceProcess(name or (argv[0] if argv else "smartedge"), tuple(argv), log_path,
                          popen)


def wait_listening(port: int, *, timeout_s: float = 30.0, host: str = "127.0.0.1",
                   process: ServiceProcess | None = None, step_s: float = 0.05) -> None:
    """Wait until ``host:port`` accepts TCP connections; :class:`LaunchError` after
    ``timeout_s``, or as soon as ``process`` (the one that should listen) exits."""
    deadline = time.monotonic() + timeout_s
    while True:
        if process is not None and not process.running():
            raise LaunchError(f"{process.name} exited with {process.returncode} before "
                              f"listening on {host}:{port}; see {process.log_path}:\n"
                              f"{process.log_tail()}")
        if _listening(port, host):
            return
        if time.monotonic() >= deadline:
            where = f"; see {process.log_path}" if process is not None else ""
            raise LaunchError(f"nothing listened on {host}:{port} within {timeout_s:g} s"
                              f"{where}")
        time.sleep(step_s)


def stop_services(services: Sequence[ServiceProcess], timeout_s: float = 20.0
                  ) -> dict[str, int]:
    """Stop every service (SIGTERM to all in the given order, then wait, SIGKILL after
    ``timeout_s``); exit codes by name."""
    codes = stop_processes([s.popen for s in services], timeout_s)
    return {s.name: code for s, code in zip(services, codes, strict=True)}


__all__ = [
    "KILLED_EXIT_CODE",
    "LaunchError",
    "RssSampler",
    "ServiceProcess",
    "free_port",
    "rss_mib",
    "start_service",
    "stop_process",
    "stop_processes",
    "stop_services",
    "wait_listening",
]
