"""Held-out evaluation of the deployed detector + keypoint models (onnxruntime, no torch).

Renders fresh views (:class:`simulation.dataset.SampleGenerator`, a seed the shipped models were
not trained on) of domain-randomized scenes and of the site's own cameras, runs the edge
pipeline (:class:`edge_agent.models.RobotKeypointPipeline`) on each full frame and compares with
the exact labels: detection AP@0.5, keypoint pixel errors of the robot found by the detector,
the same keypoint errors on ground-truth boxes (the keypoint network alone), occluded keypoints
separately, and whether a low confidence means a worse keypoint.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from edge_agent.boxes import box_iou
from edge_agent.far_band import FarBand, far_band_for_camera
from edge_agent.metrics import detection_ap, keypoint_metrics
from edge_agent.models import RobotKeypointPipeline

#: the default held-out seed (the shipped models train on seeds 1-2, validate on 1001-1002)
DEFAULT_SEED = 4242


@dataclasses.dataclass(frozen=True)
class KeypointEvaluation:
    """Figures per set (``randomized``, ``site``): name → value, in print order."""

    figures: dict[str, dict[str, float]]
    views: int
    wall_s: float
    #: per set, when asked for: :func:`error_breakdown`
    breakdown: dict[str, ErrorBreakdown] = dataclasses.field(default_factory=dict)

    def lines(self) -> list[str]:
        out = []
        for set_name, figs in self.figures.items():
            for name, value in figs.items():
                out.append(f"{set_name} {name} {format_figure(value)}")
        for set_name, b in self.breakdown.items():
            out += [f"{set_name} {line}" for line in b.lines()]
        return out


def format_figure(value: float) -> str:
    if not np.isfinite(value):
        return "n/a"
    if float(value).is_integer() and abs(value) >= 1:
        return str(int(value))
    return f"{value:.3f}" if abs(value) < 10 else f"{value:.1f}"


def evaluate_set(pipeline: RobotKeypointPipeline, samples: Sequence[Any],
                 min_score: float = 0.05,
                 far_bands: Callable[[Any], FarBand | None] | None = None) -> dict[str, float]:
    """Figures on rendered samples (each a :class:`simulation.dataset.Sample`): detection
    AP@0.5 over every robot; the same with the robots that show fewer than
    :data:`MIN_VISIBLE_KEYPOINTS` keypoints as ignore regions (the rule of the held-out set: no
    view can measure their pose; :func:`edge_agent.metrics.detection_ap`'s ``ignore``) and the
    measurable robots' recall at :data:`OPERATING_SCORE` per :data:`SITE_BANDS_M` distance
    band; the keypoint errors of the best detection and of the keypoint network on the true
    box. ``far_bands``: each sample camera's far band (None: the whole frame only)."""
    from simulation.scenes import robot_distance_m

    dets, gts, hidden = [], [], []
    found_in_band: dict[str, list[bool]] = {_band_label(*b): [] for b in SITE_BANDS_M}
    err_det, conf_det, valid_det, vis_det = [], [], [], []
    err_gt, conf_gt, valid_gt, vis_gt = [], [], [], []
    det_ms, kp_ms = [], []
    for s in samples:
        robot = s.robots[0]
        band = far_bands(s.camera) if far_bands is not None else None
        found = pipeline(s.image_rgb, min_score=min_score, max_robots=4, far_band=band)
        det_ms.append(pipeline.times.detector_ms)
        kp_ms.append(pipeline.times.keypoints_ms)
        boxes = np.array([[*o.bbox_xyxy, o.score] for o in found]).reshape(-1, 5)
        dets.append(boxes)
        gt = np.full(4, np.nan) if robot.bbox_xyxy is None else np.asarray(robot.bbox_xyxy)
        gts.append(gt)
        measurable = int(np.sum(robot.visible)) >= MIN_VISIBLE_KEYPOINTS
        hidden.append(not measurable)
        if robot.bbox_xyxy is None:
            continue
        if measurable and s.camera is not None:  # a dataset's frame has no simulated pose
            dist = robot_distance_m(s.camera, s.robot_pose)
            hit = any(o.score >= OPERATING_SCORE and box_iou(o.bbox_xyxy, gt) >= 0.5
                      for o in found)
            for lo, hi in SITE_BANDS_M:
                if lo <= dist < hi:
                    found_in_band[_band_label(lo, hi)].append(hit)
        valid = robot.in_image
        # the keypoint network alone, on the true box
        kp, conf = pipeline.keypoints.estimate(s.image_rgb, gt[None])
        err_gt.append(np.linalg.norm(kp[0] - robot.keypoints_px, axis=1))
        conf_gt.append(conf[0])
        valid_gt.append(valid)
        vis_gt.append(robot.visible)
        # the whole pipeline: the best detection, if it matches
        if found and box_iou(found[0].bbox_xyxy, gt) >= 0.5:
            err_det.append(np.linalg.norm(found[0].keypoints_px - robot.keypoints_px, axis=1))
            conf_det.append(found[0].confidence)
            valid_det.append(valid)
            vis_det.append(robot.visible)
    figures = dict(detection_ap(dets, np.array(gts).reshape(-1, 4)))
    if dets:
        seen = detection_ap(dets, np.array(gts).reshape(-1, 4), ignore=hidden)
        figures[f"AP@0.5 (>= {MIN_VISIBLE_KEYPOINTS} keypoints visible)"] = seen["AP@0.5"]
        figures[f"robots ignored (< {MIN_VISIBLE_KEYPOINTS} keypoints visible)"] = seen[
            "robots ignored"]
    for label, hits in found_in_band.items():
        if hits:
            count = f"{len(hits)} robot" + ("s" if len(hits) != 1 else "")
            figures[f"recall {label} ({count})"] = float(np.mean(hits))
    if err_det:
        pipe = keypoint_metrics(np.array(err_det), np.array(conf_det), np.array(valid_det),
                                np.array(vis_det))
        figures.update({f"pipeline {k}": v for k, v in pipe.items()})
    if err_gt:
        alone = keypoint_metrics(np.array(err_gt), np.array(conf_gt), np.array(valid_gt),
                                 np.array(vis_gt))
        for k in ("median error px", "mean error px", "PCK@2px", "PCK@5px",
                  "occluded median error px"):
            figures[f"true-box {k}"] = alone[k]
    figures["detector ms"] = float(np.median(det_ms))
    figures["keypoints ms"] = float(np.median(kp_ms))
    return figures


class CameraFarBands:
    """Each camera's far band as the deployed edge computes it (``--far-band on``,
    :func:`edge_agent.far_band.far_band_for_camera`) for ``pipeline``'s detector and robots
    ``robot_height_m`` tall, once per camera (a camera is its id, intrinsics and pose)."""

    def __init__(self, pipeline: RobotKeypointPipeline, robot_height_m: float) -> None:
        self.input_w = pipeline.detector.card.input_w
        self.robot_height_m = robot_height_m
        self._bands: dict[tuple[str, bytes, bytes], FarBand | None] = {}

    def __call__(self, camera: Any) -> FarBand | None:
        key = (camera.camera_id, camera.K.tobytes(), camera.T_cam_world.tobytes())
        if key not in self._bands:
            self._bands[key] = far_band_for_camera(camera, self.robot_height_m, self.input_w)
        return self._bands[key]


def _far_bands(pipeline: RobotKeypointPipeline, scenario: Any) -> CameraFarBands:
    return CameraFarBands(pipeline, scenario.site.robot_model(scenario.robot_id).height_m)


def _read_rgb(path: Path) -> np.ndarray | None:
    import cv2

    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def evaluate_on_dataset(dataset_path: Path, model_dir: Path | None = None, *,
                        image_root: Path | None = None, category: str | None = None,
                        threads: int = 2, flip: bool | None = None,
                        detector_flip: bool | None = None
                        ) -> tuple[dict[str, float], dict[str, list[str]], int]:
    """:func:`evaluate_set`'s figures on a COCO keypoints dataset (a lab's own labelled frames,
    ``smartedge dataset``): (figures, what was left out, frames evaluated). ``image_root``: the
    folder the file names are relative to (default: the dataset file's); ``category``: the
    robot model (default: the file's only one). The keypoint network must know the category's
    keypoint names (its card is matched by name)."""
    from core.coco import labelled_frames, read_dataset

    dataset = read_dataset(dataset_path)
    if category is None:
        if len(dataset.categories) != 1:
            raise ValueError(f"{dataset_path}: {len(dataset.categories)} categories "
                             f"{[c.name for c in dataset.categories]}: name one")
        category = dataset.categories[0].name
    names = dataset.category(category).keypoints
    pipeline = RobotKeypointPipeline.from_folder(model_dir, threads=threads, keypoint_names=names,
                                                 flip=flip, detector_flip=detector_flip)
    frames, skipped = labelled_frames(dataset, dataset.category(category),
                                      image_root or Path(dataset_path).parent, _read_rgb)
    if not frames:
        raise ValueError(f"{dataset_path}: no frame could be evaluated ({skipped})")
    return evaluate_set(pipeline, frames), skipped, len(frames)


def _deployed_pipeline(scenario: Any, model_dir: Path | None, threads: int,
                       flip: bool | None, detector_flip: bool | None = None
                       ) -> RobotKeypointPipeline:
    """The edge's detector + keypoint pipeline of ``model_dir`` (default: the shipped models),
    keypoints named as the scenario's robot model names them."""
    model = scenario.site.robot_model(scenario.robot_id)
    return RobotKeypointPipeline.from_folder(model_dir, threads=threads,
                                             keypoint_names=model.keypoint_names, flip=flip,
                                             detector_flip=detector_flip)


def evaluate_keypoints(model_dir: Path | None = None, *, seed: int = DEFAULT_SEED,
                       count: int = 300, modes: Sequence[str] = ("randomized", "site"),
                       scenario_path: Path | None = None, threads: int = 2,
                       flip: bool | None = None, detector_flip: bool | None = None,
                       breakdown: bool = False, far_band: bool = False,
                       progress: Callable[[str], None] | None = None) -> KeypointEvaluation:
    """Render ``count`` held-out views per mode from ``seed`` and evaluate the models of
    ``model_dir`` (default: the shipped ones); ``flip``: with the keypoint network's test-time
    flip augmentation or without (None: as the model's card says); ``detector_flip``: the same
    for the detector; ``far_band``: each view's camera's far band (:class:`CameraFarBands`)
    or the whole frame only; ``breakdown``: also :func:`error_breakdown` per set."""
    from simulation.dataset import SampleGenerator
    from simulation.scenario import PAPER_SCENARIO, load_scenario

    say = progress or (lambda line: None)
    scenario = load_scenario(scenario_path or PAPER_SCENARIO)
    pipeline = _deployed_pipeline(scenario, model_dir, threads, flip, detector_flip)
    bands = _far_bands(pipeline, scenario) if far_band else None
    t0 = time.perf_counter()
    figures: dict[str, dict[str, float]] = {}
    split: dict[str, ErrorBreakdown] = {}
    for mode in modes:
        gen = SampleGenerator(scenario, mode, seed=seed)
        say(f"rendering {count} held-out {mode} views (seed {seed})")
        samples = [gen(i) for i in range(count)]
        figures[mode] = evaluate_set(pipeline, samples, far_bands=bands)
        if breakdown:
            split[mode] = error_breakdown(pipeline, samples)
    return KeypointEvaluation(figures, count * len(modes), time.perf_counter() - t0, split)


#: figure names that describe the detector; the others describe the keypoint network
DETECTOR_FIGURES: Final = ("AP@", "recall", "robots", "mean IoU", "false", "images with",
                           "detector ms", "views")


def record_evaluation(model_dir: Path | None, name: str, command: str,
                      figures: dict[str, dict[str, float]], views: int) -> list[Path]:
    """Write ``figures`` (set → name → value, as :class:`KeypointEvaluation` holds them) into
    the model cards (``.json`` + ``.md``) of ``model_dir``'s detector and keypoint network
    (default: the shipped ones) as evaluation ``name`` (an earlier one of that name replaced):
    the detector's figures (:data:`DETECTOR_FIGURES`) into its card, the rest into the keypoint
    network's, with the command, the date, the machine and the number of views. Values that are
    not finite are left out. Returns the cards written."""
    import datetime

    from edge_agent.model_cards import (
        DetectorCard,
        KeypointCard,
        card_machine,
        card_path,
        model_files,
    )

    base = {"command": command, "date": datetime.date.today().isoformat(),
            "machine": card_machine(), "views": int(views)}
    written = []
    det_path, kp_path = model_files(model_dir)
    for onnx, card_type, detector in ((det_path, DetectorCard, True),
                                      (kp_path, KeypointCard, False)):
        chosen = {set_name: {k: round(float(v), 4) for k, v in figs.items()
                             if k.startswith(DETECTOR_FIGURES) == detector
                             and np.isfinite(v)}
                  for set_name, figs in figures.items()}
        chosen = {k: v for k, v in chosen.items() if v}
        if not chosen:
            continue
        path = card_path(onnx)
        card = card_type.read(path)
        card.with_evaluation(name, {**base, "figures": chosen}).write(path.parent)
        written.append(path)
    return written


#: held-out seeds the calibration renders (the training's validation seeds, never the
#: evaluation's DEFAULT_SEED, so `evaluate keypoints` stays an independent check)
CALIBRATION_SEEDS = {"randomized": 1001, "site": 1002}


def calibration_errors(pipeline: RobotKeypointPipeline, samples: Sequence[Any],
                       min_score: float = 0.3,
                       correlated: list[np.ndarray] | None = None,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(errors in crop pixels, confidences) of the in-image keypoints of every robot the
    deployed pipeline finds (IoU >= 0.5 with the true box) in full rendered frames: the
    conditions the edge runs under, detector box errors included. ``correlated``: when given,
    each found robot's common error is appended to it (:func:`detection_common_error`)."""
    from edge_agent.crop import crop_transform

    card = pipeline.keypoints.card
    errs, confs = [], []
    for s in samples:
        robot = s.robots[0]
        if robot.bbox_xyxy is None:
            continue
        found = pipeline(s.image_rgb, min_score=min_score, max_robots=1)
        if not found or box_iou(found[0].bbox_xyxy, np.asarray(robot.bbox_xyxy)) < 0.5:
            continue
        tf = crop_transform(found[0].bbox_xyxy, card.input_w, card.input_h,
                            padding=card.crop_padding)
        err = np.linalg.norm(found[0].keypoints_px - robot.keypoints_px, axis=1) * tf.scale
        valid = np.asarray(robot.in_image, bool)
        errs.append(err[valid])
        confs.append(np.asarray(found[0].confidence)[valid])
        if correlated is not None and valid.sum() >= 3:
            correlated.append(detection_common_error(found[0].keypoints_px[valid],
                                                     np.asarray(robot.keypoints_px)[valid]))
    if not errs:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(errs), np.concatenate(confs)


def detection_common_error(found_px: np.ndarray, true_px: np.ndarray) -> np.ndarray:
    """(4,) the part of one detection's keypoint errors that all its keypoints share: the
    least-squares shift (dx, dy in image px) and relative scale about the true centroid, and
    the RMS per-axis error left after removing them: ``e_k ~ t + s (p_k - c)``. Gross
    keypoint errors (beyond 3 px and 3x the median rest) are left out of a second fit, as the
    backend's robust loss leaves them out of the pose."""
    c = true_px.mean(axis=0)
    d = true_px - c
    e = (found_px - true_px).reshape(-1)
    m = len(true_px)
    A = np.zeros((2 * m, 3))
    A[0::2, 0] = 1.0
    A[1::2, 1] = 1.0
    A[0::2, 2] = d[:, 0]
    A[1::2, 2] = d[:, 1]
    keep = np.ones(m, bool)
    x = np.zeros(3)
    for _ in range(2):
        rows = np.repeat(keep, 2)
        x, *_ = np.linalg.lstsq(A[rows], e[rows], rcond=None)
        rest = np.linalg.norm((e - A @ x).reshape(m, 2), axis=1)
        new_keep = rest <= max(3.0, 3.0 * float(np.median(rest)))
        if new_keep.sum() < 3 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    rest = (e - A @ x).reshape(m, 2)[keep]
    return np.array([x[0], x[1], x[2], math.sqrt(float(np.mean(rest ** 2)))])


#: share of the largest per-detection errors left out of the summary: swapped or missed
#: detections (measured up to 140 px), which the robust loss and the gates handle
COMMON_ERROR_TRIM: Final = 0.05


def _trimmed_rms(values: np.ndarray) -> float:
    v = np.sort(np.abs(values))
    keep = v[:max(1, round((1.0 - COMMON_ERROR_TRIM) * len(v)))]
    return float(np.sqrt(np.mean(keep ** 2)))


def common_error_summary(rows: Sequence[np.ndarray]) -> dict[str, float]:
    """RMS of the per-detection shift (both axes pooled, image px) and scale over
    :func:`detection_common_error` rows, the largest :data:`COMMON_ERROR_TRIM` left out, and
    the median rest: the figures ``SolverConfig.detection_shift_sigma_px`` and
    ``detection_scale_sigma`` take. (The spread is heavy-tailed: a median-based sigma would
    understate it, the plain RMS is ruled by a few gross failures.)"""
    arr = np.asarray(rows, np.float64).reshape(-1, 4)
    if not len(arr):
        return {}
    return {"shift_px": _trimmed_rms(arr[:, :2].ravel()),
            "scale": _trimmed_rms(arr[:, 2]),
            "rest_px": float(np.median(arr[:, 3])),
            "detections": float(len(arr))}


def calibrate_keypoints(model_dir: Path | None = None, *, count: int = 300,
                        scenario_path: Path | None = None, threads: int = 2,
                        bins: int = 8, write: bool = True,
                        progress: Callable[[str], None] | None = None
                        ) -> dict[str, list[float]]:
    """Measure the keypoint model's confidence → pixel-error table on ``count`` held-out
    views of each kind (:data:`CALIBRATION_SEEDS`) through the deployed pipeline, and (with
    ``write``) store it in the model card (``keypoints.json`` + ``.md``) of ``model_dir``
    (default: the shipped models; a folder without ``detector.onnx``, e.g. a keypoint training
    run, is paired with the shipped detector). Returns the table."""
    from edge_agent.metrics import sigma_calibration
    from edge_agent.model_cards import KeypointCard, card_path
    from simulation.dataset import SampleGenerator
    from simulation.scenario import PAPER_SCENARIO, load_scenario

    say = progress or (lambda line: None)
    scenario = load_scenario(scenario_path or PAPER_SCENARIO)
    model = scenario.site.robot_model(scenario.robot_id)
    from edge_agent.model_cards import model_files

    det_path, kp_path = model_files(model_dir)
    pipeline = RobotKeypointPipeline(det_path if det_path.is_file() else None, kp_path,
                                     threads=threads, keypoint_names=model.keypoint_names)
    errs, confs = [], []
    common: dict[str, list[np.ndarray]] = {}
    for mode, seed in CALIBRATION_SEEDS.items():
        say(f"rendering {count} held-out {mode} views (seed {seed}) for the calibration")
        gen = SampleGenerator(scenario, mode, seed=seed)
        e, c = calibration_errors(pipeline, [gen(i) for i in range(count)],
                                  correlated=common.setdefault(mode, []))
        errs.append(e)
        confs.append(c)
    table = sigma_calibration(np.concatenate(errs), np.concatenate(confs), bins=bins)
    for c, s in zip(table["confidence"], table["sigma_crop_px"], strict=True):
        say(f"  confidence {c:.3f}: sigma {s:.2f} crop px")
    for mode, rows in common.items():
        summary = common_error_summary(rows)
        if summary:
            say(f"  {mode} views: per-detection shift {summary['shift_px']:.2f} px, scale "
                f"{summary['scale']:.4f}, rest {summary['rest_px']:.2f} px per axis "
                f"({summary['detections']:.0f} detections): SolverConfig."
                "detection_shift_sigma_px / detection_scale_sigma")
    if write:
        path = card_path(pipeline.keypoints.path)
        card = KeypointCard.read(path)
        card = dataclasses.replace(card, sigma_calibration=table)
        card.write(path.parent)
        say(f"wrote the calibration into {path}")
    return table


#: distance bins of :func:`error_breakdown` (camera to robot, metres)
BREAKDOWN_DISTANCES_M: Final = (0.0, 3.0, 4.5, 6.0, 100.0)


@dataclasses.dataclass(frozen=True)
class ErrorBreakdown:
    """Where the keypoint error comes from, through the deployed pipeline (detector boxes) on
    rendered views, in frame pixels. ``per_keypoint``: name → figures (``n``, ``median px``,
    ``bias x px`` / ``bias y px``: the mean signed error, systematic; ``spread px``: the RMS
    per axis about that bias, random; ``occluded share``); ``per_distance``: bin label →
    (``n``: detections, ``median px``, ``shift px``, ``scale``, ``rest px``: the per-detection
    common shift and scale, which move the pose along the view, and the rest, which is what
    turns the heading, as :func:`detection_common_error` splits them)."""

    per_keypoint: dict[str, dict[str, float]]
    per_distance: dict[str, dict[str, float]]

    def lines(self) -> list[str]:
        out = []
        for name, figs in self.per_keypoint.items():
            out.append(f"keypoint {name}: "
                       + ", ".join(f"{k} {format_figure(v)}" for k, v in figs.items()))
        for name, figs in self.per_distance.items():
            out.append(f"distance {name}: "
                       + ", ".join(f"{k} {format_figure(v)}" for k, v in figs.items()))
        return out


def error_breakdown(pipeline: RobotKeypointPipeline, samples: Sequence[Any],
                    min_score: float = 0.3,
                    distances_m: Sequence[float] = BREAKDOWN_DISTANCES_M) -> ErrorBreakdown:
    """Per-keypoint bias and spread and per-distance error split of the robots the pipeline
    finds (IoU >= 0.5 with the true box) in ``samples``."""
    names = list(pipeline.keypoints.card.keypoint_names)
    k = len(names)
    errs, valid, occl, dist, common, med = [], [], [], [], [], []
    for s in samples:
        robot = s.robots[0] if s.robots else None
        if robot is None or robot.bbox_xyxy is None:
            continue
        found = pipeline(s.image_rgb, min_score=min_score, max_robots=1)
        if not found or box_iou(found[0].bbox_xyxy, np.asarray(robot.bbox_xyxy)) < 0.5:
            continue
        true = np.asarray(robot.keypoints_px, np.float64)
        e = np.asarray(found[0].keypoints_px, np.float64) - true
        ok = np.asarray(robot.in_image, bool)
        errs.append(e)
        valid.append(ok)
        occl.append(~np.asarray(robot.visible, bool))
        depth = np.asarray(robot.depth_m, np.float64)
        dist.append(float(np.median(depth[ok])) if ok.any() else math.nan)
        med.append(float(np.median(np.linalg.norm(e[ok], axis=1))) if ok.any() else math.nan)
        common.append(detection_common_error(found[0].keypoints_px[ok], true[ok])
                      if ok.sum() >= 3 else np.full(4, np.nan))
    e_all = np.asarray(errs).reshape(-1, k, 2)
    v_all = np.asarray(valid).reshape(-1, k)
    o_all = np.asarray(occl).reshape(-1, k)
    per_keypoint: dict[str, dict[str, float]] = {}
    for j, name in enumerate(names):
        ej = e_all[v_all[:, j], j]
        if not len(ej):
            continue
        bias = ej.mean(axis=0)
        per_keypoint[name] = {
            "n": float(len(ej)),
            "median px": float(np.median(np.linalg.norm(ej, axis=1))),
            "bias x px": float(bias[0]), "bias y px": float(bias[1]),
            "spread px": float(np.sqrt(np.mean((ej - bias) ** 2))),
            "occluded share": float(o_all[v_all[:, j], j].mean()),
        }
    d = np.asarray(dist)
    c = np.asarray(common).reshape(-1, 4)
    m = np.asarray(med)
    per_distance: dict[str, dict[str, float]] = {}
    for lo, hi in itertools.pairwise(distances_m):
        sel = (d >= lo) & (d < hi) & np.all(np.isfinite(c), axis=1)
        if not sel.any():
            continue
        label = f"{lo:g}-{hi:g} m" if hi < 100 else f">= {lo:g} m"
        summary = common_error_summary(list(c[sel]))
        per_distance[label] = {"n": float(sel.sum()), "median px": float(np.median(m[sel])),
                               "shift px": summary["shift_px"], "scale": summary["scale"],
                               "rest px": summary["rest_px"]}
    return ErrorBreakdown(per_keypoint, per_distance)


# --------------------------------------------------------------------------------------------
# held-out renderer variations
# --------------------------------------------------------------------------------------------

#: distance bands (metres on the floor from the camera to the robot) of the held-out recall
HELD_OUT_BANDS_M: Final = ((0.0, 4.0), (4.0, 6.0), (6.0, 8.0), (8.0, math.inf))
#: distance bands of the site views' recall (:func:`evaluate_set`): the far band's robots
#: (:mod:`edge_agent.far_band`) are those beyond ~8 m
SITE_BANDS_M: Final = ((0.0, 6.0), (6.0, 8.0), (8.0, 10.0), (10.0, math.inf))
#: a robot counts (for recall, false detections and AP) when at least this many of its
#: keypoints are visible; views with less of it are left out of the detector figures
MIN_VISIBLE_KEYPOINTS: Final = 3
#: the edge's operating detector threshold (what recall and false detections are counted at)
OPERATING_SCORE: Final = 0.3


def _band_label(lo: float, hi: float) -> str:
    return f"<{hi:g} m" if lo == 0 else (f">={lo:g} m" if math.isinf(hi) else f"{lo:g}-{hi:g} m")


@dataclasses.dataclass(frozen=True)
class HeldOutEvaluation:
    """Figures of the deployed models on the held-out renderer variations: name → value, in
    print order (see :func:`evaluate_held_out_set`)."""

    figures: dict[str, float]
    views: int
    wall_s: float

    def lines(self) -> list[str]:
        return [f"held-out {name} {format_figure(value)}" for name, value in self.figures.items()]


def evaluate_held_out_set(pipeline: RobotKeypointPipeline, samples: Sequence[Any],
                          distances_m: Sequence[float],
                          progress: Callable[[str], None] | None = None,
                          far_bands: Callable[[Any], FarBand | None] | None = None
                          ) -> dict[str, float]:
    """Detector and keypoint figures on rendered ``samples`` (robots ``distances_m`` away on
    the floor): recall at :data:`OPERATING_SCORE` per :data:`HELD_OUT_BANDS_M` band (a true
    box matched by a detection with IoU >= 0.5), false detections per image (detections at
    that score matching no robot), AP@0.5 (detections from 0.05), and the keypoints of the
    matched robots: median error of the visible ones (in the image, not occluded), PCK@2/5px,
    and the same over all in-image keypoints. A robot with fewer than
    :data:`MIN_VISIBLE_KEYPOINTS` visible keypoints is an ignore region (no view can measure
    its pose): not asked for, and a detection of it is not false; its view's other detections
    count as in any view (:func:`edge_agent.metrics.detection_ap`). ``far_bands``: each
    sample camera's far band (None: the whole frame only)."""
    say = progress or (lambda line: None)
    found_in_band: dict[str, list[bool]] = {_band_label(*b): [] for b in HELD_OUT_BANDS_M}
    dets, gts, hidden = [], [], []
    false_dets = 0
    images = 0
    err_vis, err_in = [], []
    det_ms, kp_ms = [], []
    step = max(1, len(samples) // 10)
    for n, (s, dist) in enumerate(zip(samples, distances_m, strict=True), start=1):
        robot = s.robots[0] if s.robots else None
        gt = None if robot is None or robot.bbox_xyxy is None else np.asarray(robot.bbox_xyxy)
        if n % step == 0 or n == len(samples):
            say(f"  evaluating {n}/{len(samples)} views")
        ignored = gt is not None and int(np.sum(robot.visible)) < MIN_VISIBLE_KEYPOINTS
        found = pipeline(s.image_rgb, min_score=0.05, max_robots=4,
                         far_band=None if far_bands is None else far_bands(s.camera))
        det_ms.append(pipeline.times.detector_ms)
        kp_ms.append(pipeline.times.keypoints_ms)
        images += 1
        dets.append(np.array([[*o.bbox_xyxy, o.score] for o in found]).reshape(-1, 5))
        gts.append(np.full(4, np.nan) if gt is None else gt)
        hidden.append(ignored)
        matched = None
        for o in found:  # best first
            if o.score < OPERATING_SCORE:
                break
            if gt is not None and matched is None and box_iou(o.bbox_xyxy, gt) >= 0.5:
                matched = o
            else:
                false_dets += 1
        if ignored:
            continue
        if gt is not None:
            for lo, hi in HELD_OUT_BANDS_M:
                if lo <= dist < hi:
                    found_in_band[_band_label(lo, hi)].append(matched is not None)
        if matched is not None and robot is not None:
            e = np.linalg.norm(matched.keypoints_px - robot.keypoints_px, axis=1)
            err_vis.append(e[np.asarray(robot.visible, bool)])
            err_in.append(e[np.asarray(robot.in_image, bool)])
    figures: dict[str, float] = {
        "views": float(len(samples)),
        f"robots ignored (< {MIN_VISIBLE_KEYPOINTS} keypoints visible)": float(sum(hidden))}
    all_found: list[bool] = []
    for label, hits in found_in_band.items():
        if hits:
            figures[f"recall {label}"] = float(np.mean(hits))
            figures[f"robots {label}"] = float(len(hits))
            all_found += hits
    within6 = found_in_band[_band_label(0.0, 4.0)] + found_in_band[_band_label(4.0, 6.0)]
    if within6:
        figures["recall within 6 m"] = float(np.mean(within6))
    if all_found:
        figures["recall"] = float(np.mean(all_found))
    figures["false detections per image"] = false_dets / max(images, 1)
    if dets:
        figures["AP@0.5"] = detection_ap(dets, np.array(gts).reshape(-1, 4),
                                         ignore=hidden)["AP@0.5"]
    if err_vis:
        ev = np.concatenate(err_vis)
        ei = np.concatenate(err_in)
        if ev.size:
            figures["visible keypoint median error px"] = float(np.median(ev))
            figures["visible PCK@2px"] = float(np.mean(ev <= 2.0))
            figures["visible PCK@5px"] = float(np.mean(ev <= 5.0))
        if ei.size:
            figures["in-image keypoint median error px"] = float(np.median(ei))
            figures["in-image PCK@5px"] = float(np.mean(ei <= 5.0))
    if det_ms:
        figures["detector ms"] = float(np.median(det_ms))
        figures["keypoints ms"] = float(np.median(kp_ms))
    return figures


def held_out_samples(count: int, scenario: Any, *, seed: int = DEFAULT_SEED,
                     progress: Callable[[str], None] | None = None,
                     ) -> tuple[list[Any], list[float]]:
    """``count`` views of ``scenario``'s robot rendered with
    :data:`simulation.scenes.HELD_OUT_VARIATION` (checked disjoint from the training
    randomization first) and the robot's distance in each."""
    from simulation.dataset import SampleGenerator
    from simulation.scenes import (
        HELD_OUT_VARIATION,
        RandomizationConfig,
        check_disjoint,
        robot_distance_m,
    )

    check_disjoint(RandomizationConfig(), HELD_OUT_VARIATION)
    say = progress or (lambda line: None)
    gen = SampleGenerator(scenario, "randomized", seed=seed, randomization=HELD_OUT_VARIATION)
    say(f"rendering {count} views of the held-out renderer variations (seed {seed})")
    samples: list[Any] = []
    batch = 8
    step = max(batch, (count // 10) // batch * batch)
    t0 = time.perf_counter()
    for start in range(0, count, batch):
        samples += gen.samples(list(range(start, min(count, start + batch))))
        if len(samples) % step == 0 or len(samples) == count:
            rate = len(samples) / max(time.perf_counter() - t0, 1e-9)
            say(f"  rendered {len(samples)}/{count} views ({rate:.1f} views/s)")
    distances = [robot_distance_m(s.camera, s.robot_pose) for s in samples]
    return samples, distances


def evaluate_held_out_variations(model_dir: Path | None = None, *, seed: int = DEFAULT_SEED,
                                 count: int = 200, scenario_path: Path | None = None,
                                 threads: int = 2, flip: bool | None = None,
                                 detector_flip: bool | None = None, far_band: bool = False,
                                 progress: Callable[[str], None] | None = None,
                                 ) -> HeldOutEvaluation:
    """Render ``count`` views of the held-out renderer variations from ``seed`` and evaluate
    the models of ``model_dir`` (default: the shipped ones) on them
    (:func:`evaluate_held_out_set`; ``far_band``: with each view's camera's far band)."""
    from simulation.scenario import PAPER_SCENARIO, load_scenario

    say = progress or (lambda line: None)
    scenario = load_scenario(scenario_path or PAPER_SCENARIO)
    pipeline = _deployed_pipeline(scenario, model_dir, threads, flip, detector_flip)
    t0 = time.perf_counter()
    samples, distances = held_out_samples(count, scenario, seed=seed, progress=say)
    say(f"running the detector and keypoint networks on {count} views")
    figures = evaluate_held_out_set(pipeline, samples, distances, progress=say,
                                    far_bands=_far_bands(pipeline, scenario) if far_band
                                    else None)
    return HeldOutEvaluation(figures, count, time.perf_counter() - t0)
