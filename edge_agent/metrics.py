"""Held-out metrics for the detector, the keypoint network and the segmentation network (numpy
only, no torch: the ONNX evaluation in ``smartedge evaluate keypoints`` uses them too)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from edge_agent.boxes import box_iou


def detection_ap(detections: Sequence[np.ndarray], gt_boxes: np.ndarray,
                 iou_threshold: float = 0.5,
                 ignore: Sequence[bool] | np.ndarray | None = None) -> dict[str, float]:
    """AP at ``iou_threshold`` (all-point interpolated) for one class with at most one true
    box per image (``gt_boxes`` (N, 4), NaN row: none); also the mean IoU of the best-scoring
    detection on images with a robot and the false-positive rate on images without one.

    ``ignore`` (N,): true boxes that are neither to be found nor a false positive when found
    (the "ignore" / "don't care" regions of COCO, KITTI and CityPersons; here a robot too
    hidden for any view to measure it). Such a box is not counted among the robots, the best
    detection matching it leaves the ranking, and every other detection of its image counts as
    usual. With ``ignore`` the result also holds ``robots ignored``."""
    if ignore is not None and len(ignore) != len(gt_boxes):
        raise ValueError(f"ignore has {len(ignore)} flags for {len(gt_boxes)} images")
    scores: list[float] = []
    hits: list[bool] = []
    ious: list[float] = []
    fp_empty = 0
    n_gt = 0
    n_empty = 0
    n_ignored = 0
    for n, (dets, gt) in enumerate(zip(detections, gt_boxes, strict=True)):
        has_gt = bool(np.all(np.isfinite(gt)))
        ignored = has_gt and ignore is not None and bool(ignore[n])
        n_ignored += ignored
        counted = has_gt and not ignored
        n_gt += counted
        n_empty += not has_gt
        matched = False
        for i, d in enumerate(dets):  # best first
            iou = box_iou(d[:4], gt) if has_gt else 0.0
            if counted and i == 0:
                ious.append(iou)
            hit = has_gt and not matched and iou >= iou_threshold
            matched |= hit
            if hit and ignored:
                continue  # found a robot that is not asked for: not in the ranking
            scores.append(float(d[4]))
            hits.append(hit)
        if counted and len(dets) == 0:
            ious.append(0.0)
        if not has_gt and len(dets) and float(dets[0][4]) >= 0.3:
            fp_empty += 1
    order = np.argsort(-np.asarray(scores, float)) if scores else np.zeros(0, int)
    tp = np.asarray(hits, float)[order]
    if n_gt == 0:
        ap = float("nan")
    else:
        ctp, cfp = np.cumsum(tp), np.cumsum(1 - tp)
        recall = ctp / n_gt
        precision = ctp / np.maximum(ctp + cfp, 1e-9)
        # all-point interpolation: precision envelope over recall steps
        mrec = np.concatenate([[0.0], recall, [1.0]])
        mpre = np.concatenate([[1.0], precision, [0.0]])
        mpre = np.maximum.accumulate(mpre[::-1])[::-1]
        steps = np.flatnonzero(mrec[1:] != mrec[:-1])
        ap = float(np.sum((mrec[steps + 1] - mrec[steps]) * mpre[steps + 1]))
    out = {
        "AP@0.5": ap,
        "mean IoU": float(np.mean(ious)) if ious else float("nan"),
        "false positive rate (no robot, score >= 0.3)": fp_empty / n_empty if n_empty else 0.0,
        "images with robot": float(n_gt),
    }
    if ignore is not None:
        out["robots ignored"] = float(n_ignored)
    return out


def keypoint_metrics(err_px: np.ndarray, confidence: np.ndarray, valid: np.ndarray,
                     visible: np.ndarray) -> dict[str, float]:
    """Pixel-error figures over the ``valid`` (N, K) keypoints: median/mean, PCK at 2 and 5 px,
    the same for occluded (not ``visible``) keypoints, and the confidence calibration: median
    error in the lowest and highest confidence third and their Spearman correlation (negative:
    a low confidence means a worse keypoint)."""
    e = err_px[valid]
    if e.size == 0:
        return {"keypoints": 0.0}
    c = confidence[valid]
    occ = err_px[valid & ~visible]
    vis = err_px[valid & visible]
    out = {
        "median error px": float(np.median(e)),
        "mean error px": float(np.mean(e)),
        "PCK@2px": float(np.mean(e <= 2.0)),
        "PCK@5px": float(np.mean(e <= 5.0)),
        "visible median error px": float(np.median(vis)) if vis.size else float("nan"),
        "occluded median error px": float(np.median(occ)) if occ.size else float("nan"),
        "occluded PCK@5px": float(np.mean(occ <= 5.0)) if occ.size else float("nan"),
        "keypoints": float(e.size),
        "occluded share": float(occ.size / e.size),
    }
    lo, hi = np.quantile(c, [1 / 3, 2 / 3])
    out["median error px, low-confidence third"] = float(np.median(e[c <= lo]))
    out["median error px, high-confidence third"] = float(np.median(e[c >= hi]))
    out["confidence-error Spearman"] = spearman(c, e)
    return out


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 3:
        return float("nan")
    ra, rb = _average_ranks(np.asarray(a, float)), _average_ranks(np.asarray(b, float))
    ra -= ra.mean()
    rb -= rb.mean()
    den = np.sqrt((ra ** 2).sum() * (rb ** 2).sum())
    return float((ra * rb).sum() / den) if den > 0 else float("nan")


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 0..n-1 with ties given their average rank (as scipy.stats.rankdata - 1)."""
    order = np.argsort(x, kind="stable")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(len(x), dtype=float)
    _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    sums = np.bincount(inverse, weights=ranks)
    return sums[inverse] / counts[inverse]


def sigma_calibration(err_crop_px: np.ndarray, confidence: np.ndarray, bins: int = 8,
                      min_per_bin: int = 20) -> dict[str, list[float]]:
    """How wrong a keypoint is, given its confidence: the per-axis 1-sigma error (crop pixels)
    of the keypoints in each of ``bins`` confidence quantile bins, ``sqrt(mean(|e|^2) / 2)``
    (``|e|`` the 2-D distance, so u and v each have this RMS), made non-increasing in
    confidence (a more confident keypoint is never reported as less certain).

    ``err_crop_px`` / ``confidence``: (N,) 2-D distance errors and confidences over the valid
    keypoints of held-out crops. Returns
    ``{"confidence": bin medians (ascending), "sigma_crop_px": RMS per bin}`` for
    :func:`sigma_from_confidence`; empty lists when there are too few keypoints."""
    e = np.asarray(err_crop_px, np.float64).reshape(-1)
    c = np.asarray(confidence, np.float64).reshape(-1)
    ok = np.isfinite(e) & np.isfinite(c)
    e, c = e[ok], c[ok]
    bins = max(1, min(bins, len(e) // max(min_per_bin, 1)))
    if len(e) < max(min_per_bin, 1):
        return {"confidence": [], "sigma_crop_px": []}
    order = np.argsort(c, kind="stable")
    centres, sigmas = [], []
    for part in np.array_split(order, bins):
        centres.append(float(np.median(c[part])))
        sigmas.append(float(np.sqrt(np.mean(e[part] ** 2) / 2.0)))
    # non-increasing in confidence: each bin at most the RMS of the bins below it
    sig = np.minimum.accumulate(np.array(sigmas))
    return {"confidence": centres, "sigma_crop_px": [float(v) for v in sig]}


def sigma_from_confidence(confidence: np.ndarray, calibration: dict[str, list[float]]
                          ) -> np.ndarray | None:
    """Per-keypoint 1-sigma error (crop pixels) for ``confidence`` from a
    :func:`sigma_calibration` table (linear between bin medians, held flat outside); ``None``
    when the table is empty."""
    xs = np.asarray(calibration.get("confidence", []), np.float64)
    ys = np.asarray(calibration.get("sigma_crop_px", []), np.float64)
    if xs.size == 0 or xs.size != ys.size:
        return None
    return np.interp(np.asarray(confidence, np.float64), xs, ys)


def confusion_matrix(true_ids: np.ndarray, predicted_ids: np.ndarray, num_classes: int
                     ) -> np.ndarray:
    """(num_classes, num_classes) int64 pixel counts, row = true class, column = predicted, of
    two equal-shape integer class images (any leading shape); ids outside ``[0, num_classes)``
    are a ``ValueError``."""
    t = np.asarray(true_ids).astype(np.int64).ravel()
    p = np.asarray(predicted_ids).astype(np.int64).ravel()
    if t.shape != p.shape:
        raise ValueError(f"class images of {np.shape(true_ids)} and {np.shape(predicted_ids)}")
    if t.size and (min(t.min(), p.min()) < 0 or max(t.max(), p.max()) >= num_classes):
        raise ValueError(f"class ids outside [0, {num_classes})")
    return np.bincount(t * num_classes + p, minlength=num_classes ** 2).reshape(
        num_classes, num_classes)


def segmentation_metrics(confusion: np.ndarray, class_names: Sequence[str]
                         ) -> dict[str, float]:
    """Figures of a :func:`confusion_matrix`: ``pixel accuracy``, ``mean IoU`` over the classes
    present (at least one true pixel), ``IoU <name>`` of each present class (intersection over
    union of true and predicted pixels) and ``pixels``."""
    cm = np.asarray(confusion, np.float64)
    total = cm.sum()
    tp = np.diag(cm)
    true_px, pred_px = cm.sum(1), cm.sum(0)
    present = true_px > 0
    iou = tp / np.maximum(true_px + pred_px - tp, 1.0)
    out = {"pixel accuracy": float(tp.sum() / total) if total else float("nan"),
           "mean IoU": float(np.mean(iou[present])) if present.any() else float("nan")}
    for i in np.flatnonzero(present):
        out[f"IoU {class_names[i]}"] = float(iou[i])
    out["pixels"] = float(total)
    return out
