"""The far band: the rows of a static camera's frame where far robots appear, which the detector
runs a second time at twice its whole-frame scale.

The detector sees the whole frame at half resolution (848x480 → 424x240). Up to about 8 m from
the camera that finds every robot with three or more keypoints in view; beyond, a robot is
under ~25 px tall in the detector's input and recall falls (0.61-0.92 at 10-14 m on the paper
lab's site views; docs/models.md). A static camera's calibration says where those robots can
be: standing on the floor (world z = 0) at a camera depth of :data:`FAR_MIN_DEPTH_M` or more,
they fill a band of rows near the top of a downward-looking camera's frame. The detector runs
on that band at twice its scale (full resolution for an 848x480 camera) and its boxes join the
whole frame's (:meth:`edge_agent.networks.Detector.detect_many`): the far robots look to it like
robots half as far away, which it finds. The band costs one more detector run, on fewer pixels
than the whole frame's two (848x168 against 424x240 and its mirror image for the paper lab's
cameras); on two x86 cores that makes the detector + keypoints take 1.6-1.7x as long.

Pure numpy + OpenCV: the band is computed once per camera from its :class:`CameraModel`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Final

import numpy as np

from core.camera import CameraModel

log = logging.getLogger(__name__)

#: robots at this camera depth (metres along the optical axis) or more are the band's; the
#: whole-frame detector finds every robot with >= 3 keypoints in view up to ~8 m of floor
#: distance (docs/models.md, "The far band")
FAR_MIN_DEPTH_M: Final = 7.0
#: floor considered around the camera (metres): beyond it a robot is a few pixels tall anyway
FAR_MAX_RANGE_M: Final = 20.0
#: rows added above and below the rows the far robots can fill (pixels of the frame): the
#: network sees some context around a robot at the band's edge
FAR_MARGIN_PX: Final = 16
#: the band's rows are a multiple of this (the network's coarsest stride divides it evenly)
ROW_MULTIPLE: Final = 8
#: the band's scale against the detector's whole-frame scale
FAR_ZOOM: Final = 2.0
#: a band taller than this share of the frame is cut to it (its far end kept): its cost would
#: approach a whole-frame detector run at twice the resolution
MAX_BAND_SHARE: Final = 0.5
#: the edge agent's ``--far-band`` choices: ``on`` (the camera's band from its calibration,
#: where it has one), ``off``, or ``auto``: on where the detector runs on a GPU (TensorRT,
#: CUDA), off on the CPU, where the detector + keypoints take 1.6-1.7x as long with it
#: (``smartedge bench edge``), below the edge's 60 frames/s on two x86 cores
FAR_BAND_CHOICES: Final = ("auto", "on", "off")


@dataclasses.dataclass(frozen=True)
class FarBand:
    """Rows ``v0`` (first) to ``v1`` (past the last) of a ``frame_w`` x ``frame_h`` frame, run
    through the detector at ``scale`` input pixels per frame pixel. ``feet_max_v``: the lowest
    row (frame pixels) at which a far robot's feet can be (None: ``v1``); the rows below it are
    context, and a box reaching below it is a nearer robot the band cuts, the whole frame's."""

    v0: int
    v1: int
    frame_w: int
    frame_h: int
    scale: float
    feet_max_v: float | None = None

    def __post_init__(self) -> None:
        if not 0 <= self.v0 < self.v1 <= self.frame_h:
            raise ValueError(f"far band rows {self.v0}..{self.v1} do not lie in a frame "
                             f"{self.frame_h} rows tall")
        if not 0.0 < self.scale <= 1.0:
            raise ValueError(f"far band scale {self.scale}: expected (0, 1]")
        if self.feet_max_v is None:
            object.__setattr__(self, "feet_max_v", float(self.v1))

    @property
    def input_w(self) -> int:
        """The detector's input width for the band (a multiple of :data:`ROW_MULTIPLE`)."""
        return max(ROW_MULTIPLE, round(self.frame_w * self.scale / ROW_MULTIPLE) * ROW_MULTIPLE)

    @property
    def input_h(self) -> int:
        """The detector's input height for the band."""
        rows = (self.v1 - self.v0) * self.scale
        return max(ROW_MULTIPLE, round(rows / ROW_MULTIPLE) * ROW_MULTIPLE)

    def applies_to(self, width: int, height: int) -> bool:
        """Whether a frame of this size is the one the band was computed for."""
        return (width, height) == (self.frame_w, self.frame_h)

    def describe(self) -> str:
        return (f"rows {self.v0}-{self.v1} of {self.frame_w}x{self.frame_h} at "
                f"{self.input_w}x{self.input_h}")


def far_band_for_camera(camera: CameraModel, robot_height_m: float, detector_input_w: int, *,
                        min_depth_m: float = FAR_MIN_DEPTH_M,
                        max_range_m: float = FAR_MAX_RANGE_M,
                        margin_px: int = FAR_MARGIN_PX, zoom: float = FAR_ZOOM
                        ) -> FarBand | None:
    """The far band of ``camera`` for robots ``robot_height_m`` tall and a detector whose
    whole-frame input is ``detector_input_w`` pixels wide, or None: no floor at
    ``min_depth_m`` or more is in view (a camera looking steeply down), or the detector already
    sees the frame at half of full resolution or more (the band could not zoom in twice)."""
    if robot_height_m <= 0.0 or not math.isfinite(robot_height_m):
        raise ValueError(f"robot height {robot_height_m} m: expected a positive number")
    scale = min(1.0, zoom * detector_input_w / camera.width)
    if scale < 1.25 * detector_input_w / camera.width:
        return None
    rows = far_rows(camera, robot_height_m, min_depth_m, max_range_m)
    if rows is None:
        return None
    top, bottom = rows
    v0 = max(0, math.floor((top - margin_px) / ROW_MULTIPLE) * ROW_MULTIPLE)
    v1 = min(camera.height, math.ceil((bottom + margin_px) / ROW_MULTIPLE) * ROW_MULTIPLE)
    limit = int(MAX_BAND_SHARE * camera.height) // ROW_MULTIPLE * ROW_MULTIPLE
    if v1 - v0 > limit:
        log.info("%s: the far band (rows %d-%d) is cut to its upper %d rows", camera.camera_id,
                 v0, v1, limit)
        v1 = v0 + limit
    if v1 - v0 < ROW_MULTIPLE:
        return None
    return FarBand(v0, v1, camera.width, camera.height, scale, feet_max_v=min(bottom, v1))


def far_rows(camera: CameraModel, robot_height_m: float, min_depth_m: float,
             max_range_m: float) -> tuple[float, float] | None:
    """(top, bottom) rows, in frame pixels, of the robots standing on the floor within
    ``max_range_m`` of the camera at a camera depth of ``min_depth_m`` or more, as far as they
    are in the image; None when there are none."""
    import cv2

    centre = camera.position_world
    r = np.linspace(0.25, max_range_m, 160)
    bearing = np.radians(np.arange(0.0, 360.0, 0.5))
    rr, bb = np.meshgrid(r, bearing)
    feet = np.stack([centre[0] + rr.ravel() * np.cos(bb.ravel()),
                     centre[1] + rr.ravel() * np.sin(bb.ravel()), np.zeros(rr.size)], axis=1)
    depth = camera.world_to_cam(feet)[:, 2]
    feet = feet[depth >= min_depth_m]
    if not len(feet):
        return None
    heads = feet + np.array([0.0, 0.0, robot_height_m])
    points = camera.world_to_cam(np.concatenate([feet, heads]))
    # inside the field of view before the lens model (the distortion polynomial folds back
    # far outside it)
    pinhole = points[:, :2] / points[:, 2:3] * np.diag(camera.K)[:2] + camera.K[:2, 2]
    inside = ((pinhole[:, 0] >= -0.1 * camera.width) & (pinhole[:, 0] < 1.1 * camera.width)
              & (pinhole[:, 1] >= -0.1 * camera.height)
              & (pinhole[:, 1] < 1.1 * camera.height) & (points[:, 2] > 0))
    if not inside.any():
        return None
    uv, _ = cv2.projectPoints(points[inside], np.zeros(3), np.zeros(3), camera.K, camera.dist)
    uv = uv.reshape(-1, 2)
    seen = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] < camera.height)
    if not seen.any():
        return None
    v = uv[seen, 1]
    return max(0.0, float(v.min())), float(v.max())
