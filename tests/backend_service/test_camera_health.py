"""A bumped camera is noticed: the camera-health monitor on synthetic views (the paper lab's
cameras, the robot's keypoints projected through the real camera models) and its settings."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from backend_service.camera_health import CameraHealthConfig, CameraHealthMonitor
from core.camera import CameraModel
from core.pose import PlanarPose
from core.site import Site, load_site
from protocol.errors import SiteConfigError
from simulation.detections import CameraBump

REPO = Path(__file__).resolve().parents[2]
SITE = REPO / "simulation" / "sites" / "paper_lab.yaml"
#: a bump of the issue's size: 5 cm, 1 deg (world axes; not along one axis)
BUMP_T = (0.03, 0.04, 0.0)
BUMP_R = (0.0, 0.6, 0.8)


@pytest.fixture(scope="module")
def site() -> Site:
    return load_site(SITE)


def _views(site: Site, true: list[CameraModel], pose: PlanarPose, rng: np.random.Generator,
           sigma_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints of the robot at ``pose`` through the true cameras: (kp_base, T, uv, w)."""
    kp = site.robot_model(None).keypoints_base_m
    T = pose.T()
    pts = kp @ T[:3, :3].T + T[:3, 3]
    uv = np.stack([c.project(pts)[0] for c in true])
    uv = uv + rng.normal(0.0, sigma_px, uv.shape)
    return kp, T, uv, np.ones(uv.shape[:2])


def _feed(monitor: CameraHealthMonitor, site: Site, camera_ids: list[str],
          bump: CameraBump | None, seconds: float, rng: np.random.Generator,
          sigma_px: float = 0.5, start_s: float = 0.0) -> None:
    """``seconds`` of frame-sets at 5 Hz, the robot somewhere in the middle of the lab."""
    cams = [site.cameras[c] for c in camera_ids]
    true = [bump.apply(c) if bump is not None and c.camera_id == bump.camera_id else c
            for c in cams]
    for i in range(round(seconds * 5)):
        pose = PlanarPose(rng.uniform(8.8, 11.2), rng.uniform(4.8, 7.2), rng.uniform(-3, 3))
        kp, T, uv, w = _views(site, true, pose, rng, sigma_px)
        stamp = round((start_s + i / 5) * 1e9)
        monitor.observe("hsr", stamp, cams, kp, T, uv, w)


def test_a_bumped_camera_is_named_with_its_offset(site: Site) -> None:
    monitor = CameraHealthMonitor(CameraHealthConfig())
    _feed(monitor, site, sorted(site.cameras), None, 20.0, np.random.default_rng(1))
    assert monitor.moved == {}
    bump = CameraBump("cam3", 0, BUMP_T, BUMP_R)
    _feed(monitor, site, sorted(site.cameras), bump, 40.0, np.random.default_rng(2),
          start_s=20.0)
    assert set(monitor.moved) == {"cam3"}
    moved = monitor.moved["cam3"]
    # named on a partial estimate (the evidence from before the bump still weighs)...
    assert moved.translation_m > 0.02 and moved.rotation_deg > 0.5
    assert monitor.excluded == {"cam3"}
    # ...which keeps improving while the camera is left out of the solve
    _feed(monitor, site, sorted(site.cameras), bump, 120.0, np.random.default_rng(12),
          start_s=60.0)
    state = monitor.state("cam3")
    assert state is not None
    assert state.translation_m == pytest.approx(0.05, abs=0.01)
    assert state.rotation_deg == pytest.approx(1.0, abs=0.1)
    assert monitor.problems() == [
        f"cam3 moved ~{state.translation_m * 100:.0f} cm / {state.rotation_deg:.1f} deg since "
        "calibration (left out of the solve until it is recalibrated)"]
    assert set(monitor.moved) == {"cam3"}
    # the estimate itself, axis by axis (rotation rad, position m; world axes)
    np.testing.assert_allclose(state.offset[:3], np.radians(BUMP_R), atol=math.radians(0.1))
    np.testing.assert_allclose(state.offset[3:], BUMP_T, atol=0.01)
    assert monitor.counters["moved.cam3"] == 1 and monitor.counters["moved"] == 1


def test_unmoved_cameras_are_not_named(site: Site) -> None:
    monitor = CameraHealthMonitor(CameraHealthConfig())
    _feed(monitor, site, sorted(site.cameras), None, 120.0, np.random.default_rng(3),
          sigma_px=1.0)
    assert monitor.moved == {} and monitor.excluded == frozenset()
    for cid in site.cameras:
        state = monitor.state(cid)
        assert state is not None and state.evidence_s > 100
        assert state.chi2 < CameraHealthConfig().alarm_chi2 / 2
        # zero within the estimate's own uncertainty (chi-square, 6 dof, 99.9 %)
        assert state.offset @ np.linalg.solve(state.covariance, state.offset) < 22.5
        assert state.rotation_deg < 0.1


def test_one_camera_judges_nothing(site: Site) -> None:
    """With only one camera seeing the robot there is nothing to compare it with."""
    monitor = CameraHealthMonitor(CameraHealthConfig())
    bump = CameraBump("cam3", 0, BUMP_T, BUMP_R)
    _feed(monitor, site, ["cam3"], bump, 60.0, np.random.default_rng(4))
    assert monitor.moved == {}
    assert monitor.state("cam3") is None and monitor.counters["judged"] == 0


def test_which_of_two_cameras_moved_needs_a_third(site: Site) -> None:
    """Two cameras that disagree cannot say which of them moved; with ``min_other_cameras:
    2`` such frame-sets are not judged. With the default (1) they are, and the frame-sets in
    which each camera pairs with others tell the joint estimate which one moved."""
    strict = CameraHealthMonitor(CameraHealthConfig(min_other_cameras=2))
    bump = CameraBump("cam3", 0, BUMP_T, BUMP_R)
    _feed(strict, site, ["cam2", "cam3"], bump, 60.0, np.random.default_rng(4))
    assert strict.moved == {} and strict.counters["judged"] == 0
    monitor = CameraHealthMonitor(CameraHealthConfig())
    rng = np.random.default_rng(11)
    for k, pair in enumerate([("cam1", "cam2"), ("cam2", "cam3"), ("cam3", "cam4"),
                              ("cam1", "cam4")] * 4):
        _feed(monitor, site, list(pair), bump, 5.0, rng, start_s=5.0 * k)
    assert set(monitor.moved) == {"cam3"}


def test_report_only_keeps_the_camera_and_clears_with_hysteresis(site: Site) -> None:
    config = CameraHealthConfig(action="report", forgetting_s=10.0)
    monitor = CameraHealthMonitor(config)
    bump = CameraBump("cam1", 0, BUMP_T, BUMP_R)
    _feed(monitor, site, sorted(site.cameras), bump, 30.0, np.random.default_rng(5))
    assert set(monitor.moved) == {"cam1"}
    assert monitor.excluded == frozenset()  # reported, still in the solve
    assert "left out" not in monitor.problems()[0]
    # put back where it was: the evidence forgets the bump and the verdict clears
    _feed(monitor, site, sorted(site.cameras), None, 80.0, np.random.default_rng(6),
          start_s=30.0)
    assert monitor.moved == {}
    assert monitor.counters["cleared"] == 1


def test_a_recalibrated_camera_starts_afresh(site: Site) -> None:
    monitor = CameraHealthMonitor(CameraHealthConfig())
    bump = CameraBump("cam3", 0, BUMP_T, BUMP_R)
    _feed(monitor, site, sorted(site.cameras), bump, 30.0, np.random.default_rng(7))
    assert monitor.excluded == {"cam3"}
    monitor.check_calibration(site.cameras)  # the same calibration: nothing changes
    assert monitor.excluded == {"cam3"}
    recalibrated = dict(site.cameras, cam3=bump.apply(site.cameras["cam3"]))
    monitor.check_calibration(recalibrated)
    assert monitor.excluded == frozenset() and monitor.state("cam3") is None
    assert monitor.counters["recalibrated"] == 1
    # judged against its new calibration, the moved camera is healthy; the others too
    new_site_cams = [recalibrated[c] for c in sorted(recalibrated)]
    rng = np.random.default_rng(8)
    for i in range(150):
        pose = PlanarPose(rng.uniform(8.8, 11.2), rng.uniform(4.8, 7.2), rng.uniform(-3, 3))
        kp, T, uv, w = _views(site, new_site_cams, pose, rng, 0.5)
        monitor.observe("hsr", round((40 + i / 5) * 1e9), new_site_cams, kp, T, uv, w)
    assert monitor.moved == {}
    state = monitor.state("cam3")
    assert state is not None and state.rotation_deg < 0.3
    assert state.chi2 < CameraHealthConfig().clear_chi2


def test_reset_forgets(site: Site) -> None:
    monitor = CameraHealthMonitor(CameraHealthConfig())
    bump = CameraBump("cam2", 0, BUMP_T, BUMP_R)
    _feed(monitor, site, sorted(site.cameras), bump, 30.0, np.random.default_rng(9))
    assert set(monitor.moved) == {"cam2"}
    monitor.reset("cam2")
    assert monitor.moved == {} and monitor.state("cam2") is None
    assert monitor.state("cam1") is not None  # the others keep what they learnt
    monitor.reset()
    assert all(monitor.state(c) is None for c in site.cameras)


def test_bad_input_never_crashes_or_poisons(site: Site) -> None:
    monitor = CameraHealthMonitor(CameraHealthConfig())
    cams = [site.cameras[c] for c in sorted(site.cameras)]
    rng = np.random.default_rng(10)
    kp, T, uv, w = _views(site, cams, PlanarPose(10.0, 6.0, 0.3), rng, 0.5)
    bad_uv = uv.copy()
    bad_uv[0, :4] = np.nan
    bad_uv[1, 2] = np.inf
    bad_w = w.copy()
    bad_w[2, 0] = np.nan
    bad_w[3, 1] = -5.0
    monitor.observe("hsr", 1, cams, kp, T, bad_uv, bad_w)  # bad keypoints: left out
    nan_T = T.copy()
    nan_T[0, 3] = np.nan
    garbage = [
        (cams, kp, nan_T, uv, w),  # a non-finite pose
        (cams, kp, T, uv[:, :5], w),  # wrong shapes
        (cams, kp, T, uv, w[:2]),
        (cams, kp[:, :2], T, uv, w),
        (cams, kp, T[:3], uv, w),
        (cams, kp, T, np.full_like(uv, 1e300), w),  # absurd pixels
        (cams, kp, T, uv, np.zeros_like(w)),  # nothing usable
        (cams, kp, T, "not an array", w),
        (cams, kp, T, uv, np.full_like(w, 1e300)),
    ]
    for i, args in enumerate(garbage):
        assert monitor.observe("hsr", 2 + i, *args) == []  # type: ignore[arg-type]
    assert monitor.counters["skipped"] >= 4
    for cid in site.cameras:
        state = monitor.state(cid)
        assert state is None or (np.all(np.isfinite(state.offset))
                                 and np.all(np.isfinite(state.covariance)))
    # and the monitor still works afterwards
    bump = CameraBump("cam4", 0, BUMP_T, BUMP_R)
    _feed(monitor, site, sorted(site.cameras), bump, 30.0, rng, start_s=10.0)
    assert set(monitor.moved) == {"cam4"}


def _site_with(tmp_path: Path, **sections: object) -> Site:
    doc = yaml.safe_load(SITE.read_text())
    doc.update(sections)
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(doc))
    return load_site(path)


def test_settings_come_from_the_site_file(tmp_path: Path) -> None:
    site = _site_with(tmp_path, camera_health={"alarm_chi2": 40.0, "action": "report",
                                               "min_other_cameras": 3})
    config = CameraHealthConfig.from_site(site)
    assert config.alarm_chi2 == 40.0 and config.action == "report"
    assert config.min_other_cameras == 3
    assert CameraHealthConfig.from_site(load_site(SITE)) == CameraHealthConfig()


@pytest.mark.parametrize(
    ("section", "key"),
    [
        ({"alarm_chi": 40.0}, "camera_health.alarm_chi"),
        ({"tolerance_m": -0.1}, "camera_health.tolerance_m"),
        ({"action": "drop"}, "camera_health"),
        ({"min_other_cameras": 0}, "camera_health.min_other_cameras"),
        ({"enabled": "yes"}, "camera_health.enabled"),
        ({"clear_chi2": 50.0}, "camera_health"),
    ],
)
def test_bad_settings_name_the_key(tmp_path: Path, section: dict, key: str) -> None:
    site = _site_with(tmp_path, camera_health=section)
    with pytest.raises(SiteConfigError) as err:
        CameraHealthConfig.from_site(site)
    assert f": {key}" in str(err.value)
    assert str(tmp_path / "site.yaml") in str(err.value)


def _creep(monitor: CameraHealthMonitor, site: Site, bias_px: np.ndarray, seconds: float,
           rng: np.random.Generator) -> None:
    """A robot creeping 1 cm/s (5 Hz frame-sets), cam3's keypoints off by a fixed pattern
    ``bias_px`` (M, 2): a detector's error that belongs to the view, not to the frame."""
    cams = [site.cameras[c] for c in sorted(site.cameras)]
    i3 = sorted(site.cameras).index("cam3")
    for i in range(round(seconds * 5)):
        pose = PlanarPose(9.5 + 0.002 * i, 6.0, 0.3)
        kp, T, uv, w = _views(site, cams, pose, rng, 0.3)
        uv[i3] += bias_px
        monitor.observe("hsr", round(i / 5 * 1e9), cams, kp, T, uv, w)


def test_a_view_repeated_is_not_evidence_repeated(site: Site) -> None:
    """A CNN's keypoint error depends on the view: frames of a standing or creeping robot repeat
    it. Counted as independent frames, that error names an unmoved camera moved (as it did in
    the closed-loop demo); counted by how far the robot moved, it does not."""
    n_kp = len(site.robot_model(None).keypoints_base_m)
    bias = np.random.default_rng(5).normal(0.0, 2.0, (n_kp, 2))
    every_frame = CameraHealthMonitor(CameraHealthConfig(
        independent_motion_m=1e-6, independent_turn_deg=1e-6))
    _creep(every_frame, site, bias, 60.0, np.random.default_rng(6))
    assert "cam3" in every_frame.moved  # the failure this guards against
    by_motion = CameraHealthMonitor(CameraHealthConfig())
    _creep(by_motion, site, bias, 60.0, np.random.default_rng(6))
    assert by_motion.moved == {}
    state = by_motion.state("cam3")
    assert state is not None and state.evidence_s < 5.0  # 0.6 m of creeping: ~2.4 views
    # a standing robot adds nothing
    standing = CameraHealthMonitor(CameraHealthConfig())
    cams = [site.cameras[c] for c in sorted(site.cameras)]
    rng = np.random.default_rng(7)
    for i in range(50):
        kp, T, uv, w = _views(site, cams, PlanarPose(10.0, 6.0, 0.0), rng, 0.5)
        standing.observe("hsr", round(i / 5 * 1e9), cams, kp, T, uv, w)
    assert standing.counters["judged"] == 1
    assert standing.counters["skipped.same_view"] == 49


def _feed_with_gross_keypoints(monitor: CameraHealthMonitor, site: Site, camera_id: str,
                               bump: CameraBump | None, seconds: float,
                               rng: np.random.Generator, start_s: float = 0.0) -> None:
    """As :func:`_feed` (every camera, 5 Hz), but in ``camera_id``'s view the three bottom
    keypoints of the side facing away sit 30-60 px too low in every frame: what a keypoint
    network does with occluded bottom keypoints next to an obstacle's edge."""
    cams = [site.cameras[c] for c in sorted(site.cameras)]
    true = [bump.apply(c) if bump is not None and c.camera_id == bump.camera_id else c
            for c in cams]
    k = [c.camera_id for c in cams].index(camera_id)
    for i in range(round(seconds * 5)):
        pose = PlanarPose(rng.uniform(8.8, 11.2), rng.uniform(4.8, 7.2), rng.uniform(-3, 3))
        kp, T, uv, w = _views(site, true, pose, rng, 0.7)
        uv[k, -3:, 1] += rng.uniform(30.0, 60.0, 3)
        monitor.observe("hsr", round((start_s + i / 5) * 1e9), cams, kp, T, uv, w)


def test_gross_keypoint_errors_do_not_name_an_unmoved_camera(site: Site) -> None:
    """A few keypoints tens of pixels off in one view, frame after frame, are wrong keypoints
    (left out and counted), not evidence that the camera moved; a bump of that camera is
    still named, with its offset, through the same outliers."""
    monitor = CameraHealthMonitor(CameraHealthConfig())
    _feed_with_gross_keypoints(monitor, site, "cam3", None, 120.0, np.random.default_rng(21))
    assert monitor.moved == {}, monitor.problems()
    state = monitor.state("cam3")
    assert state is not None and state.evidence_s > 100
    assert state.translation_m < 0.02 and state.rotation_deg < 0.2
    assert monitor.counters["outlier_keypoints"] >= 3 * 500
    assert monitor.counters["inconsistent_views"] == 0
    bump = CameraBump("cam3", 0, BUMP_T, BUMP_R)
    _feed_with_gross_keypoints(monitor, site, "cam3", bump, 120.0, np.random.default_rng(22),
                               start_s=120.0)
    assert set(monitor.moved) == {"cam3"}
    _feed_with_gross_keypoints(monitor, site, "cam3", bump, 120.0, np.random.default_rng(23),
                               start_s=240.0)
    state = monitor.state("cam3")
    assert state.translation_m == pytest.approx(0.05, abs=0.015)
    assert state.rotation_deg == pytest.approx(1.0, abs=0.15)


def test_a_view_left_with_too_few_consistent_keypoints_is_not_judged(site: Site) -> None:
    """A view whose keypoints scatter (a robot cut by the image border, a detection of
    something else) adds nothing: counted ``inconsistent_views``."""
    monitor = CameraHealthMonitor(CameraHealthConfig())
    cams = [site.cameras[c] for c in sorted(site.cameras)]
    rng = np.random.default_rng(24)
    for i in range(200):
        pose = PlanarPose(rng.uniform(8.8, 11.2), rng.uniform(4.8, 7.2), rng.uniform(-3, 3))
        kp, T, uv, w = _views(site, cams, pose, rng, 0.7)
        uv[0] += rng.uniform(-70.0, 70.0, uv[0].shape)
        monitor.observe("hsr", round(i / 5 * 1e9), cams, kp, T, uv, w)
    assert monitor.moved == {}
    assert monitor.counters["inconsistent_views"] >= 150
    first = monitor.state(cams[0].camera_id)
    assert first is None or first.evidence_s == 0.0
