"""A backend started with ``--area`` on real Zenoh (loopback): it subscribes to its area's
cameras only, solves the robot its cameras see from those cameras alone, announces its area with
a liveliness token, and never receives the other area's detections."""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np
import pytest

from core.geometry import rotation_z
from core.site import Site, parse_site
from protocol import decode, encode, keys
from protocol.messages import Detection, Odometry, PoseEstimate, RobotDetections
from tests.conftest import wait_until

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("gtsam")

SITE = "facility"
#: robot -> where it stands (x, y, theta); r1 in the west, r2 in the east
ROBOTS = {"r1": (2.0, 0.0, 0.3), "r2": (18.0, 0.0, -0.5)}
#: camera -> (position, look-at x, y); three around r1 (west), two around r2 (east)
CAMERAS = {"w0": ((0.0, -3.0), (2.0, 0.0)), "w1": ((4.0, -3.0), (2.0, 0.0)),
           "w2": ((2.0, 3.0), (2.0, 0.0)), "e0": ((16.0, -3.0), (18.0, 0.0)),
           "e1": ((20.0, -3.0), (18.0, 0.0))}
WEST, EAST = ("w0", "w1", "w2"), ("e0", "e1")


def facility_site() -> Site:
    from simulation.scenario import load_scenario

    model = load_scenario().site.robot_model()
    doc: dict[str, Any] = {
        "site": SITE,
        "cameras": [{"id": cid, "resolution": [848, 480],
                     "intrinsics": {"fx": 428.0, "fy": 428.0, "cx": 424.0, "cy": 240.0},
                     "T_world_cam": {"position_m": [p[0], p[1], 2.5],
                                     "look_at_m": [t[0], t[1], 0.3]}}
                    for cid, (p, t) in CAMERAS.items()],
        "robot_models": {"hsr": {
            "footprint_radius_m": model.footprint_radius_m, "height_m": model.height_m,
            "keypoints": [{"name": n, "xyz_m": [float(v) for v in p]}
                          for n, p in zip(model.keypoint_names, model.keypoints_base_m,
                                          strict=True)]}},
        "robots": [{"id": rid, "model": "hsr", "ros": {"namespace": rid}} for rid in ROBOTS],
        "areas": {"west": {"cameras": list(WEST)}, "east": {"cameras": list(EAST)}},
    }
    return parse_site(doc, "facility.yaml")


def camera_messages(site: Site, stamp_ns: int, seq: int, rng: np.random.Generator
                    ) -> dict[str, RobotDetections]:
    """Every camera's unnamed detections of the robots wholly in its image (1 px noise)."""
    out = {}
    for cam in site.cameras.values():
        dets = []
        for rid, (x, y, th) in ROBOTS.items():
            pts = site.robot_model(rid).keypoints_base_m @ rotation_z(th).T + [x, y, 0.0]
            uv, depth = cam.project(pts)
            if not (np.all(depth > 0.3) and np.all(cam.in_image(uv, 2.0))):
                continue
            uv = uv + rng.normal(0.0, 0.5, uv.shape)
            lo, hi = uv.min(axis=0) - 5, uv.max(axis=0) + 5
            dets.append(Detection(np.array([*lo, *hi]), 0.95, uv, np.full(len(uv), 0.9)))
        out[cam.camera_id] = RobotDetections(cam.camera_id, stamp_ns, seq, cam.width,
                                             cam.height, "test", tuple(dets))
    return out


def test_the_site_puts_each_robot_in_front_of_its_own_areas_cameras() -> None:
    site = facility_site()
    msgs = camera_messages(site, 1, 0, np.random.default_rng(0))
    assert all(len(msgs[c].detections) == 1 for c in CAMERAS), {
        c: len(m.detections) for c, m in msgs.items()}


def test_a_backend_serving_every_area_takes_one_wildcard_channel() -> None:
    # the same messages as one channel per camera, with one Zenoh callback thread
    from backend_service.service import BackendNode

    site = facility_site()
    node = BackendNode(site, "b_all", areas=("west", "east"))
    detection_keys = [s.key_expr for s in node.subscriptions()
                      if s.message_type is RobotDetections]
    assert detection_keys == [keys.detections_key(SITE, "*")]
    east = BackendNode(site, "b_east", areas=("east",))
    assert [s.key_expr for s in east.subscriptions() if s.message_type is RobotDetections] == [
        keys.detections_key(SITE, c) for c in EAST]


def test_a_backend_with_an_area_receives_and_solves_only_its_areas_cameras() -> None:
    from backend_service.service import BackendNode
    from core.runtime import ZenohRunner
    from core.session import loopback_config
    from lab.launcher import free_port

    site = facility_site()
    node = BackendNode(site, "bw", areas=("west",))
    detection_keys = [s.key_expr for s in node.subscriptions()
                      if s.message_type is RobotDetections]
    assert detection_keys == [keys.detections_key(SITE, c) for c in WEST]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    runner = ZenohRunner(node, loopback_config(listen=[endpoint]))
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    assert runner.started.wait(20)
    poses: list[PoseEstimate] = []
    rng = np.random.default_rng(1)
    try:
        with zenoh.open(loopback_config(connect=[endpoint])) as client:
            client.declare_subscriber(keys.camera_pose_key(SITE, "*"),
                                      lambda s: poses.append(decode(s.payload.to_bytes())))
            areas = [str(r.ok.key_expr) for r in client.liveliness().get(
                keys.area_key(SITE, "*", "*"), timeout=2.0) if r.ok is not None]
            assert areas == [keys.area_key(SITE, "west", "bw")]
            block = {"congestion_control": zenoh.CongestionControl.BLOCK}
            pubs = {c: client.declare_publisher(keys.detections_key(SITE, c), **block)
                    for c in CAMERAS}
            odom = {r: client.declare_publisher(keys.odom_key(SITE, r), **block) for r in ROBOTS}
            loc = {r: client.declare_publisher(keys.localization_key(SITE, r), **block)
                   for r in ROBOTS}
            sent = {c: 0 for c in CAMERAS}
            t0 = time.time_ns()
            for k in range(45):  # 3 s at 15 Hz
                stamp = time.time_ns()
                for rid, (x, y, th) in ROBOTS.items():
                    odom[rid].put(encode(Odometry(rid, stamp, k, x, y, th, 0.0, 0.0, 0.0,
                                                  np.diag([1e-4] * 3))))
                    if k % 3 == 0:
                        loc[rid].put(encode(PoseEstimate(rid, stamp, k, x + 0.05, y, th,
                                                         np.diag([0.05, 0.05, 0.02]) ** 2,
                                                         "robot")))
                for cam, msg in camera_messages(site, stamp, k, rng).items():
                    pubs[cam].put(encode(msg))
                    sent[cam] += 1
                time.sleep(max(0.0, t0 + (k + 1) * 1e9 / 15 - time.time_ns()) * 1e-9)
            assert wait_until(lambda: len([p for p in poses if p.robot_id == "r1"]) >= 20, 10)
            time.sleep(0.3)
    finally:
        runner.stop()
        thread.join(10)
    # only the west cameras reached the backend's synchronizer: the east ones were never
    # subscribed (nothing of them arrived, nothing to drop)
    per_camera = node.pipeline.sync.camera_counters
    assert set(per_camera) == set(WEST), per_camera
    assert node.pipeline.sync.counters["received"] == sum(sent[c] for c in WEST)
    assert all(per_camera[c]["received"] == sent[c] for c in WEST)
    # r1 is solved from the west cameras alone; r2 (east, seen by no camera of this backend)
    # gets no camera pose here
    r1 = [p for p in poses if p.robot_id == "r1"]
    assert r1 and all(set(p.camera_ids) <= set(WEST) for p in r1)
    assert max(len(p.camera_ids) for p in r1) == 3
    assert all(math.hypot(p.x - 2.0, p.y) < 0.1 for p in r1[-10:])
    assert not [p for p in poses if p.robot_id == "r2"]
    assert node.ownership.table.robot_area("r1") == "west"
    assert node.ownership.table.robot_area("r2") == "east"
    assert "areas: west" in node.ownership.detail(time.time_ns())
