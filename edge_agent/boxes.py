"""Boxes ``[u_min, v_min, u_max, v_max]`` in pixels (edge coordinates): overlap, intersection
over union, and whether two boxes are one robot. The one place these are computed: the
detector's duplicate removal, the metrics and the evaluations all use them. A box with a
negative width or height has no area."""

from __future__ import annotations

import numpy as np


def box_overlap(a_xyxy: np.ndarray, b_xyxy: np.ndarray) -> tuple[float, float, float]:
    """(intersection, area of a, area of b) of two boxes, pixels²."""
    area_a = float(max(a_xyxy[2] - a_xyxy[0], 0.0) * max(a_xyxy[3] - a_xyxy[1], 0.0))
    area_b = float(max(b_xyxy[2] - b_xyxy[0], 0.0) * max(b_xyxy[3] - b_xyxy[1], 0.0))
    iw = min(a_xyxy[2], b_xyxy[2]) - max(a_xyxy[0], b_xyxy[0])
    ih = min(a_xyxy[3], b_xyxy[3]) - max(a_xyxy[1], b_xyxy[1])
    inter = float(iw * ih) if iw > 0.0 and ih > 0.0 else 0.0
    return inter, area_a, area_b


def box_iou(a_xyxy: np.ndarray, b_xyxy: np.ndarray) -> float:
    """Intersection over union of two boxes ``[u_min, v_min, u_max, v_max]`` (pixels)."""
    inter, area_a, area_b = box_overlap(a_xyxy, b_xyxy)
    union = area_a + area_b - inter
    return inter / union if union > 0.0 else 0.0


def iou_matrix(boxes_xyxy: np.ndarray) -> np.ndarray:
    """(n, n) intersection over union of every pair of (n, 4) boxes (as :func:`box_iou`)."""
    b = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    w = np.clip(np.minimum(b[:, None, 2], b[None, :, 2])
                - np.maximum(b[:, None, 0], b[None, :, 0]), 0.0, None)
    h = np.clip(np.minimum(b[:, None, 3], b[None, :, 3])
                - np.maximum(b[:, None, 1], b[None, :, 1]), 0.0, None)
    inter = w * h
    area = np.clip(b[:, 2] - b[:, 0], 0.0, None) * np.clip(b[:, 3] - b[:, 1], 0.0, None)
    union = area[:, None] + area[None, :] - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0.0)


def same_robot(a_xyxy: np.ndarray, b_xyxy: np.ndarray, iou: float, inside: float) -> bool:
    """Whether two boxes are one robot: IoU >= ``iou``, or the smaller box lies at least
    ``inside`` (a share of its area) within the other (another type's detector boxing only a
    part of the robot, e.g. the base of a taller one)."""
    inter, area_a, area_b = box_overlap(a_xyxy, b_xyxy)
    if inter <= 0.0:
        return False
    union = area_a + area_b - inter
    smaller = min(area_a, area_b)
    return (union > 0.0 and inter / union >= iou) or (smaller > 0.0 and inter / smaller >= inside)
