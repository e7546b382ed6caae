"""Draw docs/images/closed_loop_cameras.png: what the four cameras of the paper lab see with the
robot at a waypoint, and what the edge pipeline makes of it (box, keypoints with their sigma
circles) against the true keypoints.

    python scripts/closed_loop_picture.py [--out docs/images/closed_loop_cameras.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from backend_service.frame_set import best_detection
from lab.rendered_detections import RenderedDetections
from simulation.scenario import PAPER_SCENARIO, load_scenario


def _px(value: float) -> int:
    return round(float(value))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="docs/images/closed_loop_cameras.png")
    parser.add_argument("--waypoint", default="WP2", help="waypoint of traj3 (default WP2)")
    args = parser.parse_args()
    sc = load_scenario(PAPER_SCENARIO)
    det = RenderedDetections(sc, threads=2)
    wp = next(w for w in sc.trajectory("traj3", False) if w.name == args.waypoint)
    pose = np.array([wp.x, wp.y, wp.theta])
    rng = np.random.default_rng(0)
    tiles = []
    for cam in sorted(det.cameras):
        image = det.images.render(cam, pose, rng)
        msg = det.detect(cam, 0, pose, 0, rng)
        bgr = np.ascontiguousarray(image[:, :, ::-1])
        truth = det.visibility(cam, pose).uv
        d = best_detection(msg)
        text = f"{cam}: no robot"
        if d is not None:
            x0, y0, x1, y1 = (_px(v) for v in d.bbox_xyxy)
            cv2.rectangle(bgr, (x0, y0), (x1, y1), (0, 200, 255), 1)
            sig = d.keypoint_sigmas_px if d.keypoint_sigmas_px is not None else \
                np.ones(len(d.keypoints_px))
            for (u, v), s in zip(d.keypoints_px, sig, strict=True):
                cv2.circle(bgr, (_px(u), _px(v)), max(1, _px(s)),
                           (60, 60, 255), 1, cv2.LINE_AA)
            err = np.linalg.norm(d.keypoints_px - truth, axis=1)
            text = f"{cam}: median keypoint error {np.median(err):.1f} px"
        for u, v in truth:
            if np.isfinite(u) and np.isfinite(v):
                cv2.circle(bgr, (_px(u), _px(v)), 1, (60, 220, 60), -1)
        if d is not None:  # a 3x inset of the robot in the top-right corner
            cx, cy = (d.bbox_xyxy[0] + d.bbox_xyxy[2]) / 2, (d.bbox_xyxy[1] + d.bbox_xyxy[3]) / 2
            half = int(max(d.bbox_xyxy[2] - d.bbox_xyxy[0], d.bbox_xyxy[3] - d.bbox_xyxy[1]) * 0.6)
            h, w = bgr.shape[:2]
            ys, xs = max(0, int(cy) - half), max(0, int(cx) - half)
            patch = bgr[ys:min(h, int(cy) + half), xs:min(w, int(cx) + half)].copy()
            scale = min(3.0, (h * 0.55) / max(patch.shape[0], 1))
            inset = cv2.resize(patch, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
            ih, iw = inset.shape[:2]
            bgr[4:4 + ih, w - 4 - iw:w - 4] = inset
            cv2.rectangle(bgr, (w - 5 - iw, 3), (w - 3, 5 + ih), (255, 255, 255), 1)
        cv2.putText(bgr, text, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2,
                    cv2.LINE_AA)
        tiles.append(bgr)
    grid = np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:4])])
    grid = cv2.resize(grid, None, fx=0.75, fy=0.75, interpolation=cv2.INTER_AREA)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, grid)
    print(f"wrote {args.out} ({grid.shape[1]}x{grid.shape[0]})")


if __name__ == "__main__":
    main()
