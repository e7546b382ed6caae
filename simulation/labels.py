"""Training labels from a rendered image (numpy + OpenCV, no GL): keypoint pixels with their
visibility, and instance bounding boxes.

Pixel convention: OpenCV's, integer coordinates are pixel centres, (0, 0) the centre of the
top-left pixel; the same as :mod:`core.camera` and :mod:`simulation.render_gl`.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Final

import cv2
import numpy as np

from core.camera import CameraModel
from core.geometry import lens_fold_radius

if TYPE_CHECKING:
    from simulation.render_gl import RenderOutput

#: A keypoint counts as occluded only when everything rendered in the 3 x 3 pixels around its
#: pixel is closer to the camera (camera z) than the keypoint by more than this. Keypoints are
#: defined on the model's surface, but a mesh only approximates it (faceted cylinders, chamfered
#: edges, a keypoint on an edge seen at a grazing angle), which puts some of them a few cm behind
#: the rendered surface along the line of sight; 4 cm keeps those visible while real occluders
#: (people, boxes, furniture) stand well in front. Occluders closer than 4 cm in front of a
#: keypoint are not seen as occluding.
DEFAULT_DEPTH_TOLERANCE_M: Final = 0.04
#: Keypoints closer to the camera plane than this are "behind" (not projectable).
MIN_DEPTH_M: Final = 1e-6
#: Largest normalized radius (tan of the off-axis angle, ~87 deg) searched for a lens fold.


@dataclasses.dataclass(frozen=True, eq=False)
class KeypointLabels:
    """Labels of K keypoints in one image.

    ``pixels_px`` (K, 2) float64 raw distorted pixels (``cv2.projectPoints``; NaN for keypoints
    behind the camera); ``depth_m`` (K,) z in the camera optical frame, metres; ``in_image``
    (K,) bool: in front of the camera, inside the image (``CameraModel.in_image``) and where the
    lens really images it (see :func:`lens_fold_radius`); ``visible`` (K,) bool: in the image
    and not occluded.
    """

    pixels_px: np.ndarray
    depth_m: np.ndarray
    in_image: np.ndarray
    visible: np.ndarray


def project_points_cv(camera: CameraModel, points_world: np.ndarray) -> np.ndarray:
    """(N, 3) world points → (N, 2) distorted pixels exactly as ``cv2.projectPoints`` gives
    them (no check of the side of the camera)."""
    pts = np.ascontiguousarray(np.asarray(points_world, np.float64).reshape(-1, 1, 3))
    if len(pts) == 0:
        return np.zeros((0, 2))
    rvec, _ = cv2.Rodrigues(np.ascontiguousarray(camera.T_cam_world[:3, :3]))
    tvec = np.ascontiguousarray(camera.T_cam_world[:3, 3])
    dist = camera.dist if camera.dist.size else None
    uv, _ = cv2.projectPoints(pts, rvec, tvec, camera.K, dist)
    return uv.reshape(-1, 2).astype(np.float64)


def keypoint_labels(output: RenderOutput, camera: CameraModel, keypoints_world: np.ndarray,
                    depth_tolerance_m: float = DEFAULT_DEPTH_TOLERANCE_M) -> KeypointLabels:
    """Pixels and visibility of ``keypoints_world`` (K, 3) in the render ``output`` of
    ``camera``.

    A keypoint is visible when it is in the image (see :class:`KeypointLabels`) and, in the
    3 x 3 pixels around its pixel, some rendered depth (``np.inf`` where nothing was drawn) is
    ``>= depth - depth_tolerance_m``: the neighbourhood keeps keypoints on silhouette edges and
    on surfaces seen at grazing angles visible, the tolerance those slightly inside the mesh.
    """
    kp = np.asarray(keypoints_world, np.float64).reshape(-1, 3)
    if output.depth_m.shape != (camera.height, camera.width):
        raise ValueError(
            f"keypoint_labels: render is {output.depth_m.shape[::-1]}, camera "
            f"{camera.camera_id} {camera.width}x{camera.height}"
        )
    depth = camera.world_to_cam(kp)[:, 2]
    uv = project_points_cv(camera, kp)
    front = depth > MIN_DEPTH_M
    uv[~front] = np.nan
    in_image = front & camera.in_image(uv)
    if in_image.any():
        pts_cam = camera.world_to_cam(kp[in_image])
        r = np.hypot(pts_cam[:, 0], pts_cam[:, 1]) / pts_cam[:, 2]
        in_image[in_image] = r < lens_fold_radius(camera.dist)

    visible = np.zeros(len(kp), bool)
    idx = np.flatnonzero(in_image)
    if len(idx):
        iu = np.rint(uv[idx, 0]).astype(np.intp)
        iv = np.rint(uv[idx, 1]).astype(np.intp)
        h, w = output.depth_m.shape
        offsets = np.arange(-1, 2)
        rows = np.clip(iv[:, None, None] + offsets[None, :, None], 0, h - 1)
        cols = np.clip(iu[:, None, None] + offsets[None, None, :], 0, w - 1)
        around = output.depth_m[rows, cols].reshape(len(idx), 9)
        visible[idx] = np.any(around >= (depth[idx] - depth_tolerance_m)[:, None], axis=1)
    return KeypointLabels(uv, depth, in_image, visible)




def instance_bbox(output: RenderOutput, instance_id: int) -> np.ndarray | None:
    """Tight (4,) float64 box ``(x0, y0, x1, y1)`` around the pixels of ``instance_id``, or
    None when it has none.

    Box edges, not pixel centres: a single pixel (u, v) gives (u - 0.5, v - 0.5, u + 0.5,
    v + 0.5), so ``x1 - x0`` is the width in pixels.
    """
    mask = output.instance_id == instance_id
    cols = np.flatnonzero(mask.any(axis=0))
    if len(cols) == 0:
        return None
    rows = np.flatnonzero(mask.any(axis=1))
    return np.array([cols[0] - 0.5, rows[0] - 0.5, cols[-1] + 0.5, rows[-1] + 0.5])
