"""The robot keypoint pipelines: the edge's networks put together (no torch).

:class:`RobotKeypointPipeline` runs detector → crop → keypoints (:mod:`edge_agent.networks`)
on a full frame and returns raw (distorted) pixel keypoints with confidences per detected robot.
:class:`RobotTypesPipeline` does it for every robot model (type) of a site, one
:class:`RobotKeypointPipeline` each, and removes the duplicate boxes two types' detectors put on
one robot; :func:`models_for_site` picks the one or the other for a site file. The models'
cards are :mod:`edge_agent.model_cards`, where they run :mod:`edge_agent.providers`, the
test-time flip :mod:`edge_agent.flip`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from edge_agent.boxes import same_robot
from edge_agent.far_band import FarBand
from edge_agent.model_cards import ModelError, default_model_dir, model_files
from edge_agent.networks import Detector, KeypointEstimator, RobotObservation, StageTimes
from edge_agent.providers import ExecutionProviders, as_execution_providers

log = logging.getLogger(__name__)
#: a box whose keypoints the keypoint network finds with a mean confidence below this holds no
#: robot: the detector's false boxes (a wall corner of one site camera scored 0.3-0.57 in most
#: of its views) get 0.20-0.24, true boxes 0.29-0.96 (below 0.3: 5 of 650 true boxes on four
#: held-out sets, robots mostly hidden, whose keypoints carry sigmas of 30 px and more; above
#: it: 80 % of the false boxes removed; docs/models.md)
MIN_KEYPOINT_CONFIDENCE: Final = 0.3


class RobotKeypointPipeline:
    """Detector → crop → keypoints for one robot model.

    ``detector`` / ``keypoints``: ONNX files (each with its card beside it); default: the
    shipped models. ``keypoint_names``: the site's robot model's, checked against the keypoint
    model's card. ``providers``: onnxruntime execution providers in order of preference
    (default CPU). ``spinning``: let onnxruntime's idle threads spin (its default); off here,
    because on a 2-core board spinning threads starve the frame pre-processing (measured
    ~2x slower per frame, ``smartedge bench edge``). ``flip``: the keypoint network's
    test-time flip augmentation (:class:`KeypointEstimator`; None: as its card says).
    ``detector_flip``: the detector's (:class:`Detector`; None: as its card says).
    ``robot_model``: the site's model name put on every observation (``""``: none).
    ``min_keypoint_confidence``: a box whose keypoints' mean confidence is below this is not
    reported (:data:`MIN_KEYPOINT_CONFIDENCE`; counted in :attr:`unconfirmed`); only with a
    keypoint model whose card calibrates its confidence (``sigma_calibration``), else 0."""

    def __init__(self, detector: Path | str | None = None, keypoints: Path | str | None = None,
                 *, threads: int = 2,
                 providers: ExecutionProviders | Sequence[Any] | None = None,
                 keypoint_names: Sequence[str] | None = None, spinning: bool = False,
                 flip: bool | None = None, detector_flip: bool | None = None,
                 robot_model: str = "",
                 min_keypoint_confidence: float = MIN_KEYPOINT_CONFIDENCE) -> None:
        shipped = default_model_dir()
        self.robot_model = robot_model
        if not 0.0 <= min_keypoint_confidence < 1.0:
            raise ValueError(f"min_keypoint_confidence must lie in [0, 1), got "
                             f"{min_keypoint_confidence}")
        #: boxes dropped because the keypoint network found no robot in them, since start
        self.unconfirmed = 0
        #: what both networks were asked to run on (:func:`execution_providers`)
        self.execution = as_execution_providers(providers)
        self.providers = self.execution.names
        self.detector = Detector(shipped / "detector.onnx" if detector is None else detector,
                                 threads=threads, providers=self.execution, spinning=spinning,
                                 flip=detector_flip)
        self.keypoints = KeypointEstimator(
            shipped / "keypoints.onnx" if keypoints is None else keypoints, threads=threads,
            providers=self.execution, spinning=spinning, flip=flip)
        self.folder = self.keypoints.path.parent
        # a floor on a confidence means something only where the card calibrates it
        self.min_keypoint_confidence = (float(min_keypoint_confidence)
                                        if self.keypoints.calibrated else 0.0)
        kp_names = list(self.keypoints.card.keypoint_names)
        if keypoint_names is not None and list(keypoint_names) != kp_names:
            raise ModelError(
                f"{self.keypoints.path}: the model has {len(kp_names)} keypoints {kp_names}; "
                f"the site's robot model has {len(keypoint_names)} {list(keypoint_names)}")
        self.times = StageTimes()

    @classmethod
    def for_robot(cls, robot_model: Any, model_dir: Path | str | None = None,
                  **kwargs: Any) -> RobotKeypointPipeline:
        """The models of ``model_dir`` when given (a ``--model`` override), else those a
        site's :class:`core.site.RobotModel` names (default: shipped); checked against the
        robot model's keypoint names."""
        det, kp = (model_files(model_dir) if model_dir else
                   (robot_model.detector_onnx, robot_model.keypoints_onnx))
        kwargs.setdefault("robot_model", robot_model.name)
        return cls(det, kp, keypoint_names=robot_model.keypoint_names, **kwargs)

    @classmethod
    def from_folder(cls, folder: Path | str | None, **kwargs: Any) -> RobotKeypointPipeline:
        """The ``detector.onnx`` + ``keypoints.onnx`` of ``folder`` (default: shipped)."""
        det, kp = model_files(folder)
        return cls(det, kp, **kwargs)

    @property
    def model_id(self) -> str:
        return f"{self.keypoints.card.robot_model}/{self.folder.name}"

    @property
    def far_band_added(self) -> int:
        """Boxes the far band found that the whole frame did not, since start."""
        return self.detector.far_band_added

    @property
    def providers_used(self) -> list[str]:
        """The execution providers the detector's session runs on."""
        return self.detector.providers_used

    def providers_note(self) -> str:
        """What the networks run on against what was asked (:meth:`ExecutionProviders.describe`),
        for the status."""
        return self.execution.describe(self.providers_used)

    def __call__(self, image_rgb: np.ndarray, *, min_score: float = 0.3,
                 max_robots: int = 4, far_band: FarBand | None = None
                 ) -> list[RobotObservation]:
        return self.run_many([image_rgb], min_score=min_score, max_robots=max_robots,
                             far_bands=[far_band])[0]

    def run_many(self, images_rgb: Sequence[np.ndarray], *, min_score: float = 0.3,
                 max_robots: int = 4, far_bands: Sequence[FarBand | None] | None = None
                 ) -> list[list[RobotObservation]]:
        """The robots of several frames (e.g. the cameras of one capture), each network run
        once for all of them (a batch); what each frame gets is what it gets alone.
        ``far_bands``: each frame's camera's far band (:meth:`Detector.detect_many`).
        :attr:`times` holds the whole call's stage times."""
        for image_rgb in images_rgb:
            if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
                raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got "
                                 f"{image_rgb.shape} {image_rgb.dtype}")
        t0 = time.perf_counter()
        boxes = self.detector.detect_many(images_rgb, min_score, max_robots, far_bands)
        t1 = time.perf_counter()
        keypoints = self.keypoints.estimate_many(images_rgb, boxes)
        t2 = time.perf_counter()
        self.times = StageTimes((t1 - t0) * 1e3, (t2 - t1) * 1e3)
        out = []
        for frame_boxes, (kp, conf, sigma) in zip(boxes, keypoints, strict=True):
            found = []
            for i, b in enumerate(frame_boxes):
                obs = RobotObservation(b[:4].copy(), float(b[4]), kp[i], conf[i],
                                       None if sigma is None else sigma[i], self.robot_model)
                if type_evidence(obs)[0] < self.min_keypoint_confidence:
                    self.unconfirmed += 1
                    continue
                found.append(obs)
            out.append(found)
        return out


def type_evidence(obs: RobotObservation) -> tuple[float, float]:
    """How well one model's networks explain a box, for choosing between two types' boxes on
    one robot: the mean confidence of that model's keypoints in it, then the detector's score.
    A keypoint network shown another type's robot finds its keypoints with low confidence,
    while a detector trained without the other types may still score that robot high
    (measured on the two-type lab: ranking by confidence keeps the right type on 97 % of the
    HSR's views against 78 % by detector score; docs/models.md, "Several robot types")."""
    conf = np.nan_to_num(np.asarray(obs.confidence, np.float64), nan=0.0)
    mean = float(np.clip(conf, 0.0, 1.0).mean()) if conf.size else 0.0
    return mean, float(obs.score)


def suppress_across_models(found: Sequence[RobotObservation], iou: float, max_robots: int,
                           inside: float = 1.0) -> tuple[list[RobotObservation], int]:
    """The robots of one frame from several models' networks without the duplicates: boxes of
    two **different** models on one robot (:func:`same_robot` with ``iou`` and ``inside``)
    keep the one with the higher :func:`type_evidence` (boxes of one model were already
    suppressed by its own detector's decoding). Returns (kept, best evidence first, at most
    ``max_robots``; how many duplicates were dropped)."""
    kept: list[RobotObservation] = []  # sorted() is stable: equal evidence keeps input order
    dropped = 0
    for obs in sorted(found, key=type_evidence, reverse=True):
        if any(k.robot_model != obs.robot_model
               and same_robot(k.bbox_xyxy, obs.bbox_xyxy, iou, inside) for k in kept):
            dropped += 1
            continue
        kept.append(obs)
    return kept[:max_robots], dropped


#: on a site with several robot types, a box whose own keypoint network's mean confidence is
#: below this is not that type's robot: a single-class detector trained without the other
#: types may box them (the shipped HSR detector scored the box base 0.49-0.89 in 10 of 12
#: views, its keypoint network 0.27-0.46 there; true HSR boxes 0.89-0.95, and 5 % of them,
#: robots mostly hidden, below 0.5, whose keypoints carry sigmas of 24 px or more)
MIN_TYPE_CONFIDENCE: Final = 0.5


class RobotTypesPipeline:
    """Detector → crop → keypoints for every robot model (type) of a site: one
    :class:`RobotKeypointPipeline` per model (``pipelines``: model name → its pipeline, each
    with its own detector; the shipped detector is single-class), each model's keypoint network
    on that model's boxes, every observation tagged with its model. Boxes of two models on one
    robot (IoU >= ``nms_iou``, or the smaller at least ``nms_inside`` within the other) keep the
    one its own keypoint network is more confident of, then the higher detector score
    (:func:`suppress_across_models`, :func:`type_evidence`), the other counted in
    :attr:`duplicates_dropped`; a box whose own model's keypoints have a mean confidence
    below ``min_type_confidence`` (:data:`MIN_TYPE_CONFIDENCE`; models whose card calibrates
    the confidence) is not that model's robot (dropped, counted in :attr:`type_rejected`).
    The cost is the sum of the models' (measured in docs/models.md, "Several robot types").
    Same interface as :class:`RobotKeypointPipeline` where the edge pipeline uses it."""

    def __init__(self, pipelines: Mapping[str, RobotKeypointPipeline], *,
                 nms_iou: float = 0.5, nms_inside: float = 0.6,
                 min_type_confidence: float = MIN_TYPE_CONFIDENCE) -> None:
        if not pipelines:
            raise ModelError("RobotTypesPipeline: no robot models")
        if not 0.0 < nms_iou <= 1.0:
            raise ValueError(f"nms_iou must lie in (0, 1], got {nms_iou}")
        self.pipelines: dict[str, RobotKeypointPipeline] = dict(pipelines)
        for name, pipe in self.pipelines.items():
            pipe.robot_model = name
        if not 0.0 < nms_inside <= 1.0:
            raise ValueError(f"nms_inside must lie in (0, 1], got {nms_inside}")
        if not 0.0 <= min_type_confidence < 1.0:
            raise ValueError(f"min_type_confidence must lie in [0, 1), got "
                             f"{min_type_confidence}")
        self.nms_iou = float(nms_iou)
        self.nms_inside = float(nms_inside)
        self.min_type_confidence = float(min_type_confidence)
        #: boxes dropped because their own model's keypoints were not found (another type's
        #: robot, or a detector's false box), since start
        self.type_rejected = 0
        first = next(iter(self.pipelines.values()))
        self.execution = first.execution
        self.providers = first.providers
        self.times = StageTimes()
        #: boxes dropped as another model's duplicate, since start
        self.duplicates_dropped = 0

    @property
    def model_id(self) -> str:
        return "+".join(p.model_id for p in self.pipelines.values())

    @property
    def unconfirmed(self) -> int:
        """Boxes the models' own keypoint floors dropped (:attr:`RobotKeypointPipeline.
        unconfirmed`), since start."""
        return sum(p.unconfirmed for p in self.pipelines.values())

    @property
    def far_band_added(self) -> int:
        """Boxes the models' far bands found that their whole frames did not, since start."""
        return sum(p.far_band_added for p in self.pipelines.values())

    @property
    def providers_used(self) -> list[str]:
        return next(iter(self.pipelines.values())).providers_used

    def providers_note(self) -> str:
        return next(iter(self.pipelines.values())).providers_note()

    def describe(self) -> str:
        """One line per model: its name and model files (for the log)."""
        return "; ".join(f"{name}: {p.detector.path} + {p.keypoints.path}"
                         for name, p in self.pipelines.items())

    def __call__(self, image_rgb: np.ndarray, *, min_score: float = 0.3,
                 max_robots: int = 4, far_band: FarBand | None = None
                 ) -> list[RobotObservation]:
        return self.run_many([image_rgb], min_score=min_score, max_robots=max_robots,
                             far_bands=[far_band])[0]

    def run_many(self, images_rgb: Sequence[np.ndarray], *, min_score: float = 0.3,
                 max_robots: int = 4, far_bands: Sequence[FarBand | None] | None = None
                 ) -> list[list[RobotObservation]]:
        """The robots of several frames through every model's networks (each a batch), the
        duplicates across models removed; :attr:`times` sums the models' stage times."""
        merged: list[list[RobotObservation]] = [[] for _ in images_rgb]
        det_ms = kp_ms = 0.0
        for pipe in self.pipelines.values():
            per_frame = pipe.run_many(images_rgb, min_score=min_score, max_robots=max_robots,
                                      far_bands=far_bands)
            det_ms += pipe.times.detector_ms
            kp_ms += pipe.times.keypoints_ms
            # as the pipeline's own floor: only a calibrated confidence is a measure
            floor = self.min_type_confidence if pipe.keypoints.calibrated else 0.0
            for out, found in zip(merged, per_frame, strict=True):
                for obs in found:
                    if type_evidence(obs)[0] < floor:
                        self.type_rejected += 1
                        continue
                    out.append(obs)
        self.times = StageTimes(det_ms, kp_ms)
        result = []
        for found in merged:
            kept, dropped = suppress_across_models(found, self.nms_iou, max_robots,
                                                   self.nms_inside)
            if dropped:
                self.duplicates_dropped += dropped
                log.debug("dropped %d duplicate box(es) of another robot model", dropped)
            result.append(kept)
        return result


def models_for_site(site: Any, model_dir: Path | str | None = None, *,
                    robot_ids: Sequence[str] | None = None, nms_iou: float = 0.5,
                    **kwargs: Any) -> RobotKeypointPipeline | RobotTypesPipeline:
    """The edge's networks for the robots of ``site`` (a :class:`core.site.Site`;
    ``robot_ids``: only these robots' models, default all): the models of a site with one robot
    model (``model_dir`` overrides its files, the ``--model`` option), a
    :class:`RobotTypesPipeline` over each model's files (``robot_models.<name>.models``; none:
    the shipped models, which fit only the built-in HSR's keypoints) when there are several.
    ``kwargs`` go to every :class:`RobotKeypointPipeline`. Raises :class:`ModelError` naming the
    robot model whose files are missing or do not fit."""
    ids = list(site.robots) if robot_ids is None else list(robot_ids)
    names: list[str] = []
    for rid in ids:
        name = site.robots[rid]
        if name not in names:
            names.append(name)
    if not names:
        raise ModelError(f"site {site.name!r}: no robots, so no robot models to run")
    if len(names) == 1:
        return RobotKeypointPipeline.for_robot(site.robot_models[names[0]], model_dir, **kwargs)
    if model_dir:
        raise ModelError(f"site {site.name!r} has {len(names)} robot models {names}: one model "
                         "folder (--model) cannot serve them; name each model's files under "
                         "robot_models.<name>.models in the site file")
    pipelines: dict[str, RobotKeypointPipeline] = {}
    for name in names:
        model = site.robot_models[name]
        try:
            pipelines[name] = RobotKeypointPipeline.for_robot(model, None, **kwargs)
        except ModelError as exc:
            hint = ("" if model.keypoints_onnx is not None else
                    f" (no robot_models.{name}.models in the site file: the shipped models "
                    "are the built-in HSR's)")
            raise ModelError(f"robot model {name!r} of site {site.name!r}: {exc}{hint}"
                             ) from None
    return RobotTypesPipeline(pipelines, nms_iou=nms_iou)


