"""Draw the pictures of docs/calibration.md from rendered board views (the paper lab's cam1,
its true intrinsics): ``calibration_detection.png`` (a usable view with its detected corners
beside a blurred one the detector refuses, with the reason) and ``calibration_coverage.png``
(the coverage picture ``smartedge calibrate intrinsics`` writes, after 30 views).

    python scripts/calibration_pictures.py [--out-dir docs/images]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import cv2
import numpy as np

from calibration.board import (
    BoardDetector,
    CharucoBoardSpec,
    board_image,
    draw_detection,
)
from calibration.intrinsics import calibrate_intrinsics, coverage_image
from core.site import load_site
from simulation.board_views import BoardRenderer, BoardTexture, calibration_sweep

SITE = Path(__file__).resolve().parents[1] / "simulation" / "sites" / "paper_lab.yaml"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=Path("docs/images"))
    args = parser.parse_args()
    cam = load_site(SITE).cameras["cam1"]
    spec = CharucoBoardSpec(9, 7, 0.06, 0.045, "DICT_5X5_100")
    img = board_image(spec, 60)
    with BoardRenderer(BoardTexture(img.image, img.extent_board_m), cam.width,
                       cam.height) as br:
        views = [cv2.cvtColor(br.render(c, np.eye(4)).image_rgb, cv2.COLOR_RGB2BGR)
                 for c in calibration_sweep(cam, spec.size_m, 30, seed=4)]
    det = BoardDetector(spec)
    detections = [(f"view{i:02d}", det.detect(v)) for i, v in enumerate(views)]
    result = calibrate_intrinsics(detections, spec, "cam1")
    print(result.summary())
    sharp = max(range(len(views)), key=lambda i: detections[i][1].num_corners)
    blurred = cv2.GaussianBlur(views[sharp], (0, 0), 2.5)
    # both panels cropped to the board, corners and labels drawn on the crops
    pts = detections[sharp][1].corners_px
    x0, x1 = max(0, int(pts[:, 0].min()) - 90), min(cam.width, int(pts[:, 0].max()) + 90)
    y1 = min(cam.height, int(pts[:, 1].max()) + 70)
    panels = []
    for image in (views[sharp], blurred):
        found = det.detect(image)
        shifted = dataclasses.replace(found, corners_px=found.corners_px - [x0, 0])
        panels.append(draw_detection(image[:y1, x0:x1], shifted))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    out = args.out_dir / "calibration_detection.png"
    gap = np.full((y1, 6, 3), 255, np.uint8)
    cv2.imwrite(str(out), np.hstack([panels[0], gap, panels[1]]), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {out}")
    out = args.out_dir / "calibration_coverage.png"
    cv2.imwrite(str(out), coverage_image(result), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
