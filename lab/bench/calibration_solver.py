"""``smartedge bench calibration-solver``: the board adjustment's Levenberg-Marquardt loop
(:func:`calibration.board_extrinsics.adjust_board`, numpy, boards eliminated by Schur
complement) against the same problem as a GTSAM factor graph, in the same run.

The problem: a board walk (:func:`simulation.board_views.board_walk`) through the simulated
paper lab's true cameras, the board's corners projected through each camera that sees its face,
Gaussian pixel noise and a share of gross outliers; one board pose fixed (the map frame), every
other board pose and every camera pose solved. Both solvers start from the same PnP chain
(:func:`calibration.board_extrinsics.prepare_board_adjustment`) and minimise the same cost: the
Huber loss of each corner's reprojection error (:meth:`BoardProblem.huber_cost`).

The GTSAM peer: ``Pose3`` variables for the cameras (``T_world_cam``) and the free boards, one
``CustomFactor`` per corner (a 2-vector error, unit-sigma noise under GTSAM's own Huber
m-estimator with the same threshold) whose error and Jacobians come from the project's one
projection (:func:`core.projection.project_world_points`), and GTSAM's
``LevenbergMarquardtOptimizer``. GTSAM has no factor of a point on a moving rigid body seen by a
moving camera with OpenCV's 8-coefficient lens (``Cal3DS2`` has 4), so the factor is a Python
callback: the time inside the callbacks is reported apart from GTSAM's own.

Prints per solver: wall time (best of ``--repeats``) split into set-up and solve (and, for
GTSAM, the callbacks), iterations, final cost, the cameras' errors against the truth, and how
far apart the two solutions are; the ratio GTSAM / numpy. docs/calibration.md says which solver
the project uses and why.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Mapping, Sequence

import gtsam
import numpy as np

from calibration.board import CharucoBoardSpec
from calibration.board_extrinsics import (
    HUBER_PX,
    MAX_ITERATIONS,
    MIN_SIGHTING_CORNERS,
    BoardAdjustment,
    BoardProblem,
    BoardSighting,
    BoardState,
    adjust_board,
    prepare_board_adjustment,
)
from core.camera import CameraModel
from core.geometry import pose_error
from core.projection import SOLVER_MIN_DEPTH_M, project_world_points
from simulation.board_views import board_walk
from simulation.detections import true_cameras
from simulation.scenario import PAPER_SCENARIO, load_scenario

#: the extrinsics board of ``smartedge evaluate calibration`` (A0, 5 x 4 squares of 20 cm)
BOARD = CharucoBoardSpec(5, 4, 0.2, 0.156, "DICT_4X4_50")


@dataclasses.dataclass(frozen=True)
class SyntheticSightings:
    """The board walk's sightings and the truth they were made from."""

    cameras: dict[str, CameraModel]
    board_poses: dict[str, np.ndarray]
    sightings: list[BoardSighting]
    outliers: int


def synthetic_sightings(cameras: Mapping[str, CameraModel], rounds: int, noise_px: float,
                        outlier_share: float, seed: int) -> SyntheticSightings:
    """Corners of a board walk of ``rounds`` rounds projected through ``cameras`` (those that see
    the board's face, at least :data:`MIN_SIGHTING_CORNERS` corners inside the image), with
    Gaussian noise of ``noise_px`` and ``outlier_share`` of the corners moved by 5-30 px."""
    rng = np.random.default_rng(seed)
    poses = board_walk(dict(cameras), BOARD.size_m, rounds, seed=seed)
    corners_board = BOARD.corners_board_m()
    sightings: list[BoardSighting] = []
    outliers = 0
    for stamp, T_world_board in poses.items():
        corners_world = corners_board @ T_world_board[:3, :3].T + T_world_board[:3, 3]
        normal_world = T_world_board[:3, 2]
        for cid in sorted(cameras):
            cam = cameras[cid]
            to_camera = cam.T_world_cam[:3, 3] - T_world_board[:3, 3]
            if abs(float(normal_world @ to_camera)) < 0.2 * float(np.linalg.norm(to_camera)):
                continue  # seen too obliquely to be detected
            uv, depth = cam.project(corners_world)
            seen = (depth > 0.1) & cam.in_image(uv, margin_px=5.0)
            if int(seen.sum()) < MIN_SIGHTING_CORNERS:
                continue
            uv = uv[seen] + rng.normal(0.0, noise_px, (int(seen.sum()), 2))
            bad = rng.random(len(uv)) < outlier_share
            angle = rng.uniform(0, 2 * np.pi, int(bad.sum()))
            uv[bad] += rng.uniform(5.0, 30.0, int(bad.sum()))[:, None] * np.stack(
                [np.cos(angle), np.sin(angle)], axis=1)
            outliers += int(bad.sum())
            sightings.append(BoardSighting(cid, stamp, np.flatnonzero(seen), uv))
    return SyntheticSightings(dict(cameras), poses, sightings, outliers)


# ------------------------------------------------------------------------------ the GTSAM peer


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _pose3(R: np.ndarray, t: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3(np.asarray(R, float)), np.asarray(t, float))


@dataclasses.dataclass
class GtsamSolve:
    state: BoardState
    iterations: int
    build_s: float
    solve_s: float
    callback_s: float
    callbacks: int


def solve_with_gtsam(prob: BoardProblem, initial: BoardState, huber_px: float,
                     max_iterations: int) -> GtsamSolve:
    """The board adjustment as a GTSAM factor graph (module docstring), from ``initial``."""
    t0 = time.perf_counter()
    R_wc0, c_w0, R_wb0, t_wb0 = initial
    C = len(prob.cam_ids)
    cam_key = [gtsam.symbol("c", i) for i in range(C)]
    board_key = [gtsam.symbol("b", j) if prob.free_board[j] else -1
                 for j in range(len(prob.stamps))]
    values = gtsam.Values()
    for i in range(C):
        values.insert(cam_key[i], _pose3(R_wc0[i], c_w0[i]))
    for j, key in enumerate(board_key):
        if key >= 0:
            values.insert(key, _pose3(R_wb0[j], t_wb0[j]))
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(huber_px),
                                           gtsam.noiseModel.Unit.Create(2))
    timing = {"s": 0.0, "n": 0}

    def corner_error(i: int, j: int, X: np.ndarray, uv: np.ndarray):
        fixed_board = board_key[j] < 0
        R_fixed, t_fixed = R_wb0[j], t_wb0[j]

        def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list[np.ndarray] | None
                  ) -> np.ndarray:
            start = time.perf_counter()
            T_wc = v.atPose3(this.keys()[0])
            R_wc, c_w = T_wc.rotation().matrix(), T_wc.translation()
            if fixed_board:
                R_wb, t_wb = R_fixed, t_fixed
            else:
                T_wb = v.atPose3(this.keys()[1])
                R_wb, t_wb = T_wb.rotation().matrix(), T_wb.translation()
            RX = R_wb @ X
            proj = project_world_points(R_wc, c_w, prob.K[i], prob.dist[i], RX + t_wb,
                                        jacobians=H is not None,
                                        min_depth_m=SOLVER_MIN_DEPTH_M)
            if H is not None:
                G, D = proj.d_uv_d_camera, proj.d_uv_d_point  # (2, 6) rotation, position; (2, 3)
                # GTSAM's Pose3 tangent is (rotation, translation) in the body frame
                H[0] = np.hstack([G[:, :3] @ R_wc, G[:, 3:] @ R_wc])
                if not fixed_board:
                    H[1] = np.hstack([D @ (-R_wb @ _skew(X)), D @ R_wb])
            timing["s"] += time.perf_counter() - start
            timing["n"] += 1
            return proj.uv - uv

        return error

    graph = gtsam.NonlinearFactorGraph()
    for n in range(len(prob.uv)):
        i, j = int(prob.obs_cam[n]), int(prob.obs_board[n])
        keys = [cam_key[i]] + ([board_key[j]] if board_key[j] >= 0 else [])
        graph.add(gtsam.CustomFactor(noise, keys,
                                     corner_error(i, j, prob.X_board[n], prob.uv[n])))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(0.0)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    t1 = time.perf_counter()
    timing["s"], timing["n"] = 0.0, 0
    result = optimizer.optimize()
    t2 = time.perf_counter()
    R_wc = np.stack([result.atPose3(k).rotation().matrix() for k in cam_key])
    c_w = np.stack([result.atPose3(k).translation() for k in cam_key])
    R_wb, t_wb = R_wb0.copy(), t_wb0.copy()
    for j, key in enumerate(board_key):
        if key >= 0:
            R_wb[j] = result.atPose3(key).rotation().matrix()
            t_wb[j] = result.atPose3(key).translation()
    return GtsamSolve((R_wc, c_w, R_wb, t_wb), int(optimizer.iterations()), t1 - t0, t2 - t1,
                      timing["s"], timing["n"])


# ------------------------------------------------------------------------------ the bench


@dataclasses.dataclass(frozen=True)
class SolverFigures:
    """One solver's figures: ``setup_s`` (problem / graph), ``solve_s`` (the optimization, best
    of the repeats), ``callback_s`` (GTSAM: inside the Python factors), final ``cost``, the
    cameras' worst position (cm) and rotation (deg) error against the truth."""

    name: str
    setup_s: float
    solve_s: float
    callback_s: float
    iterations: int
    cost: float
    worst_position_cm: float
    worst_rotation_deg: float
    state: BoardState = dataclasses.field(repr=False)


def _camera_errors(prob: BoardProblem, state: BoardState, truth: Mapping[str, CameraModel]
                   ) -> tuple[float, float]:
    R_wc, c_w, _, _ = state
    worst_cm = worst_deg = 0.0
    for i, cid in enumerate(prob.cam_ids):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_wc[i], c_w[i]
        dp, da = pose_error(T, truth[cid].T_world_cam)
        worst_cm, worst_deg = max(worst_cm, 100 * dp), max(worst_deg, da)
    return worst_cm, worst_deg


def compare_solvers(data: SyntheticSightings, adjustment: BoardAdjustment, repeats: int,
                    huber_px: float = HUBER_PX, max_iterations: int = MAX_ITERATIONS
                    ) -> tuple[SolverFigures, SolverFigures]:
    """Both solvers on ``adjustment`` (best of ``repeats``): (numpy LM, GTSAM)."""
    prob, initial = adjustment.problem, adjustment.initial
    best_np = best_gt = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        state, iterations = adjust_board(prob, initial, huber_px, max_iterations)
        seconds = time.perf_counter() - t0
        if best_np is None or seconds < best_np[0]:
            best_np = (seconds, state, iterations)
        gt = solve_with_gtsam(prob, initial, huber_px, max_iterations)
        if best_gt is None or gt.solve_s < best_gt.solve_s:
            best_gt = gt
    assert best_np is not None and best_gt is not None
    figures = []
    for name, setup_s, solve_s, callback_s, state, iterations in (
            ("numpy LM (adjust_board)", 0.0, best_np[0], 0.0, best_np[1], best_np[2]),
            ("GTSAM LM (CustomFactor)", best_gt.build_s, best_gt.solve_s, best_gt.callback_s,
             best_gt.state, best_gt.iterations)):
        cm, deg = _camera_errors(prob, state, data.cameras)
        figures.append(SolverFigures(name, setup_s, solve_s, callback_s, iterations,
                                     prob.huber_cost(*state, huber_px), cm, deg, state))
    return figures[0], figures[1]


def solution_gap(a: BoardState, b: BoardState) -> tuple[float, float]:
    """Largest difference between two solutions' cameras: position (mm), rotation (deg)."""
    gap_mm = float(np.abs(np.linalg.norm(a[1] - b[1], axis=1)).max()) * 1000
    rel = np.einsum("nji,njk->nik", a[0], b[0])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return gap_mm, float(np.degrees(np.arccos(cos)).max())


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench calibration-solver",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=6,
                        help="rounds of the board walk, one pose per camera each (6)")
    parser.add_argument("--noise-px", type=float, default=0.3, help="corner noise, px (0.3)")
    parser.add_argument("--outliers", type=float, default=0.02,
                        help="share of corners moved 5-30 px (0.02)")
    parser.add_argument("--repeats", type=int, default=3, help="solves per solver, best kept (3)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(list(argv))
    if args.rounds < 1 or args.repeats < 1 or args.noise_px < 0 or not 0 <= args.outliers < 1:
        parser.error("--rounds and --repeats >= 1, --noise-px >= 0, 0 <= --outliers < 1")
    truth = true_cameras(load_scenario(PAPER_SCENARIO))
    data = synthetic_sightings(truth, args.rounds, args.noise_px, args.outliers, args.seed)
    t0 = time.perf_counter()
    adjustment = prepare_board_adjustment(truth, data.sightings, BOARD,
                                          {"000": data.board_poses["000"]})
    prepare_s = time.perf_counter() - t0
    prob = adjustment.problem
    print(f"board walk: {len(data.board_poses)} board poses, {len(data.sightings)} sightings, "
          f"{len(prob.uv)} corners ({data.outliers} outliers) by {len(prob.cam_ids)} cameras; "
          f"one board pose fixed, {int(prob.free_board.sum())} solved; noise {args.noise_px} px")
    start_cost = prob.huber_cost(*adjustment.initial, HUBER_PX)
    print(f"shared start (PnP of each sighting, chained from the fixed board): "
          f"{prepare_s * 1e3:.0f} ms; initial cost {start_cost:.1f}")
    ours, peer = compare_solvers(data, adjustment, args.repeats)
    print(f"{'solver':26s} {'set-up ms':>9s} {'solve ms':>9s} {'callbacks ms':>12s} "
          f"{'iter':>4s} {'cost':>10s} {'worst cam cm':>12s} {'deg':>6s}")
    for f in (ours, peer):
        print(f"{f.name:26s} {f.setup_s * 1e3:9.1f} {f.solve_s * 1e3:9.1f} "
              f"{f.callback_s * 1e3:12.1f} {f.iterations:4d} {f.cost:10.3f} "
              f"{f.worst_position_cm:12.3f} {f.worst_rotation_deg:6.3f}")
    gap_mm, gap_deg = solution_gap(ours.state, peer.state)
    total_ours, total_peer = ours.setup_s + ours.solve_s, peer.setup_s + peer.solve_s
    print(f"GTSAM / numpy: {total_peer / total_ours:.1f}x the time (solve alone "
          f"{peer.solve_s / ours.solve_s:.1f}x; GTSAM without its callbacks "
          f"{(peer.solve_s - peer.callback_s) / ours.solve_s:.2f}x); cost "
          f"{peer.cost / ours.cost:.6f}x; solutions {gap_mm:.3f} mm / {gap_deg:.4f} deg apart")
    return 0
