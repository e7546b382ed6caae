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
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from edge_agent.metrics import box_iou, detection_ap, keypoint_metrics
from edge_agent.models import RobotKeypointPipeline

#: the default held-out seed (the shipped models train on seeds 1-2, validate on 1001-1002)
DEFAULT_SEED = 4242


@dataclasses.dataclass(frozen=True)
class KeypointEvaluation:
    """Figures per set (``randomized``, ``site``): name → value, in print order."""

    figures: dict[str, dict[str, float]]
    views: int
    wall_s: float

    def lines(self) -> list[str]:
        out = []
        for set_name, figs in self.figures.items():
            for name, value in figs.items():
                out.append(f"{set_name} {name} {_fmt(value)}")
        return out


def _fmt(value: float) -> str:
    if not np.isfinite(value):
        return "n/a"
    if float(value).is_integer() and abs(value) >= 1:
        return str(int(value))
    return f"{value:.3f}" if abs(value) < 10 else f"{value:.1f}"


def evaluate_set(pipeline: RobotKeypointPipeline, samples: Sequence[Any],
                 min_score: float = 0.05) -> dict[str, float]:
    """Figures on rendered samples (each a :class:`simulation.dataset.Sample`)."""
    dets, gts = [], []
    err_det, conf_det, valid_det, vis_det = [], [], [], []
    err_gt, conf_gt, valid_gt, vis_gt = [], [], [], []
    det_ms, kp_ms = [], []
    for s in samples:
        robot = s.robots[0]
        found = pipeline(s.image_rgb, min_score=min_score, max_robots=4)
        det_ms.append(pipeline.times.detector_ms)
        kp_ms.append(pipeline.times.keypoints_ms)
        boxes = np.array([[*o.bbox_xyxy, o.score] for o in found]).reshape(-1, 5)
        dets.append(boxes)
        gt = np.full(4, np.nan) if robot.bbox_xyxy is None else np.asarray(robot.bbox_xyxy)
        gts.append(gt)
        if robot.bbox_xyxy is None:
            continue
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


def evaluate_keypoints(model_dir: Path | None = None, *, seed: int = DEFAULT_SEED,
                       count: int = 300, modes: Sequence[str] = ("randomized", "site"),
                       scenario_path: Path | None = None, threads: int = 2,
                       progress: Callable[[str], None] | None = None) -> KeypointEvaluation:
    """Render ``count`` held-out views per mode from ``seed`` and evaluate the models of
    ``model_dir`` (default: the shipped ones)."""
    from simulation.dataset import SampleGenerator
    from simulation.scenario import PAPER_SCENARIO, load_scenario

    say = progress or (lambda line: None)
    scenario = load_scenario(scenario_path or PAPER_SCENARIO)
    model = scenario.site.robot_model(scenario.robot_id)
    pipeline = RobotKeypointPipeline.from_folder(model_dir, threads=threads,
                                     keypoint_names=model.keypoint_names)
    t0 = time.perf_counter()
    figures: dict[str, dict[str, float]] = {}
    for mode in modes:
        gen = SampleGenerator(scenario, mode, seed=seed)
        say(f"rendering {count} held-out {mode} views (seed {seed})")
        samples = [gen(i) for i in range(count)]
        figures[mode] = evaluate_set(pipeline, samples)
    return KeypointEvaluation(figures, count * len(modes), time.perf_counter() - t0)
