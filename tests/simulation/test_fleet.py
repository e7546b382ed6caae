"""simulation.fleet: identical robots on one site, one camera image of all of them, the
detections merged without robot ids, the truth kept aside, each robot the same as alone."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from protocol.messages import Odometry, PoseEstimate, RobotDetections
from simulation.fleet import (
    CROSSING_ROUTES,
    FleetRun,
    alone_run,
    fleet_run,
    fleet_site,
    merged_messages,
)


@pytest.fixture
def fleet() -> FleetRun:
    return fleet_run(CROSSING_ROUTES, until_s=12.0, seed=5)


def test_the_fleet_site_gives_every_robot_its_own_namespace() -> None:
    site = fleet_site(["r1", "r2", "r3"])
    assert dict(site.robots) == {"r1": "hsr", "r2": "hsr", "r3": "hsr"}
    assert {site.ros_section(r)["namespace"] for r in site.robots} == {"r1", "r2", "r3"}
    with pytest.raises(ValueError, match="distinct"):
        fleet_site(["r1", "r1"])


def test_the_crossing_routes_pass_within_half_a_metre_without_touching(fleet: FleetRun) -> None:
    d, t, a, b = fleet.min_distance()
    radius = fleet.site.robot_model("hsr_a").footprint_radius_m
    assert 2 * radius < d <= 0.5, (d, a, b)
    assert 5.0 < t < 12.0
    # every pair comes within 1 m: all three cross paths
    times = np.arange(0.0, fleet.until_s, 0.05)
    for r1, r2 in itertools.combinations(fleet.robot_ids, 2):
        gap = np.hypot(*(fleet.runs[r1].plan.pose_at(times)[:, :2]
                         - fleet.runs[r2].plan.pose_at(times)[:, :2]).T)
        assert gap.min() < 1.0, (r1, r2)


def test_merged_images_hold_every_robots_detection_unnamed_in_arrival_order(
        fleet: FleetRun) -> None:
    stream = merged_messages(fleet, localization_rate_hz=10.0)
    arrivals = [a for a, _ in stream]
    assert arrivals == sorted(arrivals)
    images = [m for _, m in stream if isinstance(m, RobotDetections)]
    cams = len(fleet.site.cameras)
    frames = round(fleet.until_s * 15.0)
    assert abs(len(images) - cams * frames) <= cams  # one message per camera image
    assert len({(m.camera_id, m.stamp_ns) for m in images}) == len(images)
    per_robot = dict.fromkeys(fleet.robot_ids, 0)
    orders = set()
    for m in images:
        truth = fleet.truth[id(m)]
        assert len(truth) == len(m.detections) <= 3
        assert all(d.robot_id == "" for d in m.detections)
        for rid in truth:
            per_robot[rid] += 1
        if len(truth) == 3:
            orders.add(truth)
    assert min(per_robot.values()) > 300
    assert len(orders) > 3  # shuffled, not in robot order
    for rid in fleet.robot_ids:
        assert any(isinstance(m, Odometry) and m.robot_id == rid for _, m in stream)
        assert any(isinstance(m, PoseEstimate) and m.robot_id == rid for _, m in stream)
    with pytest.raises(RuntimeError, match="once"):
        next(fleet.messages())


def test_a_robot_alone_is_detected_exactly_as_in_the_fleet(fleet: FleetRun) -> None:
    merged = [m for _, m in merged_messages(fleet)]
    rid = "hsr_b"
    alone = alone_run(fleet, rid)
    assert list(alone.scenario.site.robots) == [rid]
    own: dict[tuple[str, int], np.ndarray] = {}
    for m in merged:
        if isinstance(m, RobotDetections):
            for d, t in zip(m.detections, fleet.truth[id(m)], strict=True):
                if t == rid:
                    own[(m.camera_id, m.stamp_ns)] = d.keypoints_px
    seen = 0
    for tm in alone.messages(until_s=fleet.until_s):
        m = tm.message
        if isinstance(m, RobotDetections) and m.detections:
            np.testing.assert_array_equal(own.pop((m.camera_id, m.stamp_ns)),
                                          m.detections[0].keypoints_px)
            seen += 1
    assert seen > 300 and not own
    np.testing.assert_allclose(alone.log.arrays()[2], fleet.runs[rid].log.arrays()[2])


def test_a_correction_reaches_only_the_robot_it_is_for() -> None:
    fleet = fleet_run(CROSSING_ROUTES, until_s=3.0, seed=5)
    target = np.array([8.4, 5.7, 0.0])
    done: set[str] = set()

    def on_step(rid: str, t_s: float) -> None:
        robot = fleet.runs[rid].robot
        if rid == "hsr_a" and rid not in done and t_s > 1.0:  # standing at its start
            assert robot.apply_correction(target, robot.stamp_ns(t_s))
            done.add(rid)

    for _ in fleet.messages(on_step=on_step):
        pass
    assert done == {"hsr_a"}
    assert fleet.runs["hsr_a"].robot.corrections_applied == 1
    assert all(fleet.runs[r].robot.corrections_applied == 0 for r in ("hsr_b", "hsr_c"))
