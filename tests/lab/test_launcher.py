"""The one service launcher: a smartedge service as a process with its log, waited for until it
listens, stopped; free loopback port, resident memory, stopping processes."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lab.launcher import (
    KILLED_EXIT_CODE,
    LaunchError,
    RssSampler,
    free_port,
    rss_mib,
    start_service,
    stop_process,
    stop_processes,
    stop_services,
    wait_listening,
)
from tests.conftest import REPO_ROOT

#: a child that exits 0 on SIGTERM, and one that ignores it
POLITE = ("import signal, sys, time\n"
          "signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))\n"
          "print('ready', flush=True)\n"
          "time.sleep(60)\n")
STUBBORN = ("import signal, time\n"
            "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
            "print('ready', flush=True)\n"
            "time.sleep(60)\n")


def _start(code: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    return proc


def test_free_port_can_be_bound() -> None:
    port = free_port()
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", port))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_rss_of_this_process_and_of_a_child() -> None:
    assert 1.0 < rss_mib() < 100_000.0
    proc = _start(POLITE)
    try:
        assert rss_mib(proc.pid) > 1.0
        with RssSampler(proc.pid, period_s=0.01) as sampler:
            time.sleep(0.1)
        assert sampler.peak_mib > 1.0
    finally:
        stop_process(proc, timeout_s=10.0)


def test_stop_sigterm_first_then_sigkill() -> None:
    polite, stubborn = _start(POLITE), _start(STUBBORN)
    t0 = time.monotonic()
    assert stop_processes([polite, stubborn], timeout_s=1.0) == [0, KILLED_EXIT_CODE]
    assert time.monotonic() - t0 < 10.0
    assert KILLED_EXIT_CODE == -signal.SIGKILL
    assert stop_process(polite) == 0  # already gone: its exit code, no signal


def test_a_service_starts_with_its_log_listens_and_stops_cleanly(tmp_path: Path) -> None:
    """``smartedge router`` through the launcher: its output in the log file, listening on its
    port, SIGTERM gives exit 0."""
    port = free_port()
    log = tmp_path / "logs" / "router.log"
    router = start_service(["router", "--config", str(REPO_ROOT / "deploy/zenoh/router.json5"),
                            "--listen", f"tcp/127.0.0.1:{port}"], log, cwd=REPO_ROOT)
    try:
        router.wait_listening(port, timeout_s=30.0)
        assert router.running() and router.name == "router"
    finally:
        codes = stop_services([router], timeout_s=20.0)
    assert codes == {"router": 0}, router.log_tail()
    assert f"listening on tcp/127.0.0.1:{port}" in log.read_text()


def test_a_service_that_exits_before_listening_is_named_with_its_log(tmp_path: Path) -> None:
    bad = start_service(["router", "--config", str(tmp_path / "missing.json5")],
                        tmp_path / "bad.log", name="the-router")
    with pytest.raises(LaunchError, match=r"the-router exited with 78 .*bad\.log") as exc:
        bad.wait_listening(free_port(), timeout_s=30.0)
    assert "missing.json5" in str(exc.value)  # the log's tail comes with the error
    assert bad.returncode == 78


def test_waiting_for_a_port_nobody_opens_times_out() -> None:
    t0 = time.monotonic()
    with pytest.raises(LaunchError, match="nothing listened"):
        wait_listening(free_port(), timeout_s=0.3)
    assert time.monotonic() - t0 < 5.0
