"""The shared process helpers: free loopback port, resident memory, stopping processes."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

import pytest

from lab.processes import (
    KILLED_EXIT_CODE,
    RssSampler,
    free_port,
    rss_mib,
    stop_process,
    stop_processes,
)

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
