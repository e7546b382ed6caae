"""Draw docs/images/held_out_variations.png: views rendered with renderer settings never used in
training (simulation.scenes.HELD_OUT_VARIATION) and what the shipped edge pipeline makes of them:
the true box (green) and keypoints (green dots), the reported box (orange) and keypoints (orange
crosses), the robot's distance from the camera and the detection score. Boxes the keypoint
network does not confirm are not reported (docs/models.md), so a view may show none.

    python scripts/held_out_picture.py [--out docs/images/held_out_variations.png]
        [--seed 4242] [--views 8] [--columns 4]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from edge_agent.boxes import box_iou
from edge_agent.models import RobotKeypointPipeline
from lab.evaluation.keypoints import held_out_samples
from simulation.scenario import PAPER_SCENARIO, load_scenario

GREEN = (60, 200, 60)  # BGR
ORANGE = (0, 140, 255)


def _pt(uv: np.ndarray, scale: float) -> tuple[int, int]:
    return round(float(uv[0]) * scale), round(float(uv[1]) * scale)


def tile(sample: object, distance_m: float, pipeline: RobotKeypointPipeline,
         width: int) -> np.ndarray:
    """One view at ``width`` pixels wide with the truth and the pipeline's output drawn."""
    image = sample.image_rgb  # type: ignore[attr-defined]
    scale = width / image.shape[1]
    bgr = cv2.resize(np.ascontiguousarray(image[:, :, ::-1]),
                     (width, round(image.shape[0] * scale)), interpolation=cv2.INTER_AREA)
    robot = sample.robots[0] if sample.robots else None  # type: ignore[attr-defined]
    truth_box = None
    if robot is not None and robot.bbox_xyxy is not None:
        truth_box = np.asarray(robot.bbox_xyxy, np.float64)
        cv2.rectangle(bgr, _pt(truth_box[:2], scale), _pt(truth_box[2:], scale), GREEN, 1)
        for uv, seen in zip(robot.keypoints_px, robot.visible, strict=True):
            if seen:
                cv2.circle(bgr, _pt(uv, scale), 2, GREEN, -1, cv2.LINE_AA)
    found = pipeline(image)
    label = f"{distance_m:.1f} m"
    for obs in found:
        box = obs.bbox_xyxy
        cv2.rectangle(bgr, _pt(box[:2], scale), _pt(box[2:], scale), ORANGE, 1)
        for uv in obs.keypoints_px:
            cv2.drawMarker(bgr, _pt(uv, scale), ORANGE, cv2.MARKER_CROSS, 5, 1, cv2.LINE_AA)
        iou = box_iou(box, truth_box) if truth_box is not None else 0.0
        label += f"  score {obs.score:.2f} IoU {iou:.2f}"
    if not found:
        label += "  nothing reported"
    cv2.rectangle(bgr, (0, 0), (width, 16), (0, 0, 0), -1)
    cv2.putText(bgr, label, (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                cv2.LINE_AA)
    return bgr


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="docs/images/held_out_variations.png")
    parser.add_argument("--seed", type=int, default=4242)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--columns", type=int, default=4)
    parser.add_argument("--width", type=int, default=424, help="tile width in pixels")
    args = parser.parse_args()
    samples, distances = held_out_samples(args.views, load_scenario(PAPER_SCENARIO),
                                          seed=args.seed)
    pipeline = RobotKeypointPipeline(threads=2)
    tiles = [tile(s, d, pipeline, args.width) for s, d in zip(samples, distances, strict=True)]
    h = max(t.shape[0] for t in tiles)
    tiles = [cv2.copyMakeBorder(t, 0, h - t.shape[0], 0, 0, cv2.BORDER_CONSTANT) for t in tiles]
    while len(tiles) % args.columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[i:i + args.columns]) for i in range(0, len(tiles), args.columns)]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.vstack(rows))
    print(f"wrote {out} ({len(samples)} views, seed {args.seed})")


if __name__ == "__main__":
    main()
