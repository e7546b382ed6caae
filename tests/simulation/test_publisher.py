"""The simulation publishes through protocol over a real Zenoh session on loopback and applies
pose corrections it receives (only while the robot is static)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from core.session import loopback_config  # noqa: E402
from lab.launcher import free_port  # noqa: E402
from protocol import keys  # noqa: E402
from protocol.codec import decode, encode  # noqa: E402
from protocol.messages import Odometry, PoseCorrection, RobotDetections  # noqa: E402
from simulation.publisher import publish_run  # noqa: E402
from simulation.runner import SimulationRun  # noqa: E402
from simulation.scenario import load_scenario  # noqa: E402


def test_publish_over_zenoh_and_apply_correction() -> None:
    sc = load_scenario()
    run = SimulationRun(sc, "traj3", seed=3)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    site, robot = sc.site.name, sc.robot_id
    with zenoh.open(loopback_config(listen=[endpoint])) as sim_session, \
            zenoh.open(loopback_config(connect=[endpoint])) as backend:
        dets = backend.declare_subscriber(keys.detections_key(site, "*"),
                                          zenoh.handlers.FifoChannel(10_000))
        odom = backend.declare_subscriber(keys.odom_key(site, robot),
                                          zenoh.handlers.FifoChannel(10_000))
        time.sleep(0.5)  # let the sessions connect
        result = {}
        thread = threading.Thread(
            target=lambda: result.update(stats=publish_run(sim_session, run, speed=1.0,
                                                           until_s=1.8)))
        thread.start()
        first = odom.recv()  # the robot is publishing: now send a correction
        msg = decode(first.payload.to_bytes(), Odometry)
        target = (run.waypoints[0].x + 0.05, run.waypoints[0].y - 0.03, run.waypoints[0].theta)
        backend.put(keys.correction_key(site, robot), encode(PoseCorrection(
            robot_id=robot, stamp_ns=msg.stamp_ns, seq=0, x=target[0], y=target[1],
            theta=target[2], covariance=np.eye(3) * 1e-4, kind="correction")))
        thread.join(timeout=30)
        assert not thread.is_alive()
        time.sleep(0.3)
        got_dets = []
        while (s := dets.try_recv()) is not None:
            got_dets.append(decode(s.payload.to_bytes(), RobotDetections))
        got_odom = 1
        while odom.try_recv() is not None:
            got_odom += 1
    stats = result["stats"]
    assert stats.detections > 60 and stats.odometry >= 30
    assert len(got_dets) == stats.detections and got_odom == stats.odometry
    assert {d.camera_id for d in got_dets} == set(sc.site.cameras)
    assert stats.corrections_applied == 1
    np.testing.assert_allclose(run.robot.localization_pose(), target, atol=1e-9)
