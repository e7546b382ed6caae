"""`smartedge bench fleet` builds a real facility (routers, backends, cameras) and measures it:
a tiny one here."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lab.bench import BENCHES
from protocol import decode
from protocol.messages import RobotDetections

pytest.importorskip("zenoh")


def test_registered_as_a_bench() -> None:
    assert BENCHES["fleet"][:2] == ("lab.bench.fleet", "main")


def test_every_camera_reports_the_robots_of_its_cell_unnamed(tmp_path: Path) -> None:
    from lab.bench.fleet import FleetLayout, camera_detections, write_fleet_site

    site, layout = write_fleet_site(tmp_path / "site.yaml", 3, 12)
    assert isinstance(layout, FleetLayout)
    assert len(site.cameras) == 12 and sorted(site.robots) == list(layout.robot_ids)
    assert {layout.cell_of[c] for c in site.cameras} == {0, 1, 2}
    poses = np.stack([layout.robot_pose(i, 1.0) for i in range(3)])
    msgs, seen = camera_detections(site, layout, poses, 1_000, 0, np.random.default_rng(0))
    assert seen == set(layout.robot_ids)
    for key, payload, cell in msgs:
        msg = decode(payload)
        assert isinstance(msg, RobotDetections) and key.endswith(f"/{msg.camera_id}/detections")
        assert cell == layout.cell_of[msg.camera_id]
        assert msg.detections and all(not d.robot_id for d in msg.detections)
        # the cell's own robot is in every one of its cameras' messages: its keypoints are
        # where the camera projects them (1 px noise)
        pts = (site.robot_model(layout.robot_ids[cell]).keypoints_base_m
               @ np.array([[math.cos(poses[cell][2]), -math.sin(poses[cell][2]), 0],
                           [math.sin(poses[cell][2]), math.cos(poses[cell][2]), 0],
                           [0, 0, 1]]).T + [poses[cell][0], poses[cell][1], 0.0])
        uv, _ = site.cameras[msg.camera_id].project(pts)
        err = min(float(np.abs(d.keypoints_px - uv).max()) for d in msg.detections)
        assert err < 6.0


@pytest.mark.slow
def test_two_backends_on_two_routers_split_the_robots_and_measure_latency(
        tmp_path: Path) -> None:
    from lab.bench.fleet import FleetRow, run_row

    r = run_row(FleetRow(backends=2, routers=2, robots=2, cameras=6, rate_hz=10.0,
                         odom_rate_hz=10.0, seconds=3.0, warmup_s=3.0), tmp_path, progress=False)
    print(r)
    assert r.frame_sets >= 50  # 2 robots x 30 frames, those seen by a camera
    assert r.poses >= 0.8 * r.frame_sets, r
    assert 0 < r.p50_ms <= r.p99_ms <= r.max_ms < 1000
    assert r.duplicates == 0 and r.silent == 0, r
    owned = [set(v.split(",")) - {"-"} for v in r.owners.values()]
    assert len(owned) == 2 and set.union(*owned) == {"robot00", "robot01"}, r.owners
    assert not set.intersection(*owned), r.owners
    # the work is split: each backend skips the other's robot and predicts it from the poses
    # its owner publishes on the bus
    assert r.counters.get("standby.detections", 0) > 20, r.counters
    assert r.counters.get("external_pose.used", 0) > 20, r.counters
    assert all(v >= 0 for v in r.cpu.values()) and set(r.cpu) >= {"router0", "router1",
                                                                  "backend0", "backend1"}
    # each backend's CPU by thread: the worker did the work; the classes sum to the process
    assert set(r.thread_cpu) == {"backend0", "backend1"}, r.thread_cpu
    for name, by_class in r.thread_cpu.items():
        assert by_class["worker"] > 0 and min(by_class.values()) >= 0, by_class
        assert sum(by_class.values()) == pytest.approx(r.cpu[name], abs=0.05), (by_class, r.cpu)
    assert len(r.latencies) == r.poses and all(0 <= t <= 3.5 for _, t, _ in r.latencies)


def test_worst_frames_and_the_latency_csv(tmp_path: Path) -> None:
    from lab.bench.fleet import RowResult, worst_frames, write_latencies

    lat = [("r0", 0.0, 20.0), ("r1", 0.0, 90.0), ("r0", 0.0667, 30.0), ("r1", 0.0667, 25.0),
           ("r0", 4.333, 70.0), ("r1", 4.333, 10.0)]
    # the frames whose slowest pose was slowest, in time order
    assert worst_frames(lat, 2) == [(0.0, 90.0), (4.333, 70.0)]
    assert worst_frames([]) == []
    row = RowResult(backends=3, split="area", p50_ms=25.0, p99_ms=90.0, max_ms=90.0, poses=6,
                    frame_sets=6, missing=0, accounted=0, duplicates=0, late_publish=0, cpu={},
                    counters={}, stage_ms={}, owners={}, statuses_in_span={},
                    unreadable_statuses=0, missing_at=[], received={}, areas={},
                    latencies=lat)
    out = tmp_path / "lat.csv"
    write_latencies(out, [row])
    lines = out.read_text().splitlines()
    assert lines[0] == "split,backends,robot,stamp_s,latency_ms" and len(lines) == 7
    assert lines[2] == "area,3,r1,0.000,90.000"
