"""``smartedge bench single-camera``: single-camera treatments and covariance consistency.

Frame-sets are drawn with the error model the covariance states (per trial: every camera's pose
off by ``extrinsic`` (1 cm, 0.1 deg); per detection: a common shift (0.5 px) and scale (2 %)
about the keypoints' centroid; per keypoint: 1 px), for a robot seen by one camera of a ring
(the example site's camera model) at a near (3 m) and a far (6 m) distance, and solved by
:func:`backend_service.estimate.estimate_pose` with the matching ``SolverConfig``.

Part 1, single camera with a prior, one row per geometry and prior: the prior drawn from its
covariance P ("good": 5 cm / 2 deg, "bad": 20 cm / 6 deg), or drawn at 20 cm / 6 deg but
claiming 5 cm / 2 deg ("overconfident"). Mean position (cm) and heading (deg) errors of the
prior alone, the plain solve, the paper's heuristic (``single_camera="paper"``) and the MAP
treatment (``"map"`` with P; without a prior covariance it is the plain solve).

Part 2, mean NEES (3 is consistent) of the reported covariance for 1, 2 and 4 cameras,
``covariance_model`` ``propagated`` (default) vs ``residual`` (pixel noise only).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Sequence
from typing import Final

import numpy as np

from backend_service.covariance import ErrorModel
from backend_service.estimate import SolverConfig, estimate_pose
from backend_service.frame_set import CameraObservation, FrameSet
from core.camera import CameraModel
from core.geometry import invert_transform, rotation_from_rotvec, wrap_angle
from core.pose import PlanarPose
from core.site import Site, load_site
from lab.bench.pose import SITE_FILE
from simulation.camera_ring import ring_cameras

#: the error model the frame-sets are drawn with (and the solver is told)
MODEL: Final = ErrorModel(detection_shift_sigma_px=0.5, detection_scale_sigma=0.02,
                          extrinsic_sigma_m=0.01, extrinsic_sigma_deg=0.1)
PIXEL_SIGMA_PX: Final = 1.0
#: (name, drawn std (m, deg), reported std (m, deg))
PRIORS: Final = (("good", (0.05, 2.0), (0.05, 2.0)), ("bad", (0.20, 6.0), (0.20, 6.0)),
                 ("overconfident", (0.20, 6.0), (0.05, 2.0)))
GEOMETRIES: Final = (("near 3 m", 3.0), ("far 6 m", 6.0))
TREATMENTS: Final = ("prior", "plain", "paper", "map")


def solver_config(**overrides: object) -> SolverConfig:
    """The solver told :data:`MODEL`."""
    return SolverConfig(detection_shift_sigma_px=MODEL.detection_shift_sigma_px,
                        detection_scale_sigma=MODEL.detection_scale_sigma,
                        extrinsic_sigma_m=MODEL.extrinsic_sigma_m,
                        extrinsic_sigma_deg=MODEL.extrinsic_sigma_deg,
                        **overrides)  # type: ignore[arg-type]


def _true_camera(cam: CameraModel, rng: np.random.Generator) -> CameraModel:
    T_world_cam = invert_transform(cam.T_cam_world)
    dR = rotation_from_rotvec(rng.normal(0.0, math.radians(MODEL.extrinsic_sigma_deg), 3))
    T_world_cam[:3, :3] = dR @ T_world_cam[:3, :3]
    T_world_cam[:3, 3] += rng.normal(0.0, MODEL.extrinsic_sigma_m, 3)
    return dataclasses.replace(cam, T_cam_world=invert_transform(T_world_cam))


def draw_frame_set(site: Site, truth: PlanarPose, rng: np.random.Generator) -> FrameSet:
    """One frame-set of ``truth`` seen by every camera of ``site`` with :data:`MODEL`'s errors
    (a fresh calibration error per call)."""
    model = site.robot_model()
    T = truth.T()
    pts = model.keypoints_base_m @ T[:3, :3].T + T[:3, 3]
    obs = []
    for cam in site.cameras.values():
        uv, depth = _true_camera(cam, rng).project(pts)
        ok = (depth > 0.1) & cam.in_image(uv)
        if ok.sum() < 3:
            continue
        c = uv[ok].mean(axis=0)
        scale = 1.0 + rng.normal(0.0, MODEL.detection_scale_sigma)
        uv = (c + scale * (uv - c) + rng.normal(0.0, MODEL.detection_shift_sigma_px, 2)
              + rng.normal(0.0, PIXEL_SIGMA_PX, uv.shape))
        obs.append(CameraObservation(cam.camera_id, 0, np.where(ok[:, None], uv, 0.0),
                                     ok.astype(float)))
    return FrameSet.from_observations(model.name, obs)


def _error(pose: PlanarPose, truth: PlanarPose) -> tuple[float, float]:
    return (math.hypot(pose.x - truth.x, pose.y - truth.y),
            abs(wrap_angle(pose.theta - truth.theta)))


def _nees(pose: PlanarPose, cov: np.ndarray, truth: PlanarPose) -> float:
    e = np.array([pose.x - truth.x, pose.y - truth.y, wrap_angle(pose.theta - truth.theta)])
    return float(e @ np.linalg.solve(cov, e))


def _ring_site(base: Site, count: int, radius_m: float) -> Site:
    cams = ring_cameras(next(iter(base.cameras.values())), count, radius_m=radius_m)
    return dataclasses.replace(base, cameras={c.camera_id: c for c in cams})


def _truth(rng: np.random.Generator) -> PlanarPose:
    return PlanarPose(rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3),
                      rng.uniform(-math.pi, math.pi))


def single_camera_rows(trials: int, seed: int = 0) -> list[tuple[str, str, dict[str, tuple]]]:
    """(geometry, prior, {treatment: (mean position error m, mean heading error rad)})."""
    base = load_site(SITE_FILE)
    out = []
    for geo, radius in GEOMETRIES:
        site = _ring_site(base, 1, radius)
        for name, (d_m, d_deg), (r_m, r_deg) in PRIORS:
            rng = np.random.default_rng([seed, round(radius * 10), len(name)])
            P = np.diag([r_m ** 2, r_m ** 2, math.radians(r_deg) ** 2])
            errs: dict[str, list[tuple[float, float]]] = {t: [] for t in TREATMENTS}
            for _ in range(trials):
                truth = _truth(rng)
                prior = PlanarPose(truth.x + rng.normal(0, d_m), truth.y + rng.normal(0, d_m),
                                   truth.theta + rng.normal(0, math.radians(d_deg)))
                fs = draw_frame_set(site, truth, rng)
                errs["prior"].append(_error(prior, truth))
                for t in ("plain", "paper", "map"):
                    res = estimate_pose(fs, site, prior, solver_config(single_camera=t),
                                        P if t == "map" else None)
                    errs[t].append(_error(res.pose, truth) if res.ok else (math.nan,) * 2)
            out.append((geo, name, {t: tuple(np.nanmean(np.array(v), axis=0))
                                    for t, v in errs.items()}))
    return out


def nees_rows(trials: int, seed: int = 0) -> list[tuple[int, float, float]]:
    """(cameras, mean NEES propagated, mean NEES residual) on a 4 m ring."""
    base = load_site(SITE_FILE)
    out = []
    for n in (1, 2, 4):
        site = _ring_site(base, n, 4.0)
        rng = np.random.default_rng([seed, n])
        values: dict[str, list[float]] = {"propagated": [], "residual": []}
        for _ in range(trials):
            truth = _truth(rng)
            fs = draw_frame_set(site, truth, rng)
            for model in values:
                res = estimate_pose(fs, site, truth,
                                    solver_config(single_camera="plain",
                                                  covariance_model=model))
                if res.ok:
                    values[model].append(_nees(res.pose, res.estimate.covariance, truth))
        out.append((n, float(np.mean(values["propagated"])), float(np.mean(values["residual"]))))
    return out


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench single-camera", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=300, help="frame-sets per row")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(list(argv))
    if args.trials < 2:
        print("smartedge bench single-camera: --trials >= 2", flush=True)
        return 2
    print(f"single camera with a prior: mean error, cm / deg ({args.trials} frame-sets per row;"
          f" errors drawn as stated: shift {MODEL.detection_shift_sigma_px} px, scale "
          f"{MODEL.detection_scale_sigma:.0%}, extrinsics {MODEL.extrinsic_sigma_m * 100:g} cm "
          f"/ {MODEL.extrinsic_sigma_deg} deg, {PIXEL_SIGMA_PX} px per keypoint)", flush=True)
    print(f"{'geometry':<9} {'prior':<13} " + " ".join(f"{t:>13}" for t in TREATMENTS))
    for geo, name, row in single_camera_rows(args.trials, args.seed):
        cells = " ".join(f"{row[t][0] * 100:>6.2f} /{math.degrees(row[t][1]):>5.2f}"
                         for t in TREATMENTS)
        print(f"{geo:<9} {name:<13} {cells}", flush=True)
    print("\ncovariance consistency: mean NEES (3 = consistent), 4 m ring, no prior term")
    print(f"{'cameras':>7} {'propagated':>10} {'residual':>9}")
    for n, prop, resid in nees_rows(args.trials, args.seed):
        print(f"{n:>7} {prop:>10.2f} {resid:>9.2f}", flush=True)
    return 0
