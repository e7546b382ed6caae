"""Frame-sets: the synchronized multi-view observations of one robot that one pose solve uses.

A :class:`FrameSet` is whatever cameras saw the robot within the synchronization window; it is
built by the synchronizer from :class:`protocol.RobotDetections` messages, or directly from
arrays (simulation, tests).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from protocol.geometry import se3_from_planar
from protocol.messages import Detection, RobotDetections


@dataclasses.dataclass(frozen=True)
class PlanarPose:
    """A planar pose (x, y in metres, theta in radians) of the robot base in some frame."""

    x: float
    y: float
    theta: float

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.theta])

    def T(self) -> np.ndarray:
        """(4, 4) homogeneous transform of this pose (robot base → frame), z = 0."""
        return se3_from_planar(self.x, self.y, self.theta)


@dataclasses.dataclass(frozen=True, eq=False)
class CameraObservation:
    """The keypoints of one robot seen by one camera.

    ``stamp_ns``: detection stamp already corrected by the camera's clock offset.
    ``keypoints_px``: (M, 2) float64 pixel coordinates (may contain NaN in hand-made frame-sets;
    the solver treats non-finite keypoints as missing). ``keypoint_scores``: (M,) in [0, 1].
    ``keypoint_sigmas_px``: optional (M,) 1-sigma pixel uncertainties from the detector (the
    solver then weights by them, see :mod:`backend_service.estimate`).
    """

    camera_id: str
    stamp_ns: int
    keypoints_px: np.ndarray
    keypoint_scores: np.ndarray
    bbox_xyxy: np.ndarray | None = None
    score: float = 1.0
    keypoint_sigmas_px: np.ndarray | None = None

    @classmethod
    def from_detection(
        cls, camera_id: str, stamp_ns: int, detection: Detection
    ) -> CameraObservation:
        return cls(
            camera_id=camera_id,
            stamp_ns=stamp_ns,
            keypoints_px=np.asarray(detection.keypoints_px, dtype=np.float64),
            keypoint_scores=np.asarray(detection.keypoint_scores, dtype=np.float64),
            bbox_xyxy=np.asarray(detection.bbox_xyxy, dtype=np.float64),
            score=float(detection.score),
            keypoint_sigmas_px=None if detection.keypoint_sigmas_px is None
            else np.asarray(detection.keypoint_sigmas_px, dtype=np.float64),
        )


@dataclasses.dataclass(frozen=True)
class FrameSet:
    """Synchronized observations of one robot: at most one :class:`CameraObservation` per
    camera. ``stamp_ns`` is the frame-set's reference time on the common clock (the mean of its
    observations' stamps)."""

    robot_id: str
    stamp_ns: int
    observations: tuple[CameraObservation, ...]

    @property
    def camera_ids(self) -> tuple[str, ...]:
        return tuple(o.camera_id for o in self.observations)

    @classmethod
    def from_observations(
        cls, robot_id: str, observations: tuple[CameraObservation, ...] | list[CameraObservation]
    ) -> FrameSet:
        obs = tuple(observations)
        stamp = sum(o.stamp_ns for o in obs) // len(obs) if obs else 0  # exact integer ns
        return cls(robot_id, stamp, obs)


def best_detection(msg: RobotDetections, robot_id: str = "") -> Detection | None:
    """The detection of ``robot_id`` in ``msg`` (or, for unidentified detections, the one with
    the highest score); ``None`` if the camera did not see it."""
    candidates = [d for d in msg.detections if d.robot_id in (robot_id, "")]
    if not candidates:
        return None
    named = [d for d in candidates if d.robot_id == robot_id and robot_id]
    return max(named or candidates, key=lambda d: d.score)


def image_scale(width: int, height: int, calibrated_width: int, calibrated_height: int
                ) -> float | None:
    """Calibrated pixels per message pixel when a ``width`` x ``height`` image is an exact scale
    of the ``calibrated_width`` x ``calibrated_height`` calibration (same aspect ratio to the
    pixel: a binned or resized stream); ``None`` when it is not (a crop, another camera mode).
    """
    if width <= 0 or height <= 0:
        return None
    if (width, height) == (calibrated_width, calibrated_height):
        return 1.0
    if width * calibrated_height != height * calibrated_width:
        return None
    return calibrated_width / width


def scale_detection(det: Detection, scale: float) -> Detection:
    """``det`` of an image scaled by 1/``scale`` in calibrated pixels (pixel centres at integer
    coordinates: ``u_cal = (u + 0.5) * scale - 0.5``); sigmas scale with it."""
    def to_cal(a: np.ndarray) -> np.ndarray:
        return (np.asarray(a, np.float64) + 0.5) * scale - 0.5

    sig = det.keypoint_sigmas_px
    return Detection(to_cal(det.bbox_xyxy), det.score, to_cal(det.keypoints_px),
                     np.asarray(det.keypoint_scores, np.float64), det.robot_id,
                     None if sig is None else np.asarray(sig, np.float64) * scale)
