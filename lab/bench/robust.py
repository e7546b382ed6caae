"""``smartedge bench robust``: which robust loss the pose solver should use, measured.

For 1, 2, 3 and 4 cameras on a ring around the robot (the example site's camera model with its
distortion, 12 keypoints), Monte-Carlo frame-sets with Gaussian pixel noise (``--sigma``, 1 px)
and a share of gross outliers (keypoints replaced by uniform points of the image: 0 %, 5 %,
15 %) are solved by :func:`backend_service.estimate.estimate_pose` (the deployed entry point)
from a prior 0.15 m / 6 deg off, with each loss (``none``, ``huber``, ``cauchy``; robust scale
``SolverConfig.robust_scale_px``). Printed per case: the mean squared position error divided by
the Cramer-Rao bound of the clean noise (trace of its xy block), the same for the heading, and
the share of solves more than 20 cm off. 1.0 is the best any unbiased estimator can do without
outliers.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Sequence
from typing import Final

import numpy as np

from backend_service.estimate import SolverConfig, estimate_pose
from backend_service.frame_set import CameraObservation, FrameSet
from core.geometry import wrap_angle
from core.pose import PlanarPose
from core.site import load_site
from lab.bench.pose import SITE_FILE
from lab.evaluation.cramer_rao import fisher_information
from simulation.camera_ring import ring_cameras

LOSSES: Final = ("none", "huber", "cauchy")
CAMERA_COUNTS: Final = (1, 2, 3, 4)
OUTLIER_SHARES: Final = (0.0, 0.05, 0.15)
GROSS_M: Final = 0.20


@dataclasses.dataclass(frozen=True)
class RobustRow:
    cameras: int
    outliers: float
    loss: str
    mse_crlb_position: float
    mse_crlb_heading: float
    gross_share: float
    failed: int


def run(trials: int, sigma_px: float = 1.0, seed: int = 0,
        counts: Sequence[int] = CAMERA_COUNTS, shares: Sequence[float] = OUTLIER_SHARES
        ) -> list[RobustRow]:
    """One row per (camera count, outlier share, loss); the same frame-sets for every loss."""
    base = load_site(SITE_FILE)
    template = next(iter(base.cameras.values()))
    model = base.robot_model()
    kp = model.keypoints_base_m
    rows: list[RobustRow] = []
    for n in counts:
        cams = ring_cameras(template, n)
        site = dataclasses.replace(base, cameras={c.camera_id: c for c in cams})
        for share in shares:
            rng = np.random.default_rng([seed, n, round(share * 1000)])
            cases = []
            for _ in range(trials):
                truth = PlanarPose(rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5),
                                   rng.uniform(-math.pi, math.pi))
                crlb = np.linalg.inv(fisher_information(cams, kp, truth, sigma_px))
                obs = []
                T = truth.T()
                pts = kp @ T[:3, :3].T + T[:3, 3]
                for cam in cams:
                    uv, depth = cam.project(pts)
                    ok = (depth > 0) & cam.in_image(uv)
                    uv = np.where(ok[:, None], uv, 0.0) + rng.normal(0.0, sigma_px, uv.shape)
                    out = rng.random(len(uv)) < share
                    uv[out] = rng.uniform([0, 0], [cam.width, cam.height], (int(out.sum()), 2))
                    obs.append(CameraObservation(cam.camera_id, 0, uv, ok.astype(float)))
                sign = rng.choice([-1.0, 1.0], 3)
                prior = PlanarPose(truth.x + 0.15 * sign[0], truth.y + 0.05 * sign[1],
                                   truth.theta + math.radians(6.0) * sign[2])
                cases.append((truth, crlb, FrameSet.from_observations(model.name, obs), prior))
            for loss in LOSSES:
                config = SolverConfig(robust_loss=loss, single_camera="plain")
                pos_ratio, head_ratio, gross, failed = [], [], 0, 0
                for truth, crlb, fs, prior in cases:
                    res = estimate_pose(fs, site, prior, config)
                    if not res.ok:
                        failed += 1
                        continue
                    dx, dy = res.pose.x - truth.x, res.pose.y - truth.y
                    dth = wrap_angle(res.pose.theta - truth.theta)
                    pos_ratio.append((dx * dx + dy * dy) / (crlb[0, 0] + crlb[1, 1]))
                    head_ratio.append(dth * dth / crlb[2, 2])
                    gross += math.hypot(dx, dy) > GROSS_M
                done = max(len(pos_ratio), 1)
                rows.append(RobustRow(n, share, loss, float(np.mean(pos_ratio or [np.nan])),
                                      float(np.mean(head_ratio or [np.nan])), gross / done,
                                      failed))
    return rows


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench robust", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=300, help="frame-sets per case")
    parser.add_argument("--sigma", type=float, default=1.0, help="pixel noise (px)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(list(argv))
    if args.trials < 2 or not args.sigma > 0:
        print("smartedge bench robust: --trials >= 2 and --sigma > 0", flush=True)
        return 2
    rows = run(args.trials, args.sigma, args.seed)
    print(f"robust loss: MSE / Cramer-Rao bound, {args.trials} frame-sets per case, "
          f"{args.sigma:g} px noise, robust scale {SolverConfig().robust_scale_px:g} px, "
          f"default loss {SolverConfig().robust_loss}")
    print(f"{'cams':>4} {'outliers':>8} {'loss':>7} {'pos MSE/CRLB':>12} "
          f"{'yaw MSE/CRLB':>12} {'> 20 cm':>8} {'failed':>6}")
    for r in rows:
        print(f"{r.cameras:>4} {r.outliers:>8.0%} {r.loss:>7} {r.mse_crlb_position:>12.2f} "
              f"{r.mse_crlb_heading:>12.2f} {r.gross_share:>8.1%} {r.failed:>6}")
    return 0
