"""The Rerun view: target parsing and a recording that rerun's own tooling reads."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from protocol.messages import (
    Detection,
    PoseEstimate,
    RobotDetections,
    SemanticCloud,
    ServiceStatus,
)

rr_view = pytest.importorskip("smartedge.viewer.rerun_view")


@pytest.mark.parametrize(
    ("spec", "kind", "arg"),
    [
        ("save:out/x.rrd", "save", "out/x.rrd"),
        ("spawn", "spawn", ""),
        ("connect", "connect", ""),
        ("connect:rerun+http://10.0.0.2:9876/proxy", "connect", "rerun+http://10.0.0.2:9876/proxy"),
        ("serve", "serve", ""),
        ("none", "none", ""),
    ],
)
def test_targets_parse(spec: str, kind: str, arg: str) -> None:
    target = rr_view.RerunTarget.parse(spec)
    assert (target.kind, target.arg) == (kind, arg)


@pytest.mark.parametrize("spec", ["save:", "file:x.rrd", "spawn:now", ""])
def test_bad_targets_are_clear_errors(spec: str) -> None:
    with pytest.raises(ValueError, match="--rerun"):
        rr_view.RerunTarget.parse(spec)


def test_saved_recording_verifies_and_holds_the_entities(tmp_path: Path, example_site) -> None:
    path = tmp_path / "view.rrd"
    view = rr_view.RerunView(example_site, rr_view.RerunTarget.parse(f"save:{path}"))
    det = Detection(
        np.array([1.0, 2, 30, 40]), 0.9, np.random.rand(12, 2) * 100, np.random.rand(12)
    )
    t = 1_700_000_000_000_000_000
    view.detections(RobotDetections("cam_sw", t, 0, 848, 480, "m", (det,)))
    cov = np.eye(3) * 1e-4
    view.pose(PoseEstimate("hsr", t, 0, 10.0, 6.0, 0.3, cov, "cameras", ("cam_sw",), 1.2))
    view.pose(PoseEstimate("hsr", t + 5, 0, 10.1, 6.0, 0.3, cov, "fused"))
    view.error("hsr", t, "camera", 0.02)
    view.status(ServiceStatus("backend", "main", t, 0, counters={"invalid": 1}))
    view.close()
    assert not view._failed
    rerun = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    verify = subprocess.run(
        [rerun, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120
    )
    assert verify.returncode == 0, verify.stderr[-1000:]
    stats = subprocess.run(
        [rerun, "rrd", "stats", str(path)], capture_output=True, text=True, timeout=120
    ).stdout
    for entity in (
        "/world/cameras/cam_sw/image",
        "/world/cameras/cam_sw/image/keypoints",
        "/world/robots/hsr/camera_keypoints",
        "/world/robots/hsr/fused/body",
        "/metrics/hsr/error_cm/camera",
        "/status/backend/main",
    ):
        assert f"{entity}:" in stats, entity


def _rerun_stats(path: Path) -> str:
    proc = subprocess.run([str(rr_view.rerun_cli()), "rrd", "stats", str(path)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-1000:]
    return proc.stdout + proc.stderr


def test_recording_holds_blueprint_scene_trails_and_reprojections_compactly(
        tmp_path: Path, example_site) -> None:
    """A saved recording carries the layout, the floor plan and obstacles, trails logged one
    segment at a time, the estimate projected back into the cameras that see it, and is
    compacted on close (no 'unoptimized' warning from rerun's own tooling)."""
    path = tmp_path / "view.rrd"
    box = rr_view.ObstacleBox("table", (9.0, 5.0, 0.4), (1.2, 0.8, 0.8), 0.3)
    scene = rr_view.StaticScene((0.0, 0.0), (14.0, 10.0), 3.0, (box,))
    view = rr_view.RerunView(example_site, rr_view.RerunTarget.parse(f"save:{path}"),
                             scene=scene)
    cov = np.diag([1e-4, 4e-4, 1e-4])
    t0 = 1_700_000_000_000_000_000
    logged: list[int] = []
    original = view.rec.log

    def spy(entity: str, *args, **kwargs):
        if entity == "world/trajectories/hsr/fused" and not kwargs.get("static"):
            strips = args[0].strips.as_arrow_array()  # one segment per row, never the trail
            logged.append(len(strips[0]))
        return original(entity, *args, **kwargs)

    view.rec.log = spy
    for i in range(400):  # 4 m at 1 cm a step: a trail point every 2 cm
        t = t0 + i * 50_000_000
        view.pose(PoseEstimate("hsr", t, i, 8.0 + 0.01 * i, 5.0, 0.0, cov, "fused"))
        if i % 3 == 0:
            view.pose(PoseEstimate("hsr", t, i, 8.0 + 0.01 * i, 5.02, 0.01, cov, "cameras",
                                   ("cam_sw",), 0.8))
    view.correction("hsr", t0 + 10_000_000_000, 10.0, 5.0, 0.1)
    view.close()
    assert not view._failed
    # 4 m with a point every 2-3 cm (float steps of 1 cm land on either side of 2 cm)
    assert 133 <= len(logged) <= 200 and set(logged) == {2}
    stats = _rerun_stats(path)
    assert "unoptimized" not in stats
    for entity in ("/world/site/floor_plan", "/world/site/obstacles", "/world/site/floor",
                   "/world/trajectories/hsr/fused", "/world/trajectories/hsr/camera",
                   "/world/robots/hsr/covariance/fused", "/world/robots/hsr/corrections",
                   "/world/cameras/cam_sw/image/reprojection",
                   "/world/cameras/cam_sw/image/bounds", "/viewport"):
        assert f"{entity}:" in stats, entity
    assert "/container/" in stats and "/view/" in stats  # the blueprint's own entities


def test_reprojection_lands_on_the_true_keypoints(example_site) -> None:
    """The estimate drawn back into a camera is the model's keypoints through that camera's
    calibration: at the true pose it falls on the true pixels."""
    view = rr_view.RerunView(example_site, rr_view.RerunTarget("none"))
    drawn: dict[str, np.ndarray] = {}
    view.rec.log = lambda entity, *args, **kw: drawn.__setitem__(entity, args[0])
    model = example_site.robot_model("hsr")
    pose = (9.1, 5.1, 0.4)
    pts = model.keypoints_base_m @ rr_view.rotation_z(pose[2]).T + [pose[0], pose[1], 0.0]
    view._reproject(pts)
    cam = example_site.camera("cam_sw")
    uv, _ = cam.project(pts)
    got = drawn["world/cameras/cam_sw/image/reprojection"].positions.as_arrow_array()
    np.testing.assert_allclose(np.asarray(got.to_pylist()), uv[cam.in_image(uv)], atol=1e-3)


@pytest.mark.parametrize(("cov", "axes"), [
    (np.diag([0.04, 0.01, 0.0]), (0.4, 0.2)),  # 2 sigma of 0.2 m and 0.1 m
    (np.diag([0.01, 0.01, 1.0]), (0.2, 0.2)),
])
def test_covariance_ellipse_has_two_sigma_axes(cov: np.ndarray, axes: tuple) -> None:
    ring = rr_view.covariance_ellipse(1.0, 2.0, cov)
    r = np.linalg.norm(ring[:, :2] - [1.0, 2.0], axis=1)
    assert r.max() == pytest.approx(max(axes), rel=1e-3)
    assert r.min() == pytest.approx(min(axes), rel=2e-2)
    assert rr_view.covariance_ellipse(0, 0, np.full((3, 3), np.nan)) is None
    assert rr_view.covariance_ellipse(0, 0, -np.eye(3)) is None


def test_semantic_map_is_drawn_by_class_with_the_legend_and_throttled(
        tmp_path: Path, example_site) -> None:
    """The mapper's voxels appear as points with class ids (coloured through the legend's
    annotation context); a second map within the drawing period is not logged again."""
    path = tmp_path / "map.rrd"
    view = rr_view.RerunView(example_site, rr_view.RerunTarget.parse(f"save:{path}"))
    logged: list[tuple[str, object]] = []
    original = view.rec.log

    def spy(entity: str, *args, **kwargs):
        logged.append((entity, args[0]))
        return original(entity, *args, **kwargs)

    view.rec.log = spy
    n = 500
    t0 = 1_700_000_000_000_000_000
    msg = SemanticCloud("main", t0, 0, "map", np.random.default_rng(0).random((n, 3), np.float32),
                        np.full(n, 2, np.uint16), np.full(n, 0.9, np.float32))
    view.semantic_map(msg)
    view.semantic_map(SemanticCloud("main", t0 + 1_000_000_000, 1, "map", msg.points_xyz,
                                    msg.class_ids, msg.confidences))
    view.close()
    drawn = [obj for entity, obj in logged if entity.startswith("world/map/voxels/")]
    assert len(drawn) == 1  # all points in one 1 m tile, drawn once
    assert drawn[0].class_ids.as_arrow_array().to_pylist() == [2] * n
    stats = _rerun_stats(path)
    assert "/world/map/voxels/x0_y0:" in stats and "/world/map:" in stats  # points and legend
    assert view._failed == set(), view._failed
