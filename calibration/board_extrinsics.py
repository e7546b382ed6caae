"""Every camera's pose ``T_world_cam`` from sightings of one ChArUco board by several cameras,
solved jointly: a bundle adjustment over every board-corner sighting, the cameras' poses and the
board's unknown poses (one per stamp) as unknowns, with the board poses the user or the robot
gives held fixed in the map frame (they fix the frame: at least one is needed).

Start: per-sighting ``cv2.solvePnP`` chained through the board poses the cameras share (from the
fixed ones outwards). Refinement: Levenberg-Marquardt in numpy with closed-form Jacobians
(:func:`core.geometry.distort_normalized_jacobian`) and Huber weights on each corner's
reprojection error. Each camera's 6x6 covariance is the inverse of the Gauss-Newton normal
matrix scaled by the residual variance; its parameters are the camera's position in the world
(m) and a rotation about world axes (rad) applied on the left of ``R_world_cam``.

Intrinsics stay as the cameras have them (calibrate them first, ``intrinsics``).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np

from calibration.board import (
    BoardDetection,
    BoardSpecError,
    CalibrationError,
    CharucoBoardSpec,
)
from calibration.least_squares import Damping, Problem, huber_weights, levenberg_marquardt
from calibration.site_file import pose_node
from core.camera import CameraModel
from core.config_file import ConfigReader, join_key, read_yaml_file
from core.geometry import (
    invert_transform,
    quaternion_to_rotation,
    rotation_from_rotvec,
    rotation_from_rpy,
)
from core.projection import SOLVER_MIN_DEPTH_M, project_world_points

log = logging.getLogger(__name__)

#: Fewest corners a sighting needs to enter the adjustment.
MIN_SIGHTING_CORNERS: Final = 6
#: A sighting whose own PnP fit is worse than this (px RMS) is left out (a misdetection).
MAX_PNP_RMS_PX: Final = 3.0
#: Huber threshold on a corner's reprojection error, pixels.
HUBER_PX: Final = 2.0
MAX_ITERATIONS: Final = 50


@dataclasses.dataclass(frozen=True, eq=False)
class BoardSighting:
    """The board seen by camera ``camera_id`` at ``stamp`` (a key shared by the cameras that saw
    the same board pose: a time stamp or an image index); corners as in
    :class:`~calibration.board.BoardDetection`."""

    camera_id: str
    stamp: str
    corner_ids: np.ndarray
    corners_px: np.ndarray

    @classmethod
    def from_detection(cls, camera_id: str, stamp: str, det: BoardDetection) -> BoardSighting:
        return cls(camera_id, stamp, det.corner_ids, det.corners_px)


@dataclasses.dataclass(frozen=True, eq=False)
class CameraExtrinsics:
    """One camera's solved pose. ``T_world_cam`` (4, 4); ``covariance`` (6, 6) of (position in
    the world, m; rotation about world axes, rad); ``rms_px`` its corners' reprojection RMS."""

    camera_id: str
    T_world_cam: np.ndarray
    covariance: np.ndarray
    rms_px: float
    num_sightings: int
    num_corners: int

    @property
    def std_position_m(self) -> float:
        return float(math.sqrt(max(float(np.trace(self.covariance[:3, :3])), 0.0)))

    @property
    def std_rotation_deg(self) -> float:
        return float(math.degrees(math.sqrt(max(float(np.trace(self.covariance[3:, 3:])), 0.0))))


@dataclasses.dataclass(frozen=True, eq=False)
class BoardExtrinsicsResult:
    """The joint solution: ``cameras`` by id, ``board_poses`` stamp -> ``T_world_board``
    (the fixed ones as given), ``rms_px`` over every corner, ``initial`` the PnP-chained
    ``T_world_cam`` it started from, ``skipped`` (camera id, stamp) -> why a sighting was left
    out."""

    cameras: dict[str, CameraExtrinsics]
    board_poses: dict[str, np.ndarray]
    fixed_stamps: tuple[str, ...]
    rms_px: float
    iterations: int
    initial: dict[str, np.ndarray]
    skipped: dict[tuple[str, str], str]

    def report(self) -> str:
        lines = [f"joint adjustment: {sum(c.num_corners for c in self.cameras.values())} corner "
                 f"sightings, {len(self.board_poses)} board poses ({len(self.fixed_stamps)} "
                 f"fixed), RMS {self.rms_px:.3f} px after {self.iterations} iterations"]
        for cam in self.cameras.values():
            p = cam.T_world_cam[:3, 3]
            lines.append(
                f"  {cam.camera_id}: at ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m, RMS "
                f"{cam.rms_px:.3f} px, {cam.num_sightings} sightings / {cam.num_corners} corners,"
                f" std {100 * cam.std_position_m:.2f} cm / {cam.std_rotation_deg:.3f} deg")
        for (cam_id, stamp), why in sorted(self.skipped.items()):
            lines.append(f"  skipped {cam_id} @ {stamp}: {why}")
        return "\n".join(lines)


# ------------------------------------------------------------------------------ start


def _pnp(camera: CameraModel, obj: np.ndarray, img: np.ndarray) -> tuple[np.ndarray, float]:
    """(T_cam_board (4, 4), RMS px) of one sighting."""
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist)
    if not ok:
        return np.eye(4), math.inf
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, camera.K, camera.dist)
    rms = float(np.sqrt(((proj.reshape(-1, 2) - img) ** 2).sum(axis=1).mean()))
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.reshape(3)
    return T, rms


def _chain(pnp: dict[tuple[str, str], tuple[np.ndarray, int]],
           fixed: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray],
                                                     dict[str, np.ndarray]]:
    """Camera and board poses from the fixed boards outwards through shared sightings, each
    from the sighting with the most corners."""
    boards = {s: np.asarray(T, float) for s, T in fixed.items()}
    cams: dict[str, np.ndarray] = {}
    changed = True
    while changed:
        changed = False
        best: dict[str, tuple[int, np.ndarray]] = {}
        for (cam, stamp), (T_cam_board, n) in pnp.items():
            if cam not in cams and stamp in boards and n > best.get(cam, (-1, None))[0]:
                best[cam] = (n, boards[stamp] @ invert_transform(T_cam_board))
        for cam, (_, T) in best.items():
            cams[cam] = T
            changed = True
        best_b: dict[str, tuple[int, np.ndarray]] = {}
        for (cam, stamp), (T_cam_board, n) in pnp.items():
            if stamp not in boards and cam in cams and n > best_b.get(stamp, (-1, None))[0]:
                best_b[stamp] = (n, cams[cam] @ T_cam_board)
        for stamp, (_, T) in best_b.items():
            boards[stamp] = T
            changed = True
    return cams, boards


# ------------------------------------------------------------------------------ adjustment


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices of (..., 3) vectors."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


@dataclasses.dataclass
class BoardProblem:
    """The joint adjustment's data: corner ``n`` was seen by camera ``obs_cam[n]`` (index into
    ``cam_ids``) on the board at ``stamps[obs_board[n]]``, at ``X_board[n]`` on the board (m)
    and ``uv[n]`` in the image (px). ``free_board``: the board poses being solved (the others
    are fixed in the map frame). The state is ``(R_wc (C, 3, 3), c_w (C, 3), R_wb (B, 3, 3),
    t_wb (B, 3))``: each camera's ``R_world_cam`` and position, each board's pose."""

    cam_ids: list[str]
    stamps: list[str]  # every board pose, fixed ones included
    free_board: np.ndarray  # (B,) bool
    K: np.ndarray  # (C, 3, 3)
    dist: np.ndarray  # (C, 8)
    obs_cam: np.ndarray  # (N,)
    obs_board: np.ndarray  # (N,)
    X_board: np.ndarray  # (N, 3)
    uv: np.ndarray  # (N, 2)

    @property
    def num_params(self) -> int:
        return 6 * len(self.cam_ids) + 6 * int(self.free_board.sum())

    def board_cols(self) -> np.ndarray:
        """(B,) first column of each board's parameters (-1: fixed)."""
        cols = np.full(len(self.stamps), -1)
        cols[self.free_board] = 6 * len(self.cam_ids) + 6 * np.arange(int(self.free_board.sum()))
        return cols

    def residuals(self, R_wc: np.ndarray, c_w: np.ndarray, R_wb: np.ndarray, t_wb: np.ndarray,
                  jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, 2) reprojection errors (predicted - observed, px) and (N, 2, 12) Jacobian
        with respect to the corner's camera and board (columns: :meth:`columns`)."""
        ci, bi = self.obs_cam, self.obs_board
        RX = np.einsum("nij,nj->ni", R_wb[bi], self.X_board)
        proj = project_world_points(R_wc[ci], c_w[ci], self.K[ci], self.dist[ci],
                                    RX + t_wb[bi], jacobians=jacobian,
                                    min_depth_m=SOLVER_MIN_DEPTH_M)
        r = proj.uv - self.uv
        if not jacobian:
            return r, None
        assert proj.d_uv_d_camera is not None and proj.d_uv_d_point is not None
        G, D = proj.d_uv_d_camera, proj.d_uv_d_point  # (N, 2, 6) rotation, position; (N, 2, 3)
        J_cam = np.concatenate([G[..., 3:], G[..., :3]], axis=2)  # position, then rotation
        J_board = np.concatenate([D, D @ -_skew(RX)], axis=2)
        # each corner touches its camera's 6 columns and its board's 6 (a fixed board's go to
        # a dummy column P, dropped when the normal equations are assembled)
        J = np.concatenate([J_cam, J_board], axis=2)  # (N, 2, 12)
        return r, J

    def huber_cost(self, R_wc: np.ndarray, c_w: np.ndarray, R_wb: np.ndarray,
                   t_wb: np.ndarray, huber_px: float) -> float:
        """The adjustment's cost: the Huber loss (threshold ``huber_px``) of every corner's
        reprojection error, summed (``inf`` where a corner cannot be projected)."""
        r, _ = self.residuals(R_wc, c_w, R_wb, t_wb, jacobian=False)
        if not np.all(np.isfinite(r)):
            return math.inf
        e = np.linalg.norm(r, axis=1)
        return float(np.where(e <= huber_px, 0.5 * e * e, huber_px * (e - 0.5 * huber_px)).sum())

    def columns(self) -> np.ndarray:
        """(N, 12) parameter column of each entry of :meth:`residuals`' Jacobian (P: none)."""
        board_col = self.board_cols()[self.obs_board]
        board_col = np.where(board_col >= 0, board_col, self.num_params)
        k = np.arange(6)
        return np.concatenate([6 * self.obs_cam[:, None] + k,
                               np.where(board_col[:, None] < self.num_params,
                                        board_col[:, None] + k, self.num_params)], axis=1)

    def normal_equations(self, r: np.ndarray, J: np.ndarray, w: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
        """(H (P, P), g (P,)) of the weighted problem: sum over corners of w J^T J, w J^T r,
        assembled block by block (each corner's Jacobian has 12 non-zero columns)."""
        P = self.num_params
        cols = self.columns()
        blocks = np.einsum("n,nai,naj->nij", w, J, J)  # (N, 12, 12)
        flat = (cols[:, :, None] * (P + 1) + cols[:, None, :]).ravel()
        H = np.bincount(flat, weights=blocks.ravel(), minlength=(P + 1) ** 2)
        gv = np.einsum("n,nai,na->ni", w, J, r)
        g = np.bincount(cols.ravel(), weights=gv.ravel(), minlength=P + 1)
        return H.reshape(P + 1, P + 1)[:P, :P], g[:P]


BoardState = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@dataclasses.dataclass(frozen=True, eq=False)
class BoardAdjustment:
    """A joint adjustment ready to run: the :class:`BoardProblem`, the PnP-chained ``initial``
    state, the ``fixed`` board poses, the PnP-chained ``initial_cameras`` (``T_world_cam``) and
    the sightings left out (``skipped``, (camera id, stamp) -> why)."""

    problem: BoardProblem
    initial: BoardState
    fixed: dict[str, np.ndarray]
    initial_cameras: dict[str, np.ndarray]
    skipped: dict[tuple[str, str], str]


def solve_board_extrinsics(cameras: Mapping[str, CameraModel],
                           sightings: Sequence[BoardSighting], spec: CharucoBoardSpec,
                           fixed_board_poses: Mapping[str, np.ndarray], *,
                           huber_px: float = HUBER_PX,
                           max_iterations: int = MAX_ITERATIONS) -> BoardExtrinsicsResult:
    """Solve every camera's ``T_world_cam`` that the sightings tie to a fixed board pose.

    ``cameras``: intrinsics (their extrinsics are not used); ``fixed_board_poses``: stamp ->
    ``T_world_board`` (4, 4) known in the map frame (at least one, seen by some camera).
    Cameras that no chain of sightings ties to a fixed board pose are left out of the result
    (logged; the caller names them). Raises :class:`CalibrationError` when no camera saw the
    board at a fixed pose, naming the fixed stamps and the cameras that had sightings.
    """
    adjustment = prepare_board_adjustment(cameras, sightings, spec, fixed_board_poses)
    state, iterations = adjust_board(adjustment.problem, adjustment.initial, huber_px,
                                     max_iterations)
    return board_result(adjustment, state, iterations)


def prepare_board_adjustment(cameras: Mapping[str, CameraModel],
                             sightings: Sequence[BoardSighting], spec: CharucoBoardSpec,
                             fixed_board_poses: Mapping[str, np.ndarray]) -> BoardAdjustment:
    """The joint adjustment of :func:`solve_board_extrinsics` up to the solve: sightings
    checked (each by its own PnP fit), cameras and boards chained from the fixed board poses
    outwards, the corners gathered. Raises as :func:`solve_board_extrinsics`."""
    if not fixed_board_poses:
        raise CalibrationError("no fixed board pose: give the board's pose in the map frame "
                               "for one stamp (or the robot's localization for each)")
    corners_board = spec.corners_board_m()
    skipped: dict[tuple[str, str], str] = {}
    pnp: dict[tuple[str, str], tuple[np.ndarray, int]] = {}
    kept: list[BoardSighting] = []
    for s in sightings:
        key = (s.camera_id, s.stamp)
        if s.camera_id not in cameras:
            skipped[key] = f"camera {s.camera_id!r} is not in the site"
            continue
        if key in pnp:
            skipped[key] = "a second sighting of the same camera and stamp"
            continue
        if len(s.corner_ids) < MIN_SIGHTING_CORNERS:
            skipped[key] = f"{len(s.corner_ids)} corners < {MIN_SIGHTING_CORNERS}"
            continue
        obj = corners_board[s.corner_ids]
        T, rms = _pnp(cameras[s.camera_id], obj, np.asarray(s.corners_px, float))
        if not rms <= MAX_PNP_RMS_PX:
            skipped[key] = f"its own PnP fit is poor (RMS {rms:.2f} px > {MAX_PNP_RMS_PX})"
            continue
        pnp[key] = (T, len(s.corner_ids))
        kept.append(s)
    fixed = {str(k): np.asarray(v, float) for k, v in fixed_board_poses.items()}
    init_cams, init_boards = _chain(pnp, fixed)
    seen = sorted({s.camera_id for s in kept} | {c for c, _ in skipped})
    missing = [c for c in sorted(cameras) if c not in init_cams]
    if not init_cams:
        fixed_seen = sorted(set(fixed) & {s.stamp for s in kept})
        raise CalibrationError(
            f"no camera saw the board at a fixed pose (fixed stamps: {sorted(fixed)}; seen: "
            f"{fixed_seen or 'none'}); cameras with sightings: {seen}")
    if missing:
        log.warning("cameras not tied to the map frame by any sighting: %s", missing)
    cam_ids = sorted(init_cams)
    stamps = sorted(init_boards)
    cam_index = {c: i for i, c in enumerate(cam_ids)}
    board_index = {s: i for i, s in enumerate(stamps)}
    obs_cam, obs_board, X, uv = [], [], [], []
    for s in kept:
        if s.camera_id not in cam_index or s.stamp not in board_index:
            skipped[(s.camera_id, s.stamp)] = "not connected to a fixed board pose"
            continue
        n = len(s.corner_ids)
        obs_cam.append(np.full(n, cam_index[s.camera_id]))
        obs_board.append(np.full(n, board_index[s.stamp]))
        X.append(corners_board[s.corner_ids])
        uv.append(np.asarray(s.corners_px, float))
    dist8 = np.zeros((len(cam_ids), 8))
    for i, c in enumerate(cam_ids):
        dist8[i, :cameras[c].dist.size] = cameras[c].dist
    prob = BoardProblem(cam_ids, stamps, np.array([s not in fixed for s in stamps]),
                        np.stack([cameras[c].K for c in cam_ids]), dist8,
                        np.concatenate(obs_cam), np.concatenate(obs_board), np.concatenate(X),
                        np.concatenate(uv))
    R_wc = np.stack([init_cams[c][:3, :3] for c in cam_ids])
    c_w = np.stack([init_cams[c][:3, 3] for c in cam_ids])
    R_wb = np.stack([init_boards[s][:3, :3] for s in stamps])
    t_wb = np.stack([init_boards[s][:3, 3] for s in stamps])
    return BoardAdjustment(prob, (R_wc, c_w, R_wb, t_wb), fixed, init_cams, skipped)


def board_result(adjustment: BoardAdjustment, state: BoardState, iterations: int
                 ) -> BoardExtrinsicsResult:
    """The :class:`BoardExtrinsicsResult` of an adjusted ``state``: each camera's pose, its
    covariance (the boards marginalized, scaled by the residual variance) and RMS."""
    prob, fixed, skipped = adjustment.problem, adjustment.fixed, adjustment.skipped
    cam_ids, stamps = prob.cam_ids, prob.stamps
    R_wc, c_w, R_wb, t_wb = state
    r, J = prob.residuals(R_wc, c_w, R_wb, t_wb, jacobian=True)
    assert J is not None
    dof = max(2 * len(r) - prob.num_params, 1)
    sigma2 = float((r ** 2).sum()) / dof
    # the cameras' block of the inverse normal matrix, boards marginalized
    H, g = prob.normal_equations(r, J, np.ones(len(r)))
    try:
        cov = _schur_solve(H, g, 6 * len(cam_ids))[1] * sigma2
    except np.linalg.LinAlgError:
        cov = np.full((6 * len(cam_ids), 6 * len(cam_ids)), np.inf)
    err2 = (r ** 2).sum(axis=1)
    out: dict[str, CameraExtrinsics] = {}
    for i, c in enumerate(cam_ids):
        mine = prob.obs_cam == i
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_wc[i], c_w[i]
        num_sightings = len({int(b) for b in prob.obs_board[mine]})
        out[c] = CameraExtrinsics(c, T, cov[6 * i:6 * i + 6, 6 * i:6 * i + 6],
                                  float(np.sqrt(err2[mine].mean())), num_sightings,
                                  int(mine.sum()))
    boards: dict[str, np.ndarray] = {}
    for j, stamp in enumerate(stamps):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_wb[j], t_wb[j]
        boards[stamp] = fixed.get(stamp, T)
    result = BoardExtrinsicsResult(out, boards, tuple(sorted(set(fixed) & set(stamps))),
                                   float(np.sqrt(err2.mean())), iterations,
                                   adjustment.initial_cameras, skipped)
    log.debug("%s", result.report())
    return result


def _schur_solve(A: np.ndarray, g: np.ndarray, num_cam_params: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Solve ``A x = g`` for a normal matrix whose free-board part is block diagonal (6 x 6 per
    board): the boards are eliminated (Schur complement), the cameras' small system solved,
    the boards back-substituted. Returns (x (P,), the inverse Schur complement (6C, 6C), i.e.
    the cameras' block of ``A^-1``)."""
    c = num_cam_params
    nb = (len(g) - c) // 6
    S, rhs = A[:c, :c], g[:c]
    if nb:
        idx = np.arange(nb)
        B_inv = np.linalg.inv(A[c:, c:].reshape(nb, 6, nb, 6)[idx, :, idx, :])  # (nb, 6, 6)
        A_cb = A[:c, c:].reshape(c, nb, 6)
        W = np.einsum("cbi,bij->cbj", A_cb, B_inv)
        S = S - np.einsum("cbj,dbj->cd", W, A_cb)
        rhs = rhs - np.einsum("cbj,bj->c", W, g[c:].reshape(nb, 6))
    S_inv = np.linalg.inv(S)
    x_cam = S_inv @ rhs
    if not nb:
        return x_cam, S_inv
    x_board = np.einsum("bij,bj->bi", B_inv,
                        g[c:].reshape(nb, 6) - np.einsum("cbi,c->bi", A_cb, x_cam))
    return np.concatenate([x_cam, x_board.ravel()]), S_inv


#: the board adjustment's damping: relaxed tenfold after a kept step, down to 1e-9
BOARD_DAMPING: Final = Damping(initial=1e-3, down=10.0, floor=1e-9, step_tol=1e-9,
                               rel_tol=1e-10)


def adjust_board(prob: BoardProblem, state: BoardState, huber_px: float = HUBER_PX,
                 max_iterations: int = MAX_ITERATIONS) -> tuple[BoardState, int]:
    """Every camera's and free board's pose minimising the corners' Huber reprojection cost
    (:meth:`BoardProblem.huber_cost`) from ``state``, by
    :func:`calibration.least_squares.levenberg_marquardt` (the boards eliminated by Schur
    complement in each step); the adjusted state and the iterations run."""
    C = len(prob.cam_ids)
    free_idx = np.flatnonzero(prob.free_board)

    def linearize(x: BoardState) -> tuple[np.ndarray, np.ndarray]:
        r, J = prob.residuals(*x, jacobian=True)
        assert J is not None
        return prob.normal_equations(r, J, huber_weights(np.linalg.norm(r, axis=1), huber_px))

    def cost(x: BoardState) -> float:
        return prob.huber_cost(*x, huber_px)

    def step(x: BoardState, A: np.ndarray, g: np.ndarray) -> tuple[BoardState, np.ndarray]:
        R_wc, c_w, R_wb, t_wb = x
        delta = -_schur_solve(A, g, 6 * C)[0]
        d_cam = delta[:6 * C].reshape(C, 6)
        n_R_wc = np.stack([rotation_from_rotvec(d[3:]) @ R for d, R in zip(d_cam, R_wc,
                                                                             strict=True)])
        n_R_wb, n_t_wb = R_wb.copy(), t_wb.copy()
        d_board = delta[6 * C:].reshape(-1, 6)
        for k, j in enumerate(free_idx):
            n_R_wb[j] = rotation_from_rotvec(d_board[k, 3:]) @ R_wb[j]
            n_t_wb[j] = t_wb[j] + d_board[k, :3]
        return (n_R_wc, c_w + d_cam[:, :3], n_R_wb, n_t_wb), delta

    return levenberg_marquardt(Problem(linearize, cost, step), state, max_iterations,
                               BOARD_DAMPING)


# ------------------------------------------------------------------------------ files


def transform_from_yaml(ctx: ConfigReader, key: str, value: Any) -> np.ndarray:
    """A pose ``{translation_m: [x, y, z], rpy_deg: [r, p, y] | quaternion_xyzw: [x, y, z, w]}``
    (the site file's forms) as (4, 4)."""
    node = ctx.mapping(key, value)
    ctx.no_unknown(key, node, {"translation_m", "rpy_deg", "quaternion_xyzw"})
    t = ctx.vector(join_key(key, "translation_m"), ctx.require(key, node, "translation_m"), 3)
    given = [k for k in ("rpy_deg", "quaternion_xyzw") if k in node]
    if len(given) != 1:
        raise ctx.fail(key, "give exactly one of rpy_deg, quaternion_xyzw")
    if given[0] == "rpy_deg":
        rpy = ctx.vector(join_key(key, "rpy_deg"), node["rpy_deg"], 3)
        R = rotation_from_rpy(*(float(a) for a in np.deg2rad(rpy)))
    else:
        q = ctx.vector(join_key(key, "quaternion_xyzw"), node["quaternion_xyzw"], 4)
        if np.linalg.norm(q) < 1e-9:
            raise ctx.fail(join_key(key, "quaternion_xyzw"), "all zero")
        R = quaternion_to_rotation(q)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def pose_from_xyz_rpy(text: str) -> np.ndarray:
    """(4, 4) from ``"x y z roll pitch yaw"`` (metres, degrees); ``ValueError`` naming what is
    wrong."""
    parts = text.replace(",", " ").split()
    if len(parts) != 6:
        raise ValueError(f"expected 'x y z roll pitch yaw' (m, deg), got {text!r}")
    try:
        x, y, z, roll, pitch, yaw = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"expected six numbers 'x y z roll pitch yaw', got {text!r}") from None
    T = np.eye(4)
    T[:3, :3] = rotation_from_rpy(*np.deg2rad([roll, pitch, yaw]))
    T[:3, 3] = (x, y, z)
    return T


def load_board_poses(path: str | Path) -> dict[str, np.ndarray]:
    """Board poses in the map frame per stamp (``board_poses: {<stamp>: {translation_m,
    rpy_deg | quaternion_xyzw}}``), e.g. from the robot's localization with the board mounted
    on the robot; errors name the file and key."""
    doc = read_yaml_file(path, "board poses", BoardSpecError)
    ctx = ConfigReader(str(path), BoardSpecError)
    top = ctx.mapping("", doc)
    ctx.no_unknown("", top, {"board_poses"})
    node = ctx.mapping("board_poses", ctx.require("", top, "board_poses"))
    if not node:
        raise ctx.fail("board_poses", "empty: give at least one stamp's pose")
    return {str(stamp): transform_from_yaml(ctx, f"board_poses.{stamp}", value)
            for stamp, value in node.items()}


def site_header(result: BoardExtrinsicsResult, site_path: str | Path,
                unsolved: Sequence[str] = ()) -> str:
    """The header of a site file written from ``result``
    (:func:`calibration.site_file.write_site_with_cameras`): the source, the
    adjustment's report with each camera's uncertainty, the cameras left as they were."""
    lines = [f"cameras' T_world_cam from `smartedge calibrate extrinsics` (source: "
             f"{Path(site_path).name})", *result.report().splitlines()]
    if unsolved:
        lines.append(f"not solved (pose as before): {', '.join(unsolved)}")
    return "\n".join(lines)


def report_yaml(result: BoardExtrinsicsResult) -> dict[str, Any]:
    """The machine-readable report: per camera pose, std, 6x6 covariance, RMS, sightings."""
    return {
        "rms_px": round(result.rms_px, 4),
        "iterations": result.iterations,
        "fixed_stamps": list(result.fixed_stamps),
        "cameras": {
            c.camera_id: {
                "T_world_cam": pose_node(c.T_world_cam),
                "std_position_m": round(c.std_position_m, 6),
                "std_rotation_deg": round(c.std_rotation_deg, 5),
                "covariance_position_m_rotation_rad": [[float(f"{v:.6g}") for v in row]
                                                       for row in c.covariance],
                "rms_px": round(c.rms_px, 4),
                "sightings": c.num_sightings,
                "corners": c.num_corners,
            } for c in result.cameras.values()},
        "board_poses": {s: pose_node(T) for s, T in result.board_poses.items()},
        "skipped": [{"camera": c, "stamp": s, "reason": why}
                    for (c, s), why in sorted(result.skipped.items())],
    }


def sightings_by_stamp(sightings: Sequence[BoardSighting]) -> dict[str, list[str]]:
    """stamp -> the cameras that saw the board then (for reports)."""
    out: dict[str, list[str]] = collections.defaultdict(list)
    for s in sightings:
        out[s.stamp].append(s.camera_id)
    return dict(out)
