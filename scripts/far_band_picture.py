"""Draw docs/images/far_band.jpg: site-camera views of the paper lab (held-out seed 4242) with a
robot 10-14 m away, through the shipped edge pipeline without and with the camera's far band
(edge_agent/far_band.py). Each row: left the whole frame only, right with the band (its
rows tinted and outlined blue). Green: the true box of the robot's visible pixels; orange: what
the edge reports, with its score; the crop below each view enlarges the robot.

    python scripts/far_band_picture.py [--out docs/images/far_band.jpg] [--seed 4242]
        [--views 180,97,26]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from edge_agent.boxes import box_iou
from edge_agent.far_band import FarBand
from edge_agent.models import RobotKeypointPipeline
from edge_agent.networks import RobotObservation
from edge_agent.pipeline import camera_far_band
from simulation.dataset import SampleGenerator
from simulation.scenario import PAPER_SCENARIO, load_scenario
from simulation.scenes import robot_distance_m

GREEN = (60, 200, 60)  # BGR
ORANGE = (0, 140, 255)
BLUE = (255, 120, 0)
#: each view is drawn this wide; the enlarged crop around the robot below it as wide
WIDTH = 480


def _box(bgr: np.ndarray, box: np.ndarray, colour: tuple[int, int, int], scale: float,
         dx: float = 0.0, dy: float = 0.0, thickness: int = 2) -> None:
    x0, y0, x1, y1 = ((np.asarray(box[:4], float) - [dx, dy, dx, dy]) * scale).round().astype(int)
    cv2.rectangle(bgr, (x0, y0), (x1, y1), colour, thickness)


def panel(image_rgb: np.ndarray, truth: np.ndarray, found: list[RobotObservation],
          band: FarBand | None, title: str) -> np.ndarray:
    """The view (band shaded when given) over an enlarged crop around the true box."""
    scale = WIDTH / image_rgb.shape[1]
    bgr = np.ascontiguousarray(image_rgb[:, :, ::-1])
    view = cv2.resize(bgr, (WIDTH, round(image_rgb.shape[0] * scale)),
                      interpolation=cv2.INTER_AREA)
    if band is not None:  # the band's rows, lightly tinted and outlined
        v0, v1 = round(band.v0 * scale), round(band.v1 * scale)
        view[v0:v1] = (0.8 * view[v0:v1] + 0.2 * np.array(BLUE)).astype(np.uint8)
        cv2.rectangle(view, (1, v0), (WIDTH - 2, v1 - 1), BLUE, 2)
    _box(view, truth, GREEN, scale)
    for obs in found:
        _box(view, obs.bbox_xyxy, ORANGE, scale)
    # the crop: the true box's centre, 4x its height around it, enlarged to WIDTH
    cx, cy = (truth[0] + truth[2]) / 2, (truth[1] + truth[3]) / 2
    half_h = max(24.0, 2.0 * (truth[3] - truth[1]))
    half_w = half_h * 2.0
    x0, y0 = int(max(0, cx - half_w)), int(max(0, cy - half_h))
    x1 = int(min(image_rgb.shape[1], cx + half_w))
    y1 = int(min(image_rgb.shape[0], cy + half_h))
    zoom = WIDTH / (x1 - x0)
    crop = cv2.resize(bgr[y0:y1, x0:x1], (WIDTH, round((y1 - y0) * zoom)),
                      interpolation=cv2.INTER_NEAREST)
    _box(crop, truth, GREEN, zoom, x0, y0)
    for obs in found:
        _box(crop, obs.bbox_xyxy, ORANGE, zoom, x0, y0)
        hit = box_iou(obs.bbox_xyxy, truth)
        tx = int((obs.bbox_xyxy[0] - x0) * zoom)
        ty = max(14, int((obs.bbox_xyxy[1] - y0) * zoom) - 6)
        cv2.putText(crop, f"{obs.score:.2f} (IoU {hit:.2f})", (tx, ty),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, ORANGE, 1, cv2.LINE_AA)
    out = np.vstack([view, crop])
    cv2.putText(out, title, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2,
                cv2.LINE_AA)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("docs/images/far_band.jpg"))
    parser.add_argument("--seed", type=int, default=4242)
    parser.add_argument("--views", default="180,97,26",
                        help="site-view indices of the seed (default: three far robots)")
    args = parser.parse_args()
    scenario = load_scenario(PAPER_SCENARIO)
    site = scenario.site
    models = RobotKeypointPipeline.for_robot(site.robot_model(scenario.robot_id), threads=2)
    gen = SampleGenerator(scenario, "site", seed=args.seed)
    rows = []
    for index in (int(v) for v in args.views.split(",")):
        sample = gen(index)
        robot = sample.robots[0]
        if robot.bbox_xyxy is None:
            raise SystemExit(f"view {index} of seed {args.seed} has no robot in view")
        truth = np.asarray(robot.bbox_xyxy, float)
        band = camera_far_band(site, sample.camera.camera_id, models)
        distance = robot_distance_m(sample.camera, sample.robot_pose)
        label = f"{sample.camera.camera_id}, robot {distance:.1f} m"
        left = panel(sample.image_rgb, truth, models(sample.image_rgb), None,
                     f"{label}: whole frame only")
        right = panel(sample.image_rgb, truth, models(sample.image_rgb, far_band=band), band,
                      f"{label}: with the far band")
        height = max(left.shape[0], right.shape[0])
        pad = [np.pad(p, ((0, height - p.shape[0]), (0, 0), (0, 0))) for p in (left, right)]
        rows.append(np.hstack([pad[0], np.full((height, 6, 3), 255, np.uint8), pad[1]]))
        rows.append(np.full((6, rows[-1].shape[1], 3), 255, np.uint8))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), np.vstack(rows[:-1]), [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
