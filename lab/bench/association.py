"""CPU of matching detections to robots (``backend_service.association``) per frame-set.

A ring site (``simulation.camera_ring``: N cameras around the origin, all looking at it) with R
robots of the HSR model on a grid around the origin (0.9 m apart: every camera sees every
robot, the worst case of R detections per image). One frame-set is every camera's detections
message (exact projections plus 1 px noise, no robot ids, in random order); its routing is what
the backend adds per frame-set on a site with several robots (:class:`DetectionRouter.route`
for each camera message, the robots' predictions given: new ones each frame-set, so the
predicted views are projected into every camera once per frame-set, as in the pipeline, whose
predictions are reused for 5 ms of image stamps). Two kinds of prediction: *sharp*
(fused poses, 3 cm sigma: no detection has a rival within the gate) and *vague* (the robots'
own localization, 0.5 m sigma: neighbours are rivals, each assigned pair costs one more
assignment solve for the ambiguity rule).

    smartedge bench association [--robots 2,10] [--cameras 4,64] [--frame-sets N]

Each row also gives the vague predictions' cost as a ratio to the sharp ones of the same
site (the ambiguity rule's price). The identity figures (wrong-robot detections, switches,
ambiguous detections when two robots pass) come from the two-robot scenes of
``tests/backend_service/test_association.py`` (docs/pose_estimation.md).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from backend_service.association import RobotPrediction
from backend_service.detection_router import DetectionRouter
from core.geometry import rotation_z
from core.pose import PlanarPose
from core.site import Site, load_site
from protocol.messages import Detection, RobotDetections
from simulation.camera_ring import write_ring_site


def fleet_site(n_cameras: int, n_robots: int, directory: Path) -> Site:
    """The ring site of ``smartedge bench backend`` with ``n_robots`` HSRs."""
    path = directory / f"ring{n_cameras}.yaml"
    write_ring_site(path, n_cameras)
    text = path.read_text().replace(
        "robots:\n- id: hsr\n  model: hsr\n",
        "robots:\n" + "".join(f"- id: hsr{i}\n  model: hsr\n" for i in range(n_robots)))
    path.write_text(text)
    return load_site(path)


def robot_poses(n_robots: int) -> np.ndarray:
    """(R, 3) poses on a grid 0.9 m apart around the origin, varied headings."""
    side = math.ceil(math.sqrt(n_robots))
    out = []
    for i in range(n_robots):
        r, c = divmod(i, side)
        out.append([(c - (side - 1) / 2) * 0.9, (r - (side - 1) / 2) * 0.9, 0.7 * i])
    return np.array(out)


def frame_set(site: Site, poses: np.ndarray, stamp_ns: int, rng: np.random.Generator
              ) -> list[RobotDetections]:
    kp = site.robot_model("hsr0").keypoints_base_m
    msgs = []
    for cam in site.cameras.values():
        dets = []
        for x, y, theta in poses:
            pts = kp @ rotation_z(theta).T + [x, y, 0.0]
            uv, _ = cam.project(pts)
            uv = uv + rng.normal(0.0, 1.0, uv.shape)
            lo, hi = uv.min(axis=0) - 5, uv.max(axis=0) + 5
            dets.append(Detection(np.array([*lo, *hi]), 0.95, uv, np.full(len(uv), 0.9)))
        order = rng.permutation(len(dets))
        msgs.append(RobotDetections(cam.camera_id, stamp_ns, 0, cam.width, cam.height, "bench",
                                    tuple(dets[i] for i in order)))
    return msgs


def predictions(site: Site, poses: np.ndarray, sigma_m: float, rng: np.random.Generator
                ) -> dict[str, RobotPrediction]:
    source = "fused" if sigma_m < 0.1 else "localization"
    out = {}
    for rid, (x, y, theta) in zip(site.robots, poses, strict=True):
        err = rng.normal(0.0, min(sigma_m, 0.03), 2)
        out[rid] = RobotPrediction(rid, PlanarPose(x + err[0], y + err[1], theta),
                                   np.diag([sigma_m ** 2, sigma_m ** 2, 0.02 ** 2]), source)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench association",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--robots", default="2,10")
    parser.add_argument("--cameras", default="4,64")
    parser.add_argument("--frame-sets", type=int, default=30)
    args = parser.parse_args(None if argv is None else list(argv))
    rng = np.random.default_rng(0)
    if args.frame_sets < 1:
        print("smartedge bench association: --frame-sets must be >= 1", file=sys.stderr)
        return 2
    try:
        robot_counts = [int(v) for v in args.robots.split(",")]
        camera_counts = [int(v) for v in args.cameras.split(",")]
    except ValueError:
        print("smartedge bench association: --robots and --cameras are comma-separated "
              "integers", file=sys.stderr)
        return 2
    print(f"{'robots':>6} {'cameras':>7} {'predictions':>11} {'per frame-set':>14} "
          f"{'per image':>10} {'assigned':>9} {'ambiguous':>9} {'vs sharp':>8}")
    with tempfile.TemporaryDirectory() as tmp:
        for n_rob in robot_counts:
            for n_cam in camera_counts:
                site = fleet_site(n_cam, n_rob, Path(tmp))
                poses = robot_poses(n_rob)
                sharp_us = math.nan
                for label, sigma in (("sharp", 0.03), ("vague", 0.5)):
                    router = DetectionRouter(site)
                    sets = [frame_set(site, poses, k, rng) for k in range(args.frame_sets + 3)]
                    times = []
                    for k, msgs in enumerate(sets):
                        # new prediction objects each frame-set: the predicted views are
                        # projected once per frame-set, as in the pipeline
                        preds = predictions(site, poses, sigma, rng)
                        t0 = time.perf_counter()
                        for msg in msgs:
                            router.route(msg, preds)
                        if k >= 3:  # warm-up
                            times.append(time.perf_counter() - t0)
                    per_set_us = float(np.median(times)) * 1e6
                    if label == "sharp":
                        sharp_us = per_set_us
                    c = router.counters
                    print(f"{n_rob:>6} {n_cam:>7} {label:>11} {per_set_us:>11.0f} µs "
                          f"{per_set_us / n_cam:>7.0f} µs {c['detections_assigned']:>9} "
                          f"{c['detections_ambiguous']:>9} {per_set_us / sharp_us:>7.2f}x",
                          flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
