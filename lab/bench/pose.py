"""``smartedge bench pose``: per-frame-set solve latency of the planar pose problem.

N cameras (1, 2, 4, 16) on a ring around a 12-keypoint robot (the example site's HSR model and
camera intrinsics with distortion), 2 px pixel noise, start 0.2 m / 10 deg from the truth. The
CasADi methods (IPOPT, sqpmethod+qrqp, numpy-driven LM on the residual/Jacobian function, damped
Gauss-Newton on the normal-equations function) run on the cached formulation; pyceres
(Levenberg-Marquardt, DENSE_QR, one residual block) and scipy ``least_squares(method="lm")``
run on the numpy implementation of the identical residuals (central-difference Jacobian,
evaluated in one batched call). Only the solve is timed (formulations are built before the
clock starts). Ratios are p50 / pyceres p50; ``*`` marks the default method.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Final

import numpy as np

from backend_service.pose_solver import DEFAULT_METHOD, get_problem
from backend_service.projection import StackedCameras, numeric_jacobian, weighted_residuals
from core.geometry import wrap_angle_array
from core.pose import PlanarPose
from core.site import load_site
from simulation.camera_ring import ring_cameras

SITE_FILE: Final = Path(__file__).resolve().parents[2] / "deploy" / "site.example.yaml"
CAMERA_COUNTS: Final = (1, 2, 4, 16)
METHODS: Final = ("ipopt", "sqpmethod", "lm", "gauss_newton", "pyceres", "scipy")


def _pyceres_solver(st: StackedCameras, kp: np.ndarray, n_res: int) -> Callable[..., np.ndarray]:
    import pyceres

    class ReprojectionCost(pyceres.CostFunction):
        def __init__(self) -> None:
            super().__init__()
            self.set_num_residuals(n_res)
            self.set_parameter_block_sizes([3])
            self.uv = np.zeros(0)
            self.w = np.zeros(0)

        def Evaluate(self, parameters, residuals, jacobians):
            r, J = numeric_jacobian(st, kp, parameters[0], self.uv, self.w)
            residuals[:] = r
            if jacobians is not None and jacobians[0] is not None:
                jacobians[0][:] = J.ravel()
            return True

    cost = ReprojectionCost()
    options = pyceres.SolverOptions()
    options.linear_solver_type = pyceres.LinearSolverType.DENSE_QR
    options.minimizer_progress_to_stdout = False
    options.num_threads = 1

    def solve(q0: np.ndarray, uv: np.ndarray, w: np.ndarray) -> np.ndarray:
        cost.uv, cost.w = uv, w
        q = q0.copy()
        problem = pyceres.Problem()
        problem.add_residual_block(cost, None, [q])
        summary = pyceres.SolverSummary()
        pyceres.solve(options, problem, summary)
        return q

    return solve


def _scipy_solver(st: StackedCameras, kp: np.ndarray) -> Callable[..., np.ndarray]:
    from scipy.optimize import least_squares

    def solve(q0: np.ndarray, uv: np.ndarray, w: np.ndarray) -> np.ndarray:
        def fun(q: np.ndarray) -> np.ndarray:
            return weighted_residuals(st, kp, q[None], uv, w)[0]

        def jac(q: np.ndarray) -> np.ndarray:
            return numeric_jacobian(st, kp, q, uv, w)[1]

        return least_squares(fun, q0, jac=jac, method="lm").x

    return solve


def run(repeats: int, seed: int = 0) -> list[dict[str, float | int | str]]:
    """Time every method for every camera count; returns one row per (count, method)."""
    site = load_site(SITE_FILE)
    template = next(iter(site.cameras.values()))
    kp = site.robot_model().keypoints_base_m
    rng = np.random.default_rng(seed)
    rows: list[dict[str, float | int | str]] = []
    for n in CAMERA_COUNTS:
        cams = ring_cameras(template, n)
        st = StackedCameras.from_cameras(cams)
        problem = get_problem(cams, kp)
        problem.normal_equations_function()  # build outside the timed solves
        cases = []
        for _ in range(repeats):
            truth = PlanarPose(rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5),
                               rng.uniform(-math.pi, math.pi))
            uv, _ = [np.stack(a) for a in zip(*[c.project(kp @ truth.T()[:3, :3].T
                                                          + truth.T()[:3, 3]) for c in cams],
                                              strict=True)]
            uv = uv + rng.normal(0.0, 2.0, uv.shape)
            w = np.ones(uv.shape[:2])
            q0 = truth.as_array() + np.array([0.2 * rng.choice([-1, 1]), 0.1, math.radians(10)])
            cases.append((q0, uv, w, problem.pack(uv, w)))
        solvers: dict[str, Callable[..., np.ndarray]] = {
            "pyceres": _pyceres_solver(st, kp, 2 * n * kp.shape[0]),
            "scipy": _scipy_solver(st, kp),
        }
        results: dict[str, list[np.ndarray]] = {}
        for method in METHODS:
            times, qs = [], []
            for q0, uv, w, p in cases:
                t0 = time.perf_counter()
                if method in solvers:
                    q = solvers[method](q0, uv, w)
                else:
                    q = problem.solve(q0, p, method).q
                times.append(time.perf_counter() - t0)
                qs.append(q)
            results[method] = qs
            t = np.array(times[1:] if len(times) > 1 else times) * 1e3  # first call warms up
            rows.append({"cameras": n, "method": method, "p50_ms": float(np.percentile(t, 50)),
                         "p99_ms": float(np.percentile(t, 99))})
        for ref_name, key in (("pyceres", "max_diff_vs_ceres"), ("ipopt", "max_diff_vs_ipopt")):
            ref = np.array(results[ref_name])
            for row in rows[-len(METHODS):]:
                diff = np.array(results[str(row["method"])]) - ref
                diff[:, 2] = wrap_angle_array(diff[:, 2])
                row[key] = float(np.abs(diff).max())
    return rows


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench pose", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="30 frame-sets per case")
    parser.add_argument("--repeats", type=int, default=300, help="frame-sets per case")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(list(argv))
    repeats = 30 if args.quick else args.repeats
    rows = run(repeats, args.seed)
    n_kp = len(load_site(SITE_FILE).robot_model().keypoint_names)
    print(f"pose solve latency, {repeats} frame-sets per case, {n_kp} keypoints, 2 px noise; "
          f"default method: {DEFAULT_METHOD}")
    print(f"{'cams':>4} {'method':>13} {'p50 ms':>8} {'p99 ms':>8} {'p50/ceres':>9} "
          f"{'max|dq| vs ceres':>16} {'vs ipopt':>8}")
    for n in CAMERA_COUNTS:
        block = [r for r in rows if r["cameras"] == n]
        ceres = next(float(r["p50_ms"]) for r in block if r["method"] == "pyceres")
        for r in block:
            name = f"{r['method']}{'*' if r['method'] == DEFAULT_METHOD else ''}"
            print(f"{n:>4} {name:>13} {r['p50_ms']:>8.3f} {r['p99_ms']:>8.3f} "
                  f"{float(r['p50_ms']) / ceres:>9.2f} {r['max_diff_vs_ceres']:>16.1e} "
                  f"{r['max_diff_vs_ipopt']:>8.1e}")
    return 0
