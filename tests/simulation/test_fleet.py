"""simulation.fleet: identical robots on one site, one camera image of all of them, the
detections merged without robot ids, the truth kept aside, each robot the same as alone; a
fleet of two types (two HSR-like robots and a box base), each detected with its own model's
keypoints and typed, or untyped."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from protocol.messages import Odometry, PoseEstimate, RobotDetections
from simulation.fleet import (
    CROSSING_ROUTES,
    MIXED_FLEET,
    FleetRun,
    alone_run,
    fleet_routes,
    fleet_run,
    fleet_site,
    fleet_spec,
    footprint_gap_m,
    merged_messages,
    min_footprint_gap,
)
from simulation.robot_mesh import box_base_keypoints


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


def _mixed(until_s: float | None = 10.0, seed: int = 5, typed: bool = True) -> FleetRun:
    return fleet_run(fleet_routes(list(MIXED_FLEET)), until_s=until_s, seed=seed,
                     site=fleet_site(MIXED_FLEET), typed=typed)


def test_a_mixed_fleet_site_holds_both_models_each_robot_in_its_namespace() -> None:
    assert fleet_spec(3, mixed=True) == dict(MIXED_FLEET)
    assert fleet_spec(2, mixed=True) == {"hsr_a": "hsr", "box_c": "box_base"}
    assert fleet_spec(2) == {"hsr_a": "hsr", "hsr_b": "hsr"}
    with pytest.raises(ValueError, match="at least 2"):
        fleet_spec(1, mixed=True)
    site = fleet_site(MIXED_FLEET)  # the paper lab has no box base: the built-in one is added
    assert dict(site.robots) == dict(MIXED_FLEET)
    assert {site.ros_section(r)["namespace"] for r in site.robots} == set(MIXED_FLEET)
    box = site.robot_model("box_c")
    names, kp = box_base_keypoints()  # the site's box base is the renderer's box
    assert box.keypoint_names == names
    np.testing.assert_allclose(box.keypoints_base_m, kp, atol=1e-9)
    assert box.footprint_radius_m == pytest.approx(0.32)
    assert site.robot_model("hsr_a").footprint_radius_m == pytest.approx(0.215)
    with pytest.raises(ValueError, match="forklift"):
        fleet_site({"f1": "forklift"})


def test_footprint_gaps_measure_the_bodies_not_the_centres() -> None:
    fleet = _mixed(until_s=1.0)
    box = np.array([10.0, 6.0, 0.0])  # 0.5 m long in x, 0.4 m wide in y
    # the HSR (radius 0.215 m) beside the box's long side, 0.5 m from its centre
    assert footprint_gap_m(fleet, "box_c", "hsr_a", box, box + np.array([0.0, 0.5, 0.0])) == \
        pytest.approx(0.5 - 0.2 - 0.215, abs=1e-3)
    # the same distance off the box's front: its body reaches 5 cm further
    assert footprint_gap_m(fleet, "box_c", "hsr_a", box, box + np.array([0.5, 0.0, 0.0])) == \
        pytest.approx(0.5 - 0.25 - 0.215, abs=1e-3)
    # turned 90 degrees, the long side faces the HSR in x
    turned = box + np.array([0.0, 0.0, np.pi / 2])
    assert footprint_gap_m(fleet, "box_c", "hsr_a", turned, box + np.array([0.5, 0.0, 0.0])) == \
        pytest.approx(0.5 - 0.2 - 0.215, abs=1e-3)
    assert footprint_gap_m(fleet, "box_c", "hsr_a", box, box + np.array([0.3, 0.0, 0.0])) < 0
    assert footprint_gap_m(fleet, "hsr_a", "hsr_b", box, box + np.array([0.5, 0.0, 0.0])) == \
        pytest.approx(0.5 - 0.43, abs=1e-3)


def test_the_mixed_routes_cross_and_pass_closely_without_touching() -> None:
    for seed in (3, 4, 5):
        fleet = _mixed(until_s=None, seed=seed)
        d, _, a, b = fleet.min_distance()
        assert d <= 0.5 and {a, b} == {"hsr_a", "hsr_b"}, (seed, d, a, b)  # identical pair
        gap, _, a, b = min_footprint_gap(fleet)
        assert 0.0 < gap < 0.1, (seed, gap, a, b)  # the bodies pass within 10 cm
        t = np.arange(0.0, fleet.until_s, 0.05)
        box = fleet.runs["box_c"].plan.pose_at(t)[:, :2]
        for rid in ("hsr_a", "hsr_b"):  # the box base crosses both lanes near both robots
            own = fleet.runs[rid].plan.pose_at(t)[:, :2]
            assert np.hypot(*(box - own).T).min() < 1.0, (seed, rid)


def test_each_type_is_detected_with_its_own_keypoints_and_typed() -> None:
    fleet = _mixed()
    residual: dict[tuple[str, str], list[float]] = {}
    images = 0
    for _, m in merged_messages(fleet):
        if not isinstance(m, RobotDetections):
            continue
        images += 1
        cam = fleet.site.camera(m.camera_id)
        stamp = int(m.stamp_ns) + int(fleet.site.cameras[m.camera_id].clock_offset_ns)
        for d, rid in zip(m.detections, fleet.truth[id(m)], strict=True):
            assert d.robot_id == "" and d.robot_model == MIXED_FLEET[rid]
            pose = fleet.true_pose(rid, stamp)
            c, s_ = np.cos(pose[2]), np.sin(pose[2])
            for model_of in ("hsr_a", "box_c"):  # its own model's keypoints, and the other's
                kp = fleet.site.robot_model(model_of).keypoints_base_m
                world = np.column_stack([pose[0] + c * kp[:, 0] - s_ * kp[:, 1],
                                         pose[1] + s_ * kp[:, 0] + c * kp[:, 1], kp[:, 2]])
                uv, _ = cam.project(world)
                err = np.hypot(*(uv - d.keypoints_px).T)
                kind = "own" if fleet.site.robots[model_of] == MIXED_FLEET[rid] else "other"
                residual.setdefault((MIXED_FLEET[rid], kind), []).append(float(np.median(err)))
    assert images > 400
    for model in ("hsr", "box_base"):
        own = np.median(residual[(model, "own")])
        other = np.median(residual[(model, "other")])
        assert len(residual[(model, "own")]) > 200, model
        assert own < 5.0 and other > 4 * own, (model, own, other)


def test_an_untyped_fleet_strips_the_type_and_a_box_drives_alone_as_a_box() -> None:
    fleet = _mixed(until_s=3.0, typed=False)
    dets = [d for _, m in merged_messages(fleet) if isinstance(m, RobotDetections)
            for d in m.detections]
    assert len(dets) > 100 and all(d.robot_model == "" for d in dets)
    alone = alone_run(_mixed(until_s=3.0), "box_c")
    assert dict(alone.scenario.site.robots) == {"box_c": "box_base"}
