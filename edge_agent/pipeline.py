"""The edge's per-frame pipeline: a :class:`~edge_agent.frames.Frame` through the ONNX models to a
:class:`protocol.messages.RobotDetections` (transport-free; the edge agent publishes it).

Keypoints stay raw (distorted) frame pixels, as the backend's camera model expects; the message
carries the frame's size and the model id so the backend can tell what they refer to.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from core.site import Site
from edge_agent.far_band import FAR_MIN_DEPTH_M, FarBand, far_band_for_camera
from edge_agent.frames import Frame
from edge_agent.models import RobotKeypointPipeline, RobotTypesPipeline
from edge_agent.networks import RobotObservation
from edge_agent.providers import CUDA, TENSORRT
from protocol.messages import Detection, RobotDetections

log = logging.getLogger(__name__)

#: range of the per-keypoint sigmas the edge sends (pixels)
SIGMA_MIN_PX = 0.05
SIGMA_MAX_PX = 1000.0


@dataclasses.dataclass(frozen=True)
class StageLatency:
    """Seconds per stage of one frame."""

    detector_s: float
    keypoints_s: float
    encode_s: float = 0.0


class EdgePipeline:
    """Detector → crops → keypoints → :class:`RobotDetections` for one camera.

    ``min_score``: detections below are dropped; ``max_robots`` per frame; ``robot_id``: the
    id to put on detections (``""``: the detector cannot tell robots apart; the backend
    attributes them when the site has one robot); ``expected_size``: the camera's calibrated
    (width, height): a frame of another size is logged once (the backend then scales or rejects
    by the message's image size). ``models``: one robot model's networks, or every model's of
    a site with several robot types (:class:`RobotTypesPipeline`); each detection carries the
    robot model whose networks found it (``Detection.robot_model``). ``far_band``: the
    camera's far band (:mod:`edge_agent.far_band`; None: the detector sees the whole frame
    only)."""

    def __init__(self, camera_id: str, models: RobotKeypointPipeline | RobotTypesPipeline, *,
                 min_score: float = 0.3,
                 max_robots: int = 4, robot_id: str = "",
                 expected_size: tuple[int, int] | None = None,
                 far_band: FarBand | None = None) -> None:
        self.camera_id = camera_id
        self.far_band = far_band
        self.models = models
        self.min_score = min_score
        self.max_robots = max_robots
        self.robot_id = robot_id
        self.expected_size = expected_size
        self._warned_size = False

    @property
    def model_id(self) -> str:
        return self.models.model_id

    def process(self, frame: Frame) -> tuple[RobotDetections, StageLatency]:
        self._check_size(frame)
        band = {} if self.far_band is None else {"far_band": self.far_band}
        found = self.models(frame.image_rgb, min_score=self.min_score,
                            max_robots=self.max_robots, **band)
        return self._finish(frame, found, self.models.times.detector_ms * 1e-3,
                            self.models.times.keypoints_ms * 1e-3)

    def _check_size(self, frame: Frame) -> None:
        h, w = frame.image_rgb.shape[:2]
        if self.expected_size and (w, h) != tuple(self.expected_size) and not self._warned_size:
            log.warning("%s: frames are %dx%d, the site's calibration is %dx%d: keypoints are "
                        "sent in frame pixels with the frame's size", self.camera_id, w, h,
                        *self.expected_size)
            self._warned_size = True

    def _finish(self, frame: Frame, found: list[RobotObservation], detector_s: float,
                keypoints_s: float) -> tuple[RobotDetections, StageLatency]:
        """The message of ``frame`` from the robots the networks found in it."""
        t1 = time.perf_counter()
        h, w = frame.image_rgb.shape[:2]
        detections = []
        for obs in found:
            box = np.asarray(obs.bbox_xyxy, np.float64).copy()
            box[[0, 2]] = np.clip(box[[0, 2]], -0.5, w - 0.5)
            box[[1, 3]] = np.clip(box[[1, 3]], -0.5, h - 0.5)
            if box[2] < box[0] or box[3] < box[1]:
                continue
            kp = np.asarray(obs.keypoints_px, np.float64)
            scores = np.clip(np.nan_to_num(obs.confidence, nan=0.0), 0.0, 1.0)
            sigma = None
            if obs.sigma_px is not None:
                sigma = np.asarray(obs.sigma_px, np.float64)
                # an unusable sigma makes the keypoint uncertain, never the message invalid
                sigma = np.clip(np.nan_to_num(sigma, nan=SIGMA_MAX_PX, posinf=SIGMA_MAX_PX),
                                SIGMA_MIN_PX, SIGMA_MAX_PX)
            if not np.all(np.isfinite(kp)):
                bad = ~np.all(np.isfinite(kp), axis=1)
                kp[bad] = 0.0
                scores[bad] = 0.0
            detections.append(Detection(box, float(np.clip(obs.score, 0.0, 1.0)), kp, scores,
                                        self.robot_id, sigma, obs.robot_model))
        msg = RobotDetections(self.camera_id, frame.stamp_ns, frame.seq, w, h, self.model_id,
                              tuple(detections))
        return msg, StageLatency(detector_s, keypoints_s, time.perf_counter() - t1)


def process_batch(items: Sequence[tuple[EdgePipeline, Frame]]
                  ) -> list[tuple[RobotDetections, StageLatency]]:
    """The frames of several cameras (each with its own :class:`EdgePipeline`, all on the same
    :class:`RobotKeypointPipeline`), the networks run once for all of them
    (:meth:`RobotKeypointPipeline.run_many`); each message is what
    :meth:`EdgePipeline.process` makes of its frame. The stage latencies are the batch's,
    shared equally between its frames."""
    if not items:
        return []
    models = items[0][0].models
    settings = {(p.min_score, p.max_robots) for p, _ in items}
    if any(p.models is not models for p, _ in items) or len(settings) > 1:
        raise ValueError("process_batch: the pipelines must share models, min_score and "
                         "max_robots")
    for pipeline, frame in items:
        pipeline._check_size(frame)
    first = items[0][0]
    bands = [p.far_band for p, _ in items]
    found = models.run_many([frame.image_rgb for _, frame in items],
                            min_score=first.min_score, max_robots=first.max_robots,
                            **({"far_bands": bands} if any(bands) else {}))
    n = len(items)
    det_s, kp_s = models.times.detector_ms * 1e-3 / n, models.times.keypoints_ms * 1e-3 / n
    return [pipeline._finish(frame, obs, det_s, kp_s)
            for (pipeline, frame), obs in zip(items, found, strict=True)]


def camera_far_band(site: Site, camera_id: str,
                    models: RobotKeypointPipeline | RobotTypesPipeline) -> FarBand | None:
    """The far band of ``site``'s camera ``camera_id`` (:func:`edge_agent.far_band.
    far_band_for_camera`) for the site's tallest robot model and the detector(s) of
    ``models``; None where the camera has none or a detector file has a fixed input size
    (logged)."""
    pipes = (list(models.pipelines.values()) if isinstance(models, RobotTypesPipeline)
             else [models])
    fixed = [str(p.detector.path) for p in pipes if not p.detector.runs_far_band]
    if fixed:
        log.warning("%s: no far band: %s has a fixed input size", camera_id, ", ".join(fixed))
        return None
    names = set(site.robots.values()) or set(site.robot_models)
    height_m = max(site.robot_models[n].height_m for n in names)
    band = far_band_for_camera(site.camera(camera_id), height_m,
                               min(p.detector.card.input_w for p in pipes))
    if band is None:
        log.info("%s: no far band (no floor at %.0f m depth or more in view, or the detector "
                 "already sees the frame at half resolution or more)", camera_id,
                 FAR_MIN_DEPTH_M)
    else:
        log.info("%s: far band %s", camera_id, band.describe())
    return band


def far_band_from_args(args: Any, site: Site,
                       models: RobotKeypointPipeline | RobotTypesPipeline) -> FarBand | None:
    """The far band ``--far-band`` asks for (:data:`edge_agent.far_band.FAR_BAND_CHOICES`; an
    ``args`` without the option: ``auto``)."""
    choice = getattr(args, "far_band", "auto")
    if choice == "off":
        return None
    if choice == "auto" and not any(p in (TENSORRT, CUDA) for p in models.providers_used[:1]):
        log.info("%s: far band off (--far-band auto on the CPU; --far-band on runs it)",
                 args.camera)
        return None
    return camera_far_band(site, args.camera, models)
