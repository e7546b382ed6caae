"""Rendered samples as a COCO keypoints dataset: the frames written as PNG in the capture layout
(``<camera>/<stamp_ns>.png``) and the renderer's exact labels as the annotations
(:mod:`core.coco`), so the tools and the evaluation that read a lab's own frames read renders
the same way.

Labels: ``bbox`` the robot's visible pixels (the renderer's instance mask), keypoints visible
(2) where the renderer sees them, occluded (1) where they are in the image but hidden, not
labelled (0) outside the image; ``label_source`` ``"render"``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from core.coco import CocoAnnotation, CocoCategory, CocoDataset, CocoImage, write_dataset


def samples_to_coco(samples: Sequence[Any], out_dir: str | Path, robot_model: str,
                    keypoint_names: Sequence[str], *, t0_ns: int = 1_700_000_000_000_000_000,
                    period_ns: int = 100_000_000) -> Path:
    """Write ``samples`` (:class:`simulation.dataset.Sample`) under ``out_dir`` with
    ``out_dir/labels.json``; sample ``i`` is stamped ``t0_ns + i * period_ns``. Returns the
    dataset file."""
    out = Path(out_dir)
    images, annotations = [], []
    for i, s in enumerate(samples):
        stamp = t0_ns + i * period_ns
        cam = getattr(s.camera, "camera_id", "") or "render"
        rel = f"{cam}/{stamp}.png"
        (out / cam).mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(out / rel), cv2.cvtColor(s.image_rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"{out / rel}: cannot write")
        h, w = s.image_rgb.shape[:2]
        images.append(CocoImage(i + 1, rel, w, h, cam, stamp))
        for r in s.robots:
            if r.bbox_xyxy is None:
                continue
            x0, y0, x1, y1 = (float(v) for v in r.bbox_xyxy)
            x0, y0 = max(x0, 0.0), max(y0, 0.0)
            x1, y1 = min(x1, float(w)), min(y1, float(h))
            vis = np.where(r.visible, 2, np.where(r.in_image, 1, 0))
            kp = np.column_stack([np.where(vis[:, None] > 0, r.keypoints_px, 0.0), vis])
            annotations.append(CocoAnnotation(len(annotations) + 1, i + 1, 1,
                                              (x0, y0, x1 - x0, y1 - y0), kp, r.robot_id,
                                              "render"))
    path = out / "labels.json"
    write_dataset(CocoDataset(tuple(images), tuple(annotations),
                              (CocoCategory(1, robot_model, tuple(keypoint_names)),),
                              {"description": "rendered samples, exact labels"}), path)
    return path
