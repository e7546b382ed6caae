"""``smartedge status`` and ``smartedge echo`` against a real edge agent over loopback Zenoh."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from lab.launcher import start_service
from protocol.messages import Detection, PoseEstimate, RobotDetections, ServiceStatus
from smartedge.commands.status import echo_main, format_table, status_main, status_rows, summarize
from tests.conftest import free_port, wait_until


@pytest.fixture(scope="module")
def agent(tmp_path_factory: pytest.TempPathFactory):
    """An edge agent (simulated camera, noise model) listening on a free loopback port."""
    port = free_port()
    log = tmp_path_factory.mktemp("agent") / "agent.log"
    proc = start_service(
        ["edge-agent", "--camera", "cam1", "--source", "sim", "--listen",
         f"tcp/127.0.0.1:{port}", "--connect", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"],
        log)
    # session open and the simulation running (its epoch is 2 s ahead): the agent's status and
    # a detection of cam1 seen by a session of ours (was a fixed 3 s)
    import zenoh

    from core.session import loopback_config
    from protocol import keys

    seen: set[str] = set()
    with zenoh.open(loopback_config(connect=[f"tcp/127.0.0.1:{port}"])) as session:
        session.declare_subscriber(keys.detections_key("paper_lab", "cam1"),
                                   lambda _s: seen.add("detections"))
        session.declare_subscriber(keys.status_key("paper_lab", "*", "*"),
                                   lambda _s: seen.add("status"))
        assert wait_until(lambda: seen == {"detections", "status"} or not proc.running(),
                          30.0, 0.05)
    assert proc.running(), proc.log_tail(2000)
    assert seen == {"detections", "status"}, (seen, Path(log).read_text()[-2000:])
    yield port
    assert proc.stop(timeout_s=20.0) == 0, proc.log_tail(2000)


def _session_args(port: int) -> list[str]:
    return ["--mode", "client", "--connect", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]


def test_status_once_shows_the_live_agent(agent: int) -> None:
    out = io.StringIO()
    assert status_main(["--once", "--wait", "3", *_session_args(agent)], out) == 0
    text = out.getvalue()
    assert "edge-agent/cam1" in text and "yes" in text, text
    row = next(ln for ln in text.splitlines() if ln.startswith("edge-agent/cam1"))
    assert " ok " in row or " starting " in row, row
    assert "detections" in row  # its message rate


def test_status_once_without_anybody_exits_1() -> None:
    port = free_port()
    out = io.StringIO()
    assert status_main(["--once", "--wait", "0.5", "--listen", f"tcp/127.0.0.1:{port}",
                        "--connect", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"],
                       out) == 1


def test_echo_prints_decoded_detections(agent: int) -> None:
    out = io.StringIO()
    assert echo_main(["smartedge/paper_lab/edge/cam1/detections", "--count", "3",
                      "--duration", "10", *_session_args(agent)], out) == 0
    lines = out.getvalue().splitlines()
    assert len(lines) == 3
    for line in lines:
        assert line.startswith("smartedge/paper_lab/edge/cam1/detections: RobotDetections cam1")
        assert "848x480 sim-noise-v1" in line


def test_echo_refuses_foreign_keys(capsys) -> None:
    assert echo_main(["rt/chatter"]) == 2
    assert "not a smartedge key" in capsys.readouterr().err


def test_summaries_and_table() -> None:
    det = Detection(np.array([1.0, 2.0, 30.0, 60.0]), 0.9, np.zeros((12, 2)),
                    np.r_[np.ones(10), np.zeros(2)], "hsr", np.full(12, 0.7))
    line = summarize(RobotDetections("cam1", 2_500_000_000, 4, 848, 480, "hsr/models", (det,)))
    assert "stamp 2.500" in line and "10/12 keypoints" in line and "sigma median 0.70" in line
    pose = PoseEstimate("hsr", 1, 0, 1.0, 2.0, 0.5, np.diag([1e-4, 4e-4, 1e-4]), "fused")
    assert "x 1.000 y 2.000 theta 28.6 deg (std 1.0/2.0 cm, 0.57 deg)" in summarize(pose)
    st = ServiceStatus("backend", "main", 1, 0, "degraded", 12.0, {"frame_sets": 5.0},
                       {"solve": 1.5}, {}, {"dropped": 3, "received": 100}, (), "slow")
    rows = status_rows({"backend/main": (st, 10.0)}, {"edge-agent/cam2"}, 12.0)
    table = format_table(rows)
    assert "backend/main" in table and "NO" in table and "dropped=3" in table
    assert "received" not in table  # not a problem counter
    assert "edge-agent/cam2  yes    ?" in table  # alive, no status yet
