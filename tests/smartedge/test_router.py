"""``smartedge router``: the site's Zenoh router from the smartedge package
(smartedge/commands/router.py).

Run as the deployment runs it (a subprocess of ``python -m smartedge router``): two client-mode
sessions that only know the router's endpoint exchange a message through it, SIGTERM stops it
with exit 0, and a missing or garbage config exits 78 (EX_CONFIG) with the file named."""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from core.runtime import EXIT_CONFIG
from lab.launcher import ServiceProcess, start_service
from smartedge.commands.router import one_line
from tests.conftest import REPO_ROOT, free_port, wait_until

zenoh = pytest.importorskip("zenoh")

ROUTER_CONFIG = REPO_ROOT / "deploy" / "zenoh" / "router.json5"


def _router_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "smartedge", "router", *args]


def _client(endpoint: str):
    """A client-mode session that connects only to ``endpoint`` (multicast scouting off)."""
    doc = {
        "mode": "client",
        "connect": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
    }
    return zenoh.open(zenoh.Config.from_json5(json.dumps(doc)))


@pytest.fixture
def router(tmp_path: Path) -> Iterator[tuple[ServiceProcess, str]]:
    """``smartedge router`` on the shipped router config, listening on a free loopback port
    (``--listen`` overrides the config's ``tcp/0.0.0.0:7447``), started and logging."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = start_service(["router", "--config", str(ROUTER_CONFIG), "--listen", endpoint,
                          "--status-period", "0.5"], tmp_path / "router.log", cwd=REPO_ROOT)
    try:
        yield proc, endpoint
    finally:
        if proc.running():
            proc.kill()


@contextlib.contextmanager
def _socket_listening() -> Iterator[str]:
    """A TCP socket listening on a free loopback port; yields its zenoh endpoint."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        yield f"tcp/127.0.0.1:{sock.getsockname()[1]}"


def _wait_listening(endpoint: str, proc: ServiceProcess) -> None:
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    proc.wait_listening(int(port), timeout_s=30.0, host=host)


def test_router_carries_traffic_between_two_clients_and_stops_on_sigterm(router) -> None:
    proc, endpoint = router
    _wait_listening(endpoint, proc)
    got: list[bytes] = []
    with _client(endpoint) as subscriber_session, _client(endpoint) as publisher_session:
        subscriber_session.declare_subscriber(
            "routertest/**", lambda sample: got.append(sample.payload.to_bytes())
        )
        publisher = publisher_session.declare_publisher("routertest/hello")
        # a client reaches another client only through the router: retry until the subscriber's
        # declaration has propagated
        assert wait_until(lambda: (publisher.put(b"through the router"), bool(got))[1],
                          timeout_s=10.0, step_s=0.1)  # fmt: skip
        assert got[0] == b"through the router"
        time.sleep(1.0)  # the router's status line (every 0.5 s) sees both clients
        proc.popen.send_signal(signal.SIGTERM)
        code = proc.popen.wait(timeout=20)
    stderr = proc.log_path.read_text()
    assert code == 0, stderr
    assert "Traceback" not in stderr
    assert f"listening on {endpoint}" in stderr and "zenoh router " in stderr
    assert "2 clients" in stderr
    assert "stopping" in stderr


def test_sigint_stops_the_router_cleanly_too(router) -> None:
    proc, endpoint = router
    _wait_listening(endpoint, proc)
    proc.popen.send_signal(signal.SIGINT)
    assert proc.popen.wait(timeout=20) == 0, proc.log_tail()


@pytest.mark.parametrize("content", [None, "this is { not json5", '{mode: "router", bogus: 1}'])
def test_missing_or_bad_config_exits_with_the_config_status(
    content: str | None, tmp_path: Path
) -> None:
    path = tmp_path / "zenoh-router.json5"
    if content is not None:
        path.write_text(content)
    proc = subprocess.run(_router_argv("--config", str(path)), cwd=REPO_ROOT,
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == EXIT_CONFIG == 78
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr  # one line, no traceback, no ascii art
    assert lines[0].startswith(f"smartedge router: {path}: ")


def test_an_endpoint_that_cannot_be_opened_is_reported_without_traceback() -> None:
    """A valid config whose listen endpoint is taken: exit 1 (systemd retries), one line naming
    the config."""
    with _socket_listening() as endpoint:
        proc = subprocess.run(
            _router_argv("--config", str(ROUTER_CONFIG), "--listen", endpoint),
            cwd=REPO_ROOT, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    assert f"cannot open the router with {ROUTER_CONFIG}" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_usage_errors_exit_2() -> None:
    assert subprocess.run(_router_argv(), cwd=REPO_ROOT, capture_output=True,
                          timeout=60).returncode == 2  # fmt: skip
    proc = subprocess.run(_router_argv("--config", str(ROUTER_CONFIG), "--status-period", "-1"),
                          cwd=REPO_ROOT, capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 2 and "--status-period" in proc.stderr


def test_one_line_keeps_the_reason_and_position_of_a_json5_error() -> None:
    raw = (
        " --> 3:9\n  |\n3 | }, x: [1 2]}\n  |         ^---\n  |\n"
        "  = expected boolean, null, or string at /root/.cargo/x/zenoh-config/src/lib.rs:1486."
    )
    assert one_line(raw) == "line 3, column 9: expected boolean, null, or string"
    assert one_line("No such file or directory (os error 2) at /a/lib.rs:1507.") == (
        "No such file or directory (os error 2)"
    )
