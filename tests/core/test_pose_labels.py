"""core.pose_labels: a robot's keypoints, visibility, box and expected pixel error in a camera's
image from its pose, checked on simple geometry and measured against the renderer's exact
labels of the paper lab (site views: the same cameras and the robot's built-in mesh)."""

from __future__ import annotations

import numpy as np
import pytest

from core.camera import CameraModel
from core.geometry import se3_from_planar
from core.pose_labels import hidden_by_surface, labels_from_pose


def _cube(half: float = 0.2, height: float = 0.4) -> np.ndarray:
    """(12, 3, 3) triangles of a box on the floor."""
    x = np.array([-half, half])
    v = np.array([[a, b, c] for a in x for b in x for c in (0.0, height)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return np.array([[v[a], v[b], v[c]] for q in quads for a, b, c in ((q[0], q[1], q[2]),
                                                                    (q[0], q[2], q[3]))])


def _camera_looking_at_origin_from(x: float) -> CameraModel:
    """A 640x480 camera at (x, 0, 0.2) looking along -x (at the origin for x > 0)."""
    R_world_cam = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    T_world_cam = np.eye(4)
    T_world_cam[:3, :3], T_world_cam[:3, 3] = R_world_cam, [x, 0.0, 0.2]
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    return CameraModel("c", 640, 480, K, np.zeros(5), np.linalg.inv(T_world_cam))


def test_the_far_side_is_hidden_and_the_box_is_the_cube() -> None:
    cam = _camera_looking_at_origin_from(3.0)
    # near face, far face, the near face's top edge, the side face's top edge (behind the
    # near face as seen from 0.2 m up)
    kps = np.array([[0.2, 0.0, 0.2], [-0.2, 0.0, 0.2], [0.2, 0.0, 0.4], [0.0, 0.2, 0.4]])
    lab = labels_from_pose(cam, kps, _cube(), np.eye(4))
    assert lab.in_image.all()
    assert lab.visible.tolist() == [True, False, True, False]
    np.testing.assert_allclose(lab.keypoints_px[0], [319.5, 239.5], atol=1e-9)
    # the near face (x = 0.2, 2.8 m away) is the widest: +-0.2 m -> +-35.7 px
    x0, y0, x1, y1 = lab.bbox_xyxy
    assert x0 == pytest.approx(319.5 - 500 * 0.2 / 2.8 - 0.5, abs=1e-6)
    assert x1 == pytest.approx(319.5 + 500 * 0.2 / 2.8 + 0.5, abs=1e-6)
    assert y0 == pytest.approx(239.5 - 500 * 0.2 / 2.8 - 0.5, abs=1e-6)  # top edge 0.2 m up
    assert y1 == pytest.approx(239.5 + 500 * 0.2 / 2.8 + 0.5, abs=1e-6)  # the floor
    assert (lab.sigma_px > 0).all()
    coco = lab.coco_keypoints()
    assert coco[:, 2].tolist() == [2, 1, 2, 1]
    behind = labels_from_pose(cam, kps, _cube(), se3_from_planar(10.0, 0.0, 0.0))
    assert not behind.in_image.any() and behind.bbox_xyxy is None


def test_hidden_by_surface_respects_the_tolerance() -> None:
    tri = np.array([[[1.0, -1, -1], [1.0, 1, 0], [1.0, -1, 1]]])  # a wall at x = 1
    origin = np.zeros(3)
    pts = np.array([[2.0, 0, 0], [1.02, 0, 0], [0.5, 0, 0], [2.0, 5.0, 0]])
    assert hidden_by_surface(origin, pts, tri, 0.04).tolist() == [True, False, False, False]


def test_against_the_renderer_s_exact_labels() -> None:
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from edge_agent.boxes import box_iou
    from simulation.dataset import SampleGenerator
    from simulation.robot_mesh import builtin_robot_mesh
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    model = scenario.site.robot_model(scenario.robot_id)
    mesh = builtin_robot_mesh(model)
    tri = mesh.vertices[mesh.faces].astype(np.float64)
    gen = SampleGenerator(scenario, "site", seed=11)
    rng = np.random.default_rng(0)
    noisy_err, ious, self_hidden_wrong, self_checked = [], [], 0, 0
    robots = 0
    for i in range(60):
        s = gen(i)
        r = s.robots[0]
        if r.bbox_xyxy is None:
            continue
        robots += 1
        exact = labels_from_pose(s.camera, model.keypoints_base_m, tri,
                                 se3_from_planar(*s.robot_pose))
        m = r.in_image & exact.in_image
        np.testing.assert_allclose(exact.keypoints_px[m], r.keypoints_px[m], atol=1e-6)
        assert (exact.in_image == r.in_image).mean() >= 0.98
        # a pose as good as the fused one (1 cm, 0.3 deg)
        pose = s.robot_pose + np.r_[rng.normal(0, 0.01, 2), rng.normal(0, np.radians(0.3))]
        lab = labels_from_pose(s.camera, model.keypoints_base_m, tri, se3_from_planar(*pose))
        seen = r.visible & lab.in_image
        noisy_err += list(np.linalg.norm(lab.keypoints_px[seen] - r.keypoints_px[seen], axis=1))
        foreign = exact.visible & ~r.visible & r.in_image  # hidden by people, furniture
        if not foreign.any() and lab.bbox_xyxy is not None:
            ious.append(box_iou(lab.bbox_xyxy, r.bbox_xyxy))
        self_checked += int((r.visible & r.in_image).sum())
        self_hidden_wrong += int((~exact.visible & r.visible & r.in_image).sum())
    noisy_err, ious = np.array(noisy_err), np.array(ious)
    print(f"{robots} robots: noisy-pose keypoint error median {np.median(noisy_err):.2f} px, "
          f"{100 * np.mean(noisy_err <= 3):.1f} % within 3 px; box IoU (no foreign occluder, "
          f"{len(ious)}) median {np.median(ious):.3f}, {100 * np.mean(ious >= 0.9):.0f} % >= 0.9;"
          f" visible keypoints labelled hidden {self_hidden_wrong}/{self_checked}")
    assert robots >= 20
    assert np.median(noisy_err) <= 1.0 and np.mean(noisy_err <= 3.0) >= 0.95
    assert np.median(ious) >= 0.9 and np.mean(ious >= 0.9) >= 0.9
    assert self_hidden_wrong <= 0.1 * self_checked
