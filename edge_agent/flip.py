"""Test-time flip: a network run on the mirrored frame or crop too, and the two answers fused
(boxes matched across the mirror, keypoints swapped with their left/right partners).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final

import numpy as np

from edge_agent.boxes import iou_matrix
from edge_agent.model_cards import ModelError

#: a box of the frame and a box of its mirror image (mapped back) at least this IoU apart are
#: one robot (:func:`fuse_flipped_detections`)
FLIP_MATCH_IOU: Final = 0.5


def mirror_boxes(boxes: np.ndarray, width: int) -> np.ndarray:
    """(n, 5) boxes ``x0, y0, x1, y1, score`` of an image → those of its left/right mirror
    image ``width`` pixels wide (OpenCV centre convention: ``u -> width - 1 - u``)."""
    out = boxes.copy()
    out[:, 0] = width - 1 - boxes[:, 2]
    out[:, 2] = width - 1 - boxes[:, 0]
    return out


def fuse_flipped_detections(direct: np.ndarray, mirrored: np.ndarray, min_score: float,
                            max_detections: int, iou: float = FLIP_MATCH_IOU) -> np.ndarray:
    """The boxes of a frame (``direct``) and of its mirror image mapped back (``mirrored``),
    both (n, 5) ``x0, y0, x1, y1, score`` → one (m, 5) list, best first.

    Boxes are clustered greedily, highest score first, at ``iou``. A cluster's score is the
    mean of the two passes' best scores in it (0 for a pass that did not find it), its box the
    score-weighted mean of those two boxes. A box only one pass finds therefore keeps half its
    score: what the network sees in one orientation only (a wall corner that looks like a
    robot's side) falls below the floor, a robot both passes see keeps its score. The result
    does not depend on which pass is called direct, so the detections of a mirrored frame are
    the mirrored detections."""
    pool = np.concatenate([direct, mirrored]).reshape(-1, 5)
    source = np.repeat([0, 1], [len(direct), len(mirrored)])
    order = np.argsort(-pool[:, 4], kind="stable")
    pool, source = pool[order], source[order]
    near = iou_matrix(pool[:, :4]) >= iou
    used = np.zeros(len(pool), bool)
    fused: list[np.ndarray] = []
    for i in range(len(pool)):
        if used[i]:
            continue
        members = np.flatnonzero(near[i] & ~used)
        used[members] = True
        # each pass's highest-scoring box in the cluster (members are best first)
        firsts = [members[source[members] == p][0] for p in (0, 1)
                  if np.any(source[members] == p)]
        rows = pool[firsts]
        weights = rows[:, 4]
        box = (rows[:, :4] * weights[:, None]).sum(axis=0) / weights.sum()
        fused.append(np.append(box, weights.sum() / 2.0))
    out = np.array(fused).reshape(-1, 5)
    out = out[out[:, 4] >= min_score]
    return out[np.argsort(-out[:, 4], kind="stable")][:max_detections]


def mirror_permutation(keypoint_names: Sequence[str]) -> np.ndarray:
    """(K,) index of each keypoint's mirror partner under a left/right flip of the image:
    ``left`` and ``right`` swapped in the name (``front_left_top`` ↔ ``front_right_top``), a
    name with neither is its own partner. Raises :class:`ModelError` when a partner is
    missing (the robot's keypoints are not left/right paired)."""
    names = list(keypoint_names)
    index = {n: i for i, n in enumerate(names)}
    perm = np.arange(len(names))
    for i, name in enumerate(names):
        parts = name.split("_")
        if "left" not in parts and "right" not in parts:
            continue
        mirrored = "_".join({"left": "right", "right": "left"}.get(w, w) for w in parts)
        if mirrored not in index:
            raise ModelError(f"keypoint {name!r} has no mirror partner {mirrored!r} in "
                             f"{names}: flipping needs left/right pairs")
        perm[i] = index[mirrored]
    return perm
