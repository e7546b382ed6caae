"""The live simulation of a fleet (``--sim-robots``) as the demo's services build it: the
edge agents' merged unnamed detections, one simulated robot per bridge (``--robot``), the
demo's commands, and the check of corrections against the robots' truth."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from protocol.errors import UnknownIdError, UsageError
from protocol.messages import PoseCorrection
from simulation.live import CameraFeed, LiveSimSpec, LiveSimulation
from smartedge import demo

EPOCH_NS = 1_800_000_000 * 10**9


def _live(robots: int = 3) -> LiveSimulation:
    return LiveSimulation(LiveSimSpec(robots=robots, epoch_ns=EPOCH_NS, seed=2))


def test_a_live_fleet_camera_reports_every_robot_unnamed() -> None:
    live = _live()
    assert live.robot_ids == ("hsr_a", "hsr_b", "hsr_c")
    assert {live.site.ros_section(r)["namespace"] for r in live.robot_ids} == set(
        live.robot_ids)
    feed = CameraFeed(live, "cam1")
    counts = []
    for k in range(1, 80):  # 8 s: all three in view of cam1 most of the time
        for msg in feed.poll(EPOCH_NS + k * 100_000_000):
            assert all(d.robot_id == "" for d in msg.detections)
            counts.append(len(msg.detections))
    assert max(counts) == 3 and len(counts) > 100
    # one robot: one detection at most, as before
    single = CameraFeed(_live(1), "cam1")
    assert max(len(m.detections) for k in range(1, 40)
               for m in single.poll(EPOCH_NS + k * 100_000_000)) == 1
    # the same spec in another process: the same robots, the same truth
    again = _live()
    for rid in live.robot_ids:
        np.testing.assert_array_equal(live.ground_truth(EPOCH_NS + 7 * 10**9, rid),
                                      again.ground_truth(EPOCH_NS + 7 * 10**9, rid))
    assert "--sim-robots" in live.spec.to_argv()


def test_each_bridge_drives_its_own_robot_and_an_unknown_one_is_named() -> None:
    from robot_bridge.service import build_parser
    from smartedge.sim.plugins import SIM_ADAPTER, register_sim_adapter

    register_sim_adapter()
    spec = LiveSimSpec(robots=3, epoch_ns=EPOCH_NS, seed=2)
    args = build_parser().parse_args(["--adapter", "sim", "--robot", "hsr_b",
                                      *spec.to_argv()])
    setup = SIM_ADAPTER.build(args, None)
    assert setup.robot_id == "hsr_b" and list(setup.site.robots) == ["hsr_a", "hsr_b", "hsr_c"]
    adapter = setup.factory(None)
    setup.advance(EPOCH_NS + 3 * 10**9)
    assert adapter.read_odometry()
    loc = adapter.read_localization()
    truth = LiveSimulation(spec).ground_truth(loc.stamp_ns, "hsr_b")
    assert np.hypot(loc.x - truth[0], loc.y - truth[1]) < 0.2  # hsr_b's (hsr_a starts 3 m away)
    args.robot = "hsr_x"
    with pytest.raises(UnknownIdError, match="hsr_x"):
        SIM_ADAPTER.build(args, None)


def test_the_rendered_cameras_refuse_a_fleet() -> None:
    from edge_agent.service import build_parser
    from smartedge.sim.plugins import SIM_SOURCE, register_sim_source

    register_sim_source()
    spec = LiveSimSpec(robots=2, epoch_ns=EPOCH_NS)
    args = build_parser().parse_args(["--source", "sim", "--camera", "cam1",
                                      "--detections", "cnn", *spec.to_argv()])
    with pytest.raises(UsageError, match="noise"):
        SIM_SOURCE.build(args, None)


def test_the_demo_starts_one_bridge_per_robot() -> None:
    live = _live()
    args = argparse.Namespace(no_feedback=False, kidnapped=False, processes=False,
                              detections="noise", no_clouds=True)
    services = demo.Services(args, live.spec, Path("fleet_site.yaml"), "tcp/127.0.0.1:7447",
                             "none", ["cam1"])
    commands = dict(services.commands())
    bridges = {n: a for n, a in commands.items() if n.startswith("robot-bridge")}
    assert sorted(bridges) == [f"robot-bridge/{r}" for r in live.robot_ids]
    for name, argv in bridges.items():
        assert argv[argv.index("--robot") + 1] == name.split("/")[1]
        assert argv[argv.index("--sim-robots") + 1] == "3"


def test_wrong_robot_corrections_are_counted() -> None:
    live = _live()
    stamp = EPOCH_NS + 7 * 10**9
    a, b = (live.ground_truth(stamp, r) for r in ("hsr_a", "hsr_b"))

    def corr(rid: str, pose: np.ndarray) -> PoseCorrection:
        return PoseCorrection(rid, stamp, 0, float(pose[0]), float(pose[1]), float(pose[2]),
                              np.eye(3) * 1e-4, "correction")

    seen = demo.Observed(corrections=[corr("hsr_a", a), corr("hsr_b", b)],
                         correction_keys=["hsr_a", "hsr_b"])
    assert demo.wrong_robot_corrections(seen, live) == 0
    seen.correction_keys = ["hsr_a", "hsr_a"]  # hsr_b's correction on hsr_a's key
    assert demo.wrong_robot_corrections(seen, live) == 1
    seen = demo.Observed(corrections=[corr("hsr_a", b)], correction_keys=["hsr_a"])
    assert demo.wrong_robot_corrections(seen, live) == 1  # placed on the other robot


def test_the_viewer_has_every_robots_truth() -> None:
    from smartedge.viewer.node import truth_from_live

    live = _live()
    truth = truth_from_live(live)
    stamp = EPOCH_NS + 5 * 10**9
    for rid in live.robot_ids:
        np.testing.assert_array_equal(truth(rid, stamp), live.ground_truth(stamp, rid))
    assert not np.allclose(truth("hsr_a", stamp), truth("hsr_b", stamp))
    assert truth("hsr", stamp) is None
