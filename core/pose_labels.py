"""A robot's image labels from its pose: where its keypoints and its box are in a camera's image
when the robot stands at a known pose, what its own body hides, and how sure that is.

The system knows where the robot is (its fused pose); through a calibrated camera it can label
its own frames. :func:`labels_from_pose` takes the camera (intrinsics, OpenCV distortion,
``T_world_cam``), the robot model's keypoints and the robot's surface as triangles (both in the
robot's base frame), and ``T_world_base``:

- keypoints: projected with the camera's model (:meth:`core.camera.CameraModel.project`);
  ``in_image`` in front of the camera, inside the image and where the lens really images them
  (:func:`core.geometry.lens_fold_radius`);
- visibility: a keypoint is hidden when the ray from the camera's centre to it crosses the
  robot's own surface more than ``occlusion_tolerance_m`` before it (Moller-Trumbore against
  every triangle; keypoints sit on the real surface, a mesh only approximates it, as
  :data:`simulation.labels.DEFAULT_DEPTH_TOLERANCE_M` explains for rendered labels). Other
  objects (people, furniture) are not known here: a labeller checks those against the frame;
- box: the projected surface's extent (its vertices in front of the camera), clipped to the
  image, in box-edge coordinates as rendered labels use (a pixel ``(u, v)`` spans
  ``u - 0.5 .. u + 0.5``); ``None`` when nothing of it is in the image;
- ``sigma_px`` per keypoint: how far it moves in the image for a pose off by the stated
  ``pose_sigma`` (x, y in metres, yaw in radians, each alone, root of the summed squares).

Pure numpy. The triangles come from wherever the robot's shape is kept (the simulation's robot
meshes today).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Final

import numpy as np

from core.camera import CameraModel
from core.geometry import lens_fold_radius, se3_from_planar

#: the default tolerance of the self-occlusion test (metres along the ray)
OCCLUSION_TOLERANCE_M: Final = 0.04
#: the default pose uncertainty behind ``sigma_px``: x, y (m), yaw (rad)
POSE_SIGMA: Final = (0.01, 0.01, math.radians(0.3))
#: surface points closer to the camera plane than this do not count for the box (m)
_MIN_DEPTH_M: Final = 0.05


@dataclasses.dataclass(frozen=True, eq=False)
class PoseLabels:
    """Labels of one robot in one image: ``keypoints_px`` (K, 2) (NaN where behind the
    camera), ``in_image`` and ``visible`` (K,) bool, ``bbox_xyxy`` (4,) box edges or ``None``,
    ``sigma_px`` (K,) expected pixel error for the stated pose uncertainty."""

    keypoints_px: np.ndarray
    in_image: np.ndarray
    visible: np.ndarray
    bbox_xyxy: np.ndarray | None
    sigma_px: np.ndarray

    def coco_keypoints(self) -> np.ndarray:
        """(K, 3) (u, v, visibility) as COCO writes them: 2 visible, 1 in the image but hidden,
        0 not in the image (u, v 0)."""
        vis = np.where(self.visible, 2, np.where(self.in_image, 1, 0))
        uv = np.where(vis[:, None] > 0, self.keypoints_px, 0.0)
        return np.column_stack([uv, vis]).astype(np.float64)


def _transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def _project(camera: CameraModel, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(pixels (N, 2), in_image (N,)) with the lens-fold check."""
    pts_cam = camera.world_to_cam(points_world)
    front = pts_cam[:, 2] > 1e-6
    uv = np.full((len(points_world), 2), np.nan)
    if front.any():
        uv[front] = camera.project_cam(pts_cam[front])
    inside = front & camera.in_image(uv)
    if inside.any():
        r = np.hypot(pts_cam[inside, 0], pts_cam[inside, 1]) / pts_cam[inside, 2]
        inside[inside] = r < lens_fold_radius(camera.dist)
    return uv, inside


def hidden_by_surface(origin: np.ndarray, points: np.ndarray, triangles: np.ndarray,
                      tolerance_m: float) -> np.ndarray:
    """(N,) bool: the segment from ``origin`` (3,) to each of ``points`` (N, 3) crosses one of
    ``triangles`` (F, 3, 3) more than ``tolerance_m`` before the point (Moller-Trumbore, both
    faces)."""
    if len(points) == 0 or len(triangles) == 0:
        return np.zeros(len(points), bool)
    d = points - origin  # (N, 3)
    length = np.linalg.norm(d, axis=1)
    v0 = triangles[:, 0]
    e1, e2 = triangles[:, 1] - v0, triangles[:, 2] - v0  # (F, 3)
    s = origin - v0  # (F, 3)
    p = np.cross(d[:, None, :], e2[None, :, :])  # (N, F, 3)
    det = np.einsum("nfk,fk->nf", p, e1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    u = np.einsum("nfk,fk->nf", p, s) * inv
    q = np.cross(s, e1)  # (F, 3)
    v = np.einsum("nk,fk->nf", d, q) * inv
    t = np.einsum("fk,fk->f", e2, q)[None, :] * inv  # fraction of the segment
    limit = (1.0 - tolerance_m / np.maximum(length, 1e-9))[:, None]
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t < limit)
    return hit.any(axis=1)


def labels_from_pose(camera: CameraModel, keypoints_base_m: np.ndarray,
                     triangles_base_m: np.ndarray, T_world_base: np.ndarray, *,
                     occlusion_tolerance_m: float = OCCLUSION_TOLERANCE_M,
                     pose_sigma: Sequence[float] = POSE_SIGMA) -> PoseLabels:
    """The labels of the robot at ``T_world_base`` (4, 4) in ``camera``'s image (module
    docstring). ``keypoints_base_m`` (K, 3), ``triangles_base_m`` (F, 3, 3), base frame."""
    kp_base = np.asarray(keypoints_base_m, np.float64).reshape(-1, 3)
    tri_base = np.asarray(triangles_base_m, np.float64).reshape(-1, 3, 3)
    T = np.asarray(T_world_base, np.float64)
    kp_world = _transform(T, kp_base)
    uv, in_image = _project(camera, kp_world)
    visible = in_image.copy()
    if visible.any():
        tri_world = _transform(T, tri_base.reshape(-1, 3)).reshape(-1, 3, 3)
        visible[visible] = ~hidden_by_surface(camera.position_world, kp_world[visible],
                                              tri_world, occlusion_tolerance_m)
    # the box: the surface's vertices in front of the camera, projected, clipped to the image
    verts = np.unique(_transform(T, tri_base.reshape(-1, 3)), axis=0)
    depth = camera.world_to_cam(verts)[:, 2]
    box = None
    front = verts[depth > _MIN_DEPTH_M]
    if len(front):
        pix = camera.project_cam(camera.world_to_cam(front))
        x0, y0 = np.nanmin(pix, axis=0) - 0.5
        x1, y1 = np.nanmax(pix, axis=0) + 0.5
        x0, y0 = max(x0, -0.5), max(y0, -0.5)
        x1, y1 = min(x1, camera.width - 0.5), min(y1, camera.height - 0.5)
        if x1 > x0 and y1 > y0:
            box = np.array([x0, y0, x1, y1])
    # sigma: the keypoints' image motion for a pose off by each sigma alone
    yaw = math.atan2(T[1, 0], T[0, 0])
    base = np.array([T[0, 3], T[1, 3], yaw])
    shift2 = np.zeros(len(kp_base))
    for axis, sigma in enumerate(pose_sigma):
        moved = base.copy()
        moved[axis] += float(sigma)
        Tm = se3_from_planar(*moved)
        Tm[2, 3] = T[2, 3]
        uv_m, _ = _project(camera, _transform(Tm, kp_base))
        shift2 += np.nan_to_num(np.sum((uv_m - uv) ** 2, axis=1), nan=np.inf)
    return PoseLabels(uv, in_image, visible, box, np.sqrt(shift2))


__all__ = ["OCCLUSION_TOLERANCE_M", "POSE_SIGMA", "PoseLabels", "hidden_by_surface",
           "labels_from_pose"]
