"""Frame-sets: the synchronized multi-view observations of one robot that one pose solve uses.

A :class:`FrameSet` is whatever cameras saw the robot within the synchronization window; it is
built by the synchronizer from :class:`protocol.RobotDetections` messages, or directly from
arrays (simulation, tests).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from protocol.messages import Detection, RobotDetections


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
                     None if sig is None else np.asarray(sig, np.float64) * scale,
                     det.robot_model)


def observation_for_robot(msg: RobotDetections, robot_id: str, num_keypoints: int,
                          attribute_unnamed: bool, stamp_ns: int, scale: float = 1.0
                          ) -> CameraObservation | str:
    """The observation of ``robot_id`` in ``msg`` (stamp already on the common clock, keypoints
    converted by ``scale`` to calibrated pixels), or why there is none: ``"not_seen"`` or
    ``"bad_keypoints"`` (the synchronizer's counter names)."""
    det = best_detection(msg, robot_id)
    if det is not None and det.robot_id == "" and not attribute_unnamed:
        det = None
    if det is None:
        return "not_seen"
    if det.keypoints_px.shape[0] != num_keypoints:
        return "bad_keypoints"
    if scale != 1.0:
        det = scale_detection(det, scale)
    return CameraObservation.from_detection(msg.camera_id, stamp_ns, det)


def frame_set_from_detections(site: Any, detections: Sequence[RobotDetections],
                              robot_id: str | None = None) -> tuple[FrameSet, list[str]]:
    """One :class:`FrameSet` from camera messages that belong together (one per camera, the
    caller's synchronization), with the checks the synchronizer applies: camera known, image
    size the calibrated one or an exact scale of it (converted), the robot's detection (for
    ``robot_id``; unidentified detections count when the site has one robot: on a site with
    several, name them first, :mod:`backend_service.association`), keypoint count.
    Stamps are corrected by each camera's clock offset. Returns the frame-set and what was
    dropped and why. ``TypeError`` if ``detections`` is not a sequence of
    :class:`RobotDetections`.
    """
    if isinstance(detections, RobotDetections):
        detections = [detections]
    if not isinstance(detections, Sequence) or isinstance(detections, (str, bytes)):
        raise TypeError(f"detections: expected a sequence of RobotDetections, got "
                        f"{type(detections).__name__}")
    for i, msg in enumerate(detections):
        if not isinstance(msg, RobotDetections):
            raise TypeError(f"detections[{i}]: expected RobotDetections, got "
                            f"{type(msg).__name__}")
    robots = list(site.robots)
    if robot_id is None:
        if len(robots) != 1:
            raise ValueError(f"the site has robots {robots}: say which one (robot_id=...)")
        robot_id = robots[0]
    model = site.robot_model(robot_id)
    attribute_unnamed = len(robots) == 1
    problems: list[str] = []
    observations: dict[str, CameraObservation] = {}
    for msg in detections:
        cam = site.cameras.get(msg.camera_id)
        if cam is None:
            problems.append(f"unknown camera {msg.camera_id!r}")
            continue
        if msg.camera_id in observations:
            problems.append(f"camera {msg.camera_id!r} given twice; the first is used")
            continue
        scale = image_scale(msg.image_width, msg.image_height, cam.width, cam.height)
        if scale is None:
            problems.append(f"camera {msg.camera_id!r}: {msg.image_width}x{msg.image_height} "
                            f"images, calibrated {cam.width}x{cam.height} (not an exact scale)")
            continue
        stamp = int(msg.stamp_ns) + int(cam.clock_offset_ns)
        obs = observation_for_robot(msg, robot_id, model.num_keypoints, attribute_unnamed,
                                    stamp, scale)
        if obs == "not_seen":
            problems.append(f"camera {msg.camera_id!r}: robot {robot_id!r} not seen")
        elif obs == "bad_keypoints":
            problems.append(f"camera {msg.camera_id!r}: keypoint count differs from robot "
                            f"model {model.name!r} ({model.num_keypoints})")
        elif isinstance(obs, CameraObservation):
            observations[msg.camera_id] = obs
    return FrameSet.from_observations(robot_id, list(observations.values())), problems
