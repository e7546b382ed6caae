"""Shared fixtures: repository paths, the example site, loopback Zenoh sessions."""

from __future__ import annotations

import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_SITE = REPO_ROOT / "deploy" / "site.example.yaml"


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def stop_process(proc: subprocess.Popen, timeout_s: float = 30.0) -> int:
    """SIGTERM, then SIGKILL after ``timeout_s``; the exit code."""
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


def wait_until(predicate: Callable[[], bool], timeout_s: float = 5.0, step_s: float = 0.02) -> bool:
    """Poll ``predicate`` until it is true or ``timeout_s`` passes; returns its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step_s)
    return bool(predicate())


@pytest.fixture
def example_site_path() -> Path:
    return EXAMPLE_SITE


@pytest.fixture
def example_site():
    from protocol.site import load_site

    return load_site(EXAMPLE_SITE)


@pytest.fixture
def zenoh_pair() -> Iterator[tuple[object, object, str]]:
    """Two real Zenoh peer sessions on loopback (scouting off): (listener, connector, endpoint)."""
    zenoh = pytest.importorskip("zenoh")
    from protocol.session import loopback_config

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    a = zenoh.open(loopback_config(listen=[endpoint]))
    b = zenoh.open(loopback_config(connect=[endpoint]))
    try:
        yield a, b, endpoint
    finally:
        b.close()
        a.close()


# the tiny trained detector + keypoint models (session-scoped), for tests outside edge_agent/
from tests.edge_agent.conftest import tiny_models  # noqa: E402, F401
