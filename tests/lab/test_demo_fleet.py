"""The live simulation of a fleet (``--sim-robots``) as the demo's services build it: the
edge agents' merged unnamed detections, one simulated robot per bridge (``--robot``), the
demo's commands, and the check of corrections against the robots' truth; ``demo --robots 3``:
two HSR-like robots and a box base (``--sim-mixed-types``), the detections typed."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from lab import demo
from protocol.errors import UnknownIdError, UsageError
from protocol.messages import PoseCorrection, PoseEstimate
from simulation.live import CameraFeed, LiveSimSpec, LiveSimulation

EPOCH_NS = 1_800_000_000 * 10**9


def _live(robots: int = 3, mixed: bool = False) -> LiveSimulation:
    return LiveSimulation(LiveSimSpec(robots=robots, epoch_ns=EPOCH_NS, seed=2, mixed=mixed))


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
    from smartedge.simulated_site import SIM_ADAPTER, register_sim_adapter

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
    from smartedge.simulated_site import SIM_SOURCE, register_sim_source

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


def test_a_mixed_live_fleet_reports_each_robot_typed_with_its_own_keypoints() -> None:
    live = _live(mixed=True)
    assert live.robot_ids == ("hsr_a", "hsr_b", "box_c")
    assert dict(live.site.robots) == {"hsr_a": "hsr", "hsr_b": "hsr", "box_c": "box_base"}
    assert live.runs["box_c"].detector.model.name == "box_base"
    assert "--sim-mixed-types" in live.spec.to_argv()
    cam = live.site.camera("cam1")
    feed = CameraFeed(live, "cam1")
    models: list[str] = []
    for k in range(1, 80):
        now = EPOCH_NS + k * 100_000_000
        for msg in feed.poll(now):
            for d in msg.detections:
                assert d.robot_id == "" and d.robot_model in ("hsr", "box_base")
                models.append(d.robot_model)
                if d.robot_model != "box_base":
                    continue
                # a box-typed detection is the box base's keypoints where the box base is
                pose = live.ground_truth(msg.stamp_ns, "box_c")
                kp = live.site.robot_model("box_c").keypoints_base_m
                c, s_ = np.cos(pose[2]), np.sin(pose[2])
                world = np.column_stack([pose[0] + c * kp[:, 0] - s_ * kp[:, 1],
                                         pose[1] + s_ * kp[:, 0] + c * kp[:, 1], kp[:, 2]])
                uv, _ = cam.project(world)
                assert np.median(np.hypot(*(uv - d.keypoints_px).T)) < 5.0
    assert models.count("box_base") > 50 and models.count("hsr") > 100
    # another process with the same options builds the same mixed fleet
    from simulation.live import add_sim_arguments, spec_from_args

    parser = argparse.ArgumentParser()
    add_sim_arguments(parser)
    again = LiveSimulation(spec_from_args(parser.parse_args(live.spec.to_argv())))
    assert dict(again.site.robots) == dict(live.site.robots)
    with pytest.raises(ValueError, match="mixed"):
        _live(1, mixed=True)


def test_demo_robots_3_is_two_hsrs_and_a_box_base(tmp_path: Path) -> None:
    from core.site import load_site
    from simulation.scenario import load_scenario

    parser = demo.build_parser()
    for robots, expected in ((3, {"hsr_a": "hsr", "hsr_b": "hsr", "box_c": "box_base"}),
                             (2, {"hsr_a": "hsr", "hsr_b": "hsr"})):
        args = parser.parse_args(["--robots", str(robots), "--out", str(tmp_path)])
        path = demo._fleet_setup(args, parser, load_scenario().site, tmp_path)
        site = load_site(path)  # the file the services get: both models, every namespace
        assert dict(site.robots) == expected
        assert {site.ros_section(r)["namespace"] for r in site.robots} == set(expected)
        assert args.detections == "noise" and args.no_clouds
    live = _live(mixed=True)
    args = argparse.Namespace(no_feedback=False, kidnapped=False, processes=False,
                              detections="noise", no_clouds=True)
    services = demo.Services(args, live.spec, Path("fleet_site.yaml"), "tcp/127.0.0.1:7447",
                             "none", ["cam1"])
    commands = dict(services.commands())
    assert sorted(n for n in commands if n.startswith("robot-bridge")) == [
        "robot-bridge/box_c", "robot-bridge/hsr_a", "robot-bridge/hsr_b"]
    assert all("--sim-mixed-types" in argv for n, argv in commands.items()
               if n.startswith(("robot-bridge", "edge-agent")))


def test_the_fleet_summary_names_each_robots_model() -> None:
    import io

    live = _live(mixed=True)
    stamp = EPOCH_NS + 7 * 10**9
    seen = demo.Observed()
    for rid in live.robot_ids:
        x, y, th = live.ground_truth(stamp, rid)
        seen.fused.append(PoseEstimate(rid, stamp, 0, float(x) + 0.01, float(y), float(th),
                                       np.eye(3) * 1e-4, "fused"))
    out = io.StringIO()
    figures = demo.summarize_fleet(seen, live, out)
    rows = {line.split()[0]: line.split()[1] for line in out.getvalue().splitlines()
            if line.strip().startswith(("hsr_", "box_"))}
    assert rows == {"hsr_a": "hsr", "hsr_b": "hsr", "box_c": "box_base"}
    assert figures["box_c fused"] == pytest.approx(0.01, abs=1e-6)


def test_the_viewer_draws_the_box_base_as_a_box_and_the_hsr_as_a_cylinder() -> None:
    import rerun as rr

    from smartedge.viewer.rerun_view import robot_body

    site = _live(mixed=True).site
    hsr = robot_body(site.robot_model("hsr_a"))
    box = robot_body(site.robot_model("box_c"))
    assert isinstance(hsr, rr.Cylinders3D) and isinstance(box, rr.Boxes3D)
    half = np.asarray(box.half_sizes.as_arrow_array().to_pylist()).reshape(-1)
    np.testing.assert_allclose(half, [0.25, 0.2, 0.17], atol=1e-6)  # 0.5 x 0.4 m, 0.34 m top
