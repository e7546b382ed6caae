"""Frame-set synchronizer edge cases."""

from __future__ import annotations

import dataclasses

import numpy as np

from backend_service.sync import FrameSetSynchronizer
from protocol.messages import Detection, RobotDetections
from tests.backend_service.pose_synth import example_site

SITE = example_site()
CAMS = sorted(SITE.cameras)  # cam_ne, cam_nw, cam_se, cam_sw
MS = 1_000_000
T0 = 1_700_000_000_000_000_000


def det_msg(cam: str, stamp_ns: int, seq: int = 0, seen: bool = True,
            n_kp: int = 12) -> RobotDetections:
    dets = ()
    if seen:
        dets = (Detection(np.array([10.0, 10.0, 50.0, 80.0]), 0.9,
                          np.full((n_kp, 2), 20.0), np.full(n_kp, 0.8)),)
    return RobotDetections(cam, stamp_ns, seq, 848, 480, "test", dets)


def test_all_cameras_report_emits_immediately() -> None:
    sync = FrameSetSynchronizer(SITE)
    out = []
    for i, cam in enumerate(CAMS):
        out += sync.push(det_msg(cam, T0 + i * MS), T0 + 5 * MS)
    # cold start: every site camera is presumed live, the window closes on the fourth message
    assert len(out) == 1 and out[0].camera_ids == tuple(CAMS)
    # second round: all four live, the window closes on the fourth message, no waiting
    t1 = T0 + 33 * MS
    got = []
    for cam in CAMS:
        got += sync.push(det_msg(cam, t1 + 2 * MS, seq=1), t1 + 10 * MS)
    assert len(got) == 1 and got[0].camera_ids == tuple(CAMS)
    assert abs(got[0].stamp_ns - (t1 + 2 * MS)) <= 1


def _warm(sync: FrameSetSynchronizer, t: int) -> None:
    for cam in CAMS:
        sync.push(det_msg(cam, t), t)
    sync.poll(t + 500 * MS)


def test_missing_camera_waits_then_emits_partial_set() -> None:
    sync = FrameSetSynchronizer(SITE)
    _warm(sync, T0)
    t1 = T0 + 1000 * MS
    out = []
    for cam in CAMS[:3]:
        out += sync.push(det_msg(cam, t1, seq=1), t1 + 5 * MS)
    assert out == []
    out = sync.poll(t1 + 5 * MS + int(SITE.thresholds.sync_max_wait_ms * MS))
    assert len(out) == 1 and out[0].camera_ids == tuple(CAMS[:3])


def test_camera_not_seeing_the_robot_still_completes_the_window() -> None:
    sync = FrameSetSynchronizer(SITE)
    _warm(sync, T0)
    t1 = T0 + 1000 * MS
    out = []
    for cam in CAMS:
        out += sync.push(det_msg(cam, t1, seq=1, seen=cam != "cam_nw"), t1 + 5 * MS)
    assert len(out) == 1 and "cam_nw" not in out[0].camera_ids
    assert sync.counters["not_seen"] == 1


def test_silent_camera_is_not_waited_for_after_timeout() -> None:
    sync = FrameSetSynchronizer(SITE)
    _warm(sync, T0)
    t1 = T0 + int((SITE.thresholds.camera_timeout_s + 1) * 1e9)
    out = []
    for seq, t in ((1, t1 - 100 * MS), (2, t1)):  # the other two went silent long ago
        for cam in CAMS[:2]:
            out += sync.push(det_msg(cam, t, seq=seq), t + 1 * MS)
    # once both are live again, a window closes as soon as the two are in: nobody waits for
    # the silent cameras (the very first one closed on cam_ne alone: cam_nw was not live yet)
    assert out[-1].camera_ids == tuple(CAMS[:2])
    assert sync.open_windows == 0


def test_out_of_order_and_late_messages() -> None:
    sync = FrameSetSynchronizer(SITE)
    _warm(sync, T0)
    t1 = T0 + 1000 * MS
    # newer frame of cam_ne arrives before the older frames of the other cameras
    out = sync.push(det_msg("cam_ne", t1 + 33 * MS, seq=2), t1 + 40 * MS)
    out += sync.push(det_msg("cam_ne", t1, seq=1), t1 + 41 * MS)
    for cam in CAMS[1:]:
        out += sync.push(det_msg(cam, t1 + 3 * MS, seq=1), t1 + 42 * MS)
    assert len(out) == 1 and out[0].camera_ids == tuple(CAMS)  # the older window is complete
    # a message for the emitted window is late and dropped
    assert sync.push(det_msg("cam_sw", t1 - 5 * MS, seq=9), t1 + 50 * MS) == []
    assert sync.counters["late"] == 1
    rest = sync.flush()
    assert [fs.camera_ids for fs in rest] == [("cam_ne",)]
    stamps = [fs.stamp_ns for fs in out + rest]
    assert stamps == sorted(stamps)


def test_duplicate_future_unknown_and_bad_keypoints_are_counted() -> None:
    sync = FrameSetSynchronizer(SITE)
    sync.push(det_msg("cam_ne", T0), T0)
    sync.push(det_msg("cam_ne", T0), T0 + MS)
    assert sync.counters["duplicate"] == 1
    sync.push(det_msg("cam_ne", T0 + 10**10, seq=3), T0 + 2 * MS)
    assert sync.counters["future"] == 1
    assert sync.push(det_msg("cam_zz", T0), T0) == []
    assert sync.counters["unknown_camera"] == 1
    sync.push(det_msg("cam_sw", T0 + MS, n_kp=5), T0 + 2 * MS)
    assert sync.counters["bad_keypoints"] == 1
    assert sync.counters["received"] == 5


def test_clock_offset_brings_stamps_onto_the_common_clock() -> None:
    offset = 250 * MS  # cam_sw's clock runs 250 ms behind
    cams = dict(SITE.cameras)
    cams["cam_sw"] = dataclasses.replace(cams["cam_sw"], clock_offset_ns=offset)
    site = dataclasses.replace(SITE, cameras=cams)
    sync = FrameSetSynchronizer(site)
    out = []
    for cam in CAMS:
        stamp = T0 - offset if cam == "cam_sw" else T0
        out += sync.push(det_msg(cam, stamp), T0 + MS)
    out += sync.poll(T0 + 500 * MS)
    assert len(out) == 1 and out[0].camera_ids == tuple(CAMS)
    assert all(o.stamp_ns == T0 for o in out[0].observations)


def test_memory_is_bounded() -> None:
    th = dataclasses.replace(SITE.thresholds, sync_max_wait_ms=1e6, camera_timeout_s=1e6)
    sync = FrameSetSynchronizer(dataclasses.replace(SITE, thresholds=th), max_open_windows=8)
    out = []
    for i in range(100):  # one camera streams, the others stay "live" forever: windows pile up
        t = T0 + (i + 1) * 40 * MS
        out += sync.push(det_msg("cam_ne", t, seq=i + 1), t)
    assert sync.open_windows <= 8 + 1
    assert sync.counters["overflow"] > 0
    assert len(out) >= 90 and sync.counters["late"] == 0


def test_a_backend_of_some_cameras_waits_only_for_them_at_a_cold_start() -> None:
    # a backend serving an area receives its cameras only: at a cold start it presumes those
    # live, not the site's others (it would wait sync_max_wait_ms for every frame-set)
    sync = FrameSetSynchronizer(SITE)
    sync.expect_cameras(CAMS[:2])
    out = sync.push(det_msg(CAMS[0], T0), T0 + 5 * MS)
    assert out == []
    out = sync.push(det_msg(CAMS[1], T0), T0 + 6 * MS)
    assert len(out) == 1 and out[0].camera_ids == tuple(CAMS[:2])
    plain = FrameSetSynchronizer(SITE)
    for cam in CAMS[:2]:
        assert plain.push(det_msg(cam, T0), T0 + 6 * MS) == []  # waits for all four
    try:
        sync.expect_cameras(["cam_nope"])
    except ValueError as exc:
        assert "cam_nope" in str(exc)
    else:
        raise AssertionError("an unknown camera was accepted")


def test_robots_run_elsewhere_are_not_synchronized_and_come_back_cleanly() -> None:
    sync = FrameSetSynchronizer(SITE)
    robot = sync.robot_ids[0]
    _warm(sync, T0)
    t1 = T0 + 1000 * MS
    for cam in CAMS[:2]:
        assert sync.push(det_msg(cam, t1, seq=1), t1 + 5 * MS) == []
    assert sync.open_windows == 1
    # the robot goes to another backend: its open window comes back, nothing more opens
    left = sync.synchronize_only([])
    assert len(left) == 1 and left[0].robot_id == robot and left[0].camera_ids == tuple(CAMS[:2])
    t2 = t1 + 100 * MS
    emitted = sync.counters["emitted"]
    for cam in CAMS:
        assert sync.push(det_msg(cam, t2, seq=2), t2 + 5 * MS) == []
    assert sync.open_windows == 0 and sync.counters["emitted"] == emitted
    assert sync.poll(t2 + 1000 * MS) == []
    # taken back: the next frame is synchronized as before
    assert sync.synchronize_only(None) == []
    t3 = t2 + 100 * MS
    out = []
    for cam in CAMS:
        out += sync.push(det_msg(cam, t3, seq=3), t3 + 5 * MS)
    assert len(out) == 1 and out[0].camera_ids == tuple(CAMS)


def test_a_window_waits_only_for_the_cameras_that_can_see_its_robot() -> None:
    """With ``relevant_cameras`` (a site with several robots: the cameras where the robot's
    prediction has a keypoint), a window closes once those cameras reported; a camera that
    cannot see the robot is not waited for, and its message after the close is counted
    ``after_close``, not ``late``. A relevant camera after the close is still ``late``, and
    without a relevant set (no prediction) every live camera is waited for."""
    asked: list[tuple[str, int]] = []
    relevant: dict[str, frozenset[str] | None] = {"v": None}  # the warm-up: any camera

    def hook(robot_id: str, stamp_ns: int) -> frozenset[str] | None:
        asked.append((robot_id, stamp_ns))
        return relevant["v"]

    sync = FrameSetSynchronizer(SITE, relevant_cameras=hook)
    _warm(sync, T0)
    asked.clear()
    relevant["v"] = frozenset(CAMS[:2])
    t1 = T0 + 1000 * MS
    out = sync.push(det_msg(CAMS[0], t1, seq=1), t1 + 5 * MS)
    assert out == [] and asked == [(next(iter(SITE.robots)), t1)]
    out = sync.push(det_msg(CAMS[1], t1, seq=1), t1 + 6 * MS)
    assert len(out) == 1 and out[0].camera_ids == tuple(CAMS[:2])
    assert sync.counters["closed_early"] == 1
    late_before = sync.counters["late"]
    sync.push(det_msg(CAMS[2], t1, seq=1, seen=False), t1 + 7 * MS)
    sync.push(det_msg(CAMS[3], t1, seq=1), t1 + 8 * MS)
    assert sync.counters["after_close"] == 2 and sync.counters["late"] == late_before
    assert all(sync.camera_counters[c]["late"] == 0 for c in CAMS)
    # a relevant camera whose message comes after the close: late, as ever
    t2 = t1 + 66 * MS
    relevant["v"] = frozenset(CAMS[:2])
    out = sync.push(det_msg(CAMS[0], t2, seq=2), t2 + 5 * MS)
    out += sync.poll(t2 + 5 * MS + int(SITE.thresholds.sync_max_wait_ms * MS))
    assert len(out) == 1 and out[0].camera_ids == (CAMS[0],)
    sync.push(det_msg(CAMS[1], t2, seq=2), t2 + 200 * MS)
    assert sync.camera_counters[CAMS[1]]["late"] == 1
    # no relevant set: the window waits for every live camera
    t3 = t2 + 66 * MS
    relevant["v"] = None
    out = []
    for cam in CAMS[:3]:
        out += sync.push(det_msg(cam, t3, seq=3), t3 + 210 * MS)
    assert out == []
    out = sync.push(det_msg(CAMS[3], t3, seq=3), t3 + 211 * MS)
    assert len(out) == 1 and out[0].camera_ids == tuple(CAMS)
