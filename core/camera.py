"""Pinhole camera with OpenCV lens distortion, in plain numpy (no OpenCV on this path); the
distortion model and transform helpers are those of :mod:`core.geometry`.

Frames: ``T_cam_world`` maps world coordinates to the camera's optical frame (OpenCV
convention: z forward along the optical axis, x right, y down). Pixels: (u, v) with the origin at
the top-left corner of the image.
"""

from __future__ import annotations

import dataclasses
from typing import Final

import numpy as np

from core.geometry import distort_normalized, invert_transform
from protocol.validation import check_array, check_id, check_int

#: Distortion vector lengths OpenCV understands: (k1, k2, p1, p2[, k3[, k4, k5, k6]]).
DISTORTION_LENGTHS: Final = (0, 4, 5, 8)


@dataclasses.dataclass(frozen=True, eq=False)
class CameraModel:
    """A calibrated static camera of the site.

    ``K``: (3, 3) intrinsics in pixels. ``dist``: OpenCV distortion coefficients (0, 4, 5 or 8).
    ``T_cam_world``: (4, 4) world → camera optical frame. ``clock_offset_ns``: added to this
    camera's stamps to bring them onto the site's common clock.
    """

    camera_id: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    T_cam_world: np.ndarray
    clock_offset_ns: int = 0

    def __post_init__(self) -> None:
        check_id("camera_id", self.camera_id)
        check_int("width", self.width, lo=1, hi=65535)
        check_int("height", self.height, lo=1, hi=65535)
        object.__setattr__(
            self, "K", check_array("K", self.K, dtypes=("float64",), shape=(3, 3)).copy()
        )
        dist = check_array(
            "dist", np.asarray(self.dist, dtype=np.float64), dtypes=("float64",), shape=(None,)
        )
        if dist.size not in DISTORTION_LENGTHS:
            from protocol.errors import ValidationError

            raise ValidationError("dist", f"length {dist.size} not in {DISTORTION_LENGTHS}")
        object.__setattr__(self, "dist", dist)
        T = check_array("T_cam_world", self.T_cam_world, dtypes=("float64",), shape=(4, 4))
        object.__setattr__(self, "T_cam_world", T)
        for arr in (self.K, self.dist, self.T_cam_world):
            arr.setflags(write=False)

    @property
    def T_world_cam(self) -> np.ndarray:
        """(4, 4) camera optical frame → world."""
        return invert_transform(self.T_cam_world)

    @property
    def position_world(self) -> np.ndarray:
        """(3,) optical centre in world coordinates, metres."""
        return self.T_world_cam[:3, 3]

    @property
    def optical_axis_world(self) -> np.ndarray:
        """(3,) unit viewing direction (camera z axis) in world coordinates."""
        return self.T_cam_world[2, :3].copy()

    def world_to_cam(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world points → (N, 3) points in the camera optical frame."""
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        return pts @ self.T_cam_world[:3, :3].T + self.T_cam_world[:3, 3]

    def project_cam(self, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points → (N, 2) distorted pixels. Points behind give NaN."""
        pts = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        z = pts[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = pts[:, :2] / z[:, None]
        xy[z <= 1e-9] = np.nan
        xy = distort_normalized(xy, self.dist)
        uv = xy @ self.K[:2, :2].T + self.K[:2, 2]
        return uv

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) world points → ((N, 2) pixels, (N,) depth along the optical axis in metres)."""
        pts_cam = self.world_to_cam(points_world)
        return self.project_cam(pts_cam), pts_cam[:, 2]

    def in_image(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """(N,) bool: pixel lies inside the image (with a margin), NaN counts as outside."""
        u, v = uv[:, 0], uv[:, 1]
        with np.errstate(invalid="ignore"):
            return (
                (u >= margin_px)
                & (u <= self.width - 1 - margin_px)
                & (v >= margin_px)
                & (v <= self.height - 1 - margin_px)
            )
