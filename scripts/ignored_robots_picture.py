"""Draw docs/images/ignored_robots.jpg: every robot of the paper lab's site views (held-out seed
4242) that shows fewer than 3 of its keypoints, the robots `smartedge evaluate keypoints` treats
as ignore regions (edge_agent.metrics.detection_ap). One tile per robot: the frame around its
true box, enlarged; green the true box of its visible pixels, orange what the shipped edge
pipeline reports (with the far band, as on a GPU), with its score. The caption gives the view,
the camera, visible keypoints, the box's size in frame pixels and the robot's floor distance.

    python scripts/ignored_robots_picture.py [--out docs/images/ignored_robots.jpg]
        [--seed 4242] [--views 300]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from edge_agent.boxes import box_iou
from edge_agent.models import RobotKeypointPipeline
from lab.evaluation.keypoints import MIN_VISIBLE_KEYPOINTS, CameraFarBands
from simulation.dataset import SampleGenerator
from simulation.scenario import PAPER_SCENARIO, load_scenario
from simulation.scenes import robot_distance_m

GREEN = (60, 200, 60)  # BGR
ORANGE = (0, 140, 255)
#: tile size (pixels) and the frame region each tile shows at least (frame pixels)
TILE_W, TILE_H = 320, 200
MIN_REGION_W = 160


def tile(image_rgb: np.ndarray, truth: np.ndarray, found: list, caption: str) -> np.ndarray:
    """The frame around ``truth`` (at least MIN_REGION_W wide, 4x the box), enlarged to the
    tile, with the true and reported boxes and a caption strip."""
    h, w = image_rgb.shape[:2]
    cx, cy = (truth[0] + truth[2]) / 2, (truth[1] + truth[3]) / 2
    region_w = max(MIN_REGION_W, 4.0 * (truth[2] - truth[0]), 4.0 * (truth[3] - truth[1]) *
                   TILE_W / TILE_H)
    region_w = min(region_w, w)
    region_h = region_w * TILE_H / TILE_W
    x0 = int(np.clip(cx - region_w / 2, 0, w - region_w))
    y0 = int(np.clip(cy - region_h / 2, 0, max(0, h - region_h)))
    x1, y1 = int(x0 + region_w), int(min(h, y0 + region_h))
    zoom = TILE_W / (x1 - x0)
    bgr = np.ascontiguousarray(image_rgb[y0:y1, x0:x1, ::-1])
    out = np.zeros((TILE_H + 36, TILE_W, 3), np.uint8)
    view = cv2.resize(bgr, (TILE_W, min(TILE_H, round((y1 - y0) * zoom))),
                      interpolation=cv2.INTER_NEAREST)
    out[:view.shape[0]] = view

    def draw(box: np.ndarray, colour: tuple[int, int, int]) -> tuple[int, int]:
        bx = ((np.asarray(box[:4], float) - [x0, y0, x0, y0]) * zoom).round().astype(int)
        cv2.rectangle(out, (bx[0], bx[1]), (max(bx[2], bx[0] + 1), max(bx[3], bx[1] + 1)),
                      colour, 2)
        return int(bx[0]), int(bx[1])

    draw(truth, GREEN)
    for obs in found:
        tx, ty = draw(obs.bbox_xyxy, ORANGE)
        cv2.putText(out, f"{obs.score:.2f}", (max(2, tx), max(14, ty - 4)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, ORANGE, 1, cv2.LINE_AA)
    for n, line in enumerate(caption.split("\n")):
        cv2.putText(out, line, (4, TILE_H + 14 + 16 * n), cv2.FONT_HERSHEY_SIMPLEX, 0.42,
                    (255, 255, 255), 1, cv2.LINE_AA)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("docs/images/ignored_robots.jpg"))
    parser.add_argument("--seed", type=int, default=4242)
    parser.add_argument("--views", type=int, default=300)
    args = parser.parse_args()
    scenario = load_scenario(PAPER_SCENARIO)
    model = scenario.site.robot_model(scenario.robot_id)
    pipeline = RobotKeypointPipeline.for_robot(model, threads=2)
    bands = CameraFarBands(pipeline, model.height_m)
    gen = SampleGenerator(scenario, "site", seed=args.seed)
    tiles = []
    for i in range(args.views):
        s = gen(i)
        robot = s.robots[0]
        if robot.bbox_xyxy is None or int(np.sum(robot.visible)) >= MIN_VISIBLE_KEYPOINTS:
            continue
        found = pipeline(s.image_rgb, min_score=0.05, far_band=bands(s.camera))
        truth = np.asarray(robot.bbox_xyxy, float)
        hit = max((box_iou(o.bbox_xyxy, truth) for o in found), default=0.0)
        bw, bh = truth[2] - truth[0], truth[3] - truth[1]
        dist = robot_distance_m(s.camera, s.robot_pose)
        verdict = f"found, IoU {hit:.2f}" if hit >= 0.5 else "not found"
        caption = (f"view {i} {s.camera.camera_id}: {int(np.sum(robot.visible))} kp visible\n"
                   f"box {bw:.0f}x{bh:.0f} px, {dist:.1f} m; {verdict}")
        tiles.append(tile(s.image_rgb, truth, found, caption))
        print(f"view {i}: {caption.replace(chr(10), '; ')}")
    if not tiles:
        raise SystemExit(f"no robot with fewer than {MIN_VISIBLE_KEYPOINTS} keypoints visible "
                         f"in {args.views} views of seed {args.seed}")
    cols = 4
    blank = np.zeros_like(tiles[0])
    rows = [np.hstack(tiles[r:r + cols] + [blank] * (cols - len(tiles[r:r + cols])))
            for r in range(0, len(tiles), cols)]
    grid = np.vstack(rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), grid, [cv2.IMWRITE_JPEG_QUALITY, 88])
    print(f"wrote {args.out} ({len(tiles)} robots)")


if __name__ == "__main__":
    main()
