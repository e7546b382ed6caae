"""Public entry point of the multi-view robot pose estimation: :func:`estimate_pose`.

One frame-set in, one :class:`PoseResult` out. Steps (paper Sec. III-B):

1. validate the observations: unknown cameras, wrong keypoint counts, non-finite keypoints and
   keypoints below the score threshold are dropped; the rest are weighted by the detector's
   per-keypoint uncertainty where it sends one (w = (floor / max(sigma, floor))^2 with
   ``SolverConfig.sigma_floor_px``: in (0, 1] like a confidence), else by their confidences;
2. initialize from the prior or, without one, from per-view PnP (:mod:`.pose_init`);
3. solve Eq. 2 with the cached CasADi formulation (:mod:`.pose_solver`), optionally with a
   robust loss; if the solve from the prior fails or fits badly, retry from PnP;
4. reject impossible solutions (keypoints behind a camera, reprojection RMSE above
   ``thresholds.max_reprojection_rmse_px``);
5. covariance (:mod:`.covariance`): s^2 (J^T W J)^-1, the Gauss-Newton covariance of the
   weighted reprojection errors scaled by the residual variance s^2 (floored at
   ``covariance_floor_px``^2), plus the correlated errors the residuals cannot show (a
   detection's common shift and scale, the cameras' calibration error) propagated through the
   solve; it shrinks with more cameras and grows with the residual, as the paper prescribes
   for the pose-graph weights, and it is consistent (docs/pose_estimation.md, NEES);
6. single camera with a prior (``SolverConfig.single_camera``): ``"map"`` combines the solve
   and a prior that comes with its own covariance by information, weak along the viewing
   ray (:func:`.covariance.fuse_with_prior`); ``"paper"`` the bearing-only heuristic
   (:mod:`.single_camera`).

Bad input never raises: the result then has ``estimate=None`` and a ``reason``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from typing import Final

import numpy as np

from backend_service.covariance import (
    CovarianceParts,
    fuse_with_prior,
    propagate_correlated,
    valid_covariance,
)
from backend_service.frame_set import FrameSet, frame_set_from_detections
from backend_service.pose_init import View, init_from_prior, init_without_prior
from backend_service.pose_solver import PoseProblem, SolverConfig, get_problem, robust_weights
from backend_service.projection import stacked_cameras, weighted_residuals
from backend_service.single_camera import apply_single_camera_heuristic
from core.camera import CameraModel
from core.geometry import rotation_from_rpy, rpy_from_rotation, wrap_angle
from core.pose import PlanarPose
from core.site import Site
from protocol.messages import PoseEstimate, RobotDetections

log = logging.getLogger(__name__)

__all__ = ["PoseResult", "SolverConfig", "estimate_from_detections", "estimate_pose",
           "solver_views"]

#: A keypoint this close to (or behind) a camera's image plane makes the solution impossible.
MIN_DEPTH_M: Final = 0.05
#: Minimum number of usable keypoints over all views (3 unknowns need >= 4 equations).
MIN_TOTAL_KEYPOINTS: Final = 2
#: Under a robust loss, a solution that fewer than this share of the keypoints fit (within
#: ``_INLIER_SCALES`` robust scales) is a wrong minimum, not an estimate.
MIN_INLIER_SHARE: Final = 0.5
#: Inlier threshold (multiples of the robust scale) for the RMSE reported under a robust loss.
_INLIER_SCALES: Final = 3.0
#: Methods solved by a CasADi ``nlpsol`` (with the LM path as their fallback).
_NLP_METHODS: Final = ("ipopt", "sqpmethod")


@dataclasses.dataclass(frozen=True, eq=False)
class PoseResult:
    """Outcome of one :func:`estimate_pose` call.

    ``estimate``: the :class:`protocol.PoseEstimate` (``source="cameras"``, ``seq=0``: the
    publisher sets it) or ``None``. ``pose``: the same planar pose (world frame) for in-process
    callers. ``reason``: ``""`` when ok, else why there is no estimate. ``T_world_robot``:
    (4, 4) robot base -> world of the solution (full 6-DoF for ``dof=6``). ``iterations``:
    solver iterations. ``covariance_parts``: the estimate's covariance split into the part new
    in every frame and the systematic part (what averaging frames cannot reduce).
    """

    estimate: PoseEstimate | None
    pose: PlanarPose | None
    reason: str = ""
    T_world_robot: np.ndarray | None = None
    iterations: int = 0
    covariance_parts: CovarianceParts | None = None

    @property
    def ok(self) -> bool:
        return self.estimate is not None and not self.reason


def _fail(reason: str) -> PoseResult:
    return PoseResult(None, None, reason)


def estimate_pose(frame_set: FrameSet, site: Site, prior: PlanarPose | None = None,
                  config: SolverConfig | None = None,
                  prior_covariance: np.ndarray | None = None) -> PoseResult:
    """Estimate the robot's planar pose (world frame) from one synchronized frame-set.

    ``prior``: the robot's current pose in the world (map) frame, or ``None`` (kidnapped robot:
    PnP initialization). ``prior_covariance``: (3, 3) of the prior (x, y, theta), when it is
    independent of the cameras (e.g. the robot's own localization): a single-camera solve is
    then combined with it (``SolverConfig.single_camera``). ``config``: solver options
    (defaults: :class:`SolverConfig`); thresholds come from ``site.thresholds``. Never raises
    on bad input.
    """
    if not isinstance(frame_set, FrameSet):
        raise TypeError(f"frame_set: expected backend_service.FrameSet, got "
                        f"{type(frame_set).__name__} (for RobotDetections messages use "
                        "estimate_from_detections)")
    try:
        return _estimate(frame_set, site, prior, config or SolverConfig(), prior_covariance)
    except Exception as exc:  # a service-facing function must not raise
        log.exception("pose estimation failed unexpectedly")
        return _fail(f"internal error: {type(exc).__name__}: {exc}")


def estimate_from_detections(site: Site, detections: Sequence[RobotDetections] | RobotDetections,
                             prior: PlanarPose | None = None,
                             config: SolverConfig | None = None,
                             robot_id: str | None = None,
                             prior_covariance: np.ndarray | None = None) -> PoseResult:
    """The robot's pose from camera messages taken at (about) the same time: the entry point for
    code that has :class:`~protocol.messages.RobotDetections` rather than a frame-set.

    ``detections``: one message per camera (a single message is accepted); ``prior``: the
    robot's current world pose, or ``None`` (PnP initialization), with ``prior_covariance``
    as in :func:`estimate_pose`; ``robot_id``: which robot (needed only when the site has
    several). The messages get the synchronizer's checks
    (:func:`backend_service.frame_set.frame_set_from_detections`); what was dropped is in
    ``PoseResult.reason`` when nothing usable remains, else logged at debug level. For a stream
    of messages use :class:`backend_service.sync.FrameSetSynchronizer` and
    :func:`estimate_pose` (or the whole :class:`backend_service.pipeline.BackendPipeline`).
    ``TypeError`` for arguments of the wrong type (naming what was expected); bad data never
    raises.
    """
    if not isinstance(site, Site):
        raise TypeError(f"site: expected core.site.Site (load_site(path)), got "
                        f"{type(site).__name__}")
    if prior is not None and not isinstance(prior, PlanarPose):
        raise TypeError(f"prior: expected core.pose.PlanarPose or None, got "
                        f"{type(prior).__name__}")
    if config is not None and not isinstance(config, SolverConfig):
        raise TypeError(f"config: expected SolverConfig or None, got {type(config).__name__}")
    frame_set, problems = frame_set_from_detections(site, detections, robot_id)
    if not frame_set.observations:
        return _fail("no usable detection: " + ("; ".join(problems) or "no messages"))
    if problems:
        log.debug("estimate_from_detections: dropped %s", "; ".join(problems))
    return estimate_pose(frame_set, site, prior, config, prior_covariance)


def solver_views(frame_set: FrameSet, site: Site, config: SolverConfig | None = None
                 ) -> tuple[list[CameraModel], np.ndarray, np.ndarray]:
    """The views a solve of ``frame_set`` uses, sorted by camera id as the solver orders them,
    with the keypoints as it weighs them (step 1 of the module docstring): ``cameras`` (C),
    ``keypoints_px`` (C, M, 2; NaN where not finite) and ``weights`` (C, M; 0 where not used).
    Empty arrays when nothing is usable; never raises on bad data."""
    config = config or SolverConfig()
    try:
        model = site.robot_model(frame_set.robot_id or None)
    except KeyError:
        return [], np.zeros((0, 0, 2)), np.zeros((0, 0))
    kp_base = np.asarray(model.keypoints_base_m, dtype=np.float64)
    th = site.thresholds
    min_score = th.min_keypoint_score if config.min_keypoint_score is None \
        else config.min_keypoint_score
    views, _ = _prepare_views(frame_set, site, kp_base, float(min_score), config.sigma_floor_px)
    M = kp_base.shape[0]
    if not views:
        return [], np.zeros((0, M, 2)), np.zeros((0, M))
    views.sort(key=lambda v: v.camera.camera_id)
    return ([v.camera for v in views], np.stack([v.keypoints_px for v in views]),
            np.stack([np.where(v.valid, v.weights, 0.0) for v in views]))


def _prepare_views(frame_set: FrameSet, site: Site, kp_base: np.ndarray,
                   min_score: float, sigma_floor_px: float = 1.5
                   ) -> tuple[list[View], list[str]]:
    M = kp_base.shape[0]
    problems: list[str] = []
    seen: set[str] = set()
    cams, uvs, scores_list, weights_list = [], [], [], []
    for obs in frame_set.observations:
        cam = site.cameras.get(obs.camera_id)
        if cam is None:
            problems.append(f"unknown camera {obs.camera_id!r}")
            continue
        if obs.camera_id in seen:
            problems.append(f"camera {obs.camera_id!r} appears twice")
            continue
        uv = np.asarray(obs.keypoints_px, dtype=np.float64)
        scores = np.asarray(obs.keypoint_scores, dtype=np.float64)
        if uv.shape != (M, 2) or scores.shape != (M,):
            problems.append(f"camera {obs.camera_id!r}: keypoints {uv.shape} / scores "
                            f"{scores.shape}, model has {M}")
            continue
        sigmas = obs.keypoint_sigmas_px
        if sigmas is not None:
            sigmas = np.asarray(sigmas, dtype=np.float64)
            if sigmas.shape != (M,):
                problems.append(f"camera {obs.camera_id!r}: keypoint sigmas {sigmas.shape}, "
                                f"model has {M}; weighting by score")
                sigmas = None
        seen.add(obs.camera_id)
        cams.append(cam)
        uvs.append(uv)
        scores_list.append(scores)
        weights_list.append(np.clip(scores, 0.0, 1.0) if sigmas is None else
                            np.where(sigmas > 0.0,  # a sigma <= 0 is nonsense: drop it
                                     (sigma_floor_px / np.maximum(sigmas, sigma_floor_px)) ** 2,
                                     0.0))
    if not cams:
        return [], problems
    # all views at once: one vectorized pass instead of a dozen numpy calls per view
    uv_all = np.stack(uvs)
    scores_all = np.stack(scores_list)
    weights_all = np.stack(weights_list)
    finite = (np.isfinite(uv_all).all(axis=2) & np.isfinite(scores_all)
              & np.isfinite(weights_all))
    w_all = np.where(finite & (scores_all >= min_score) & (scores_all > 0), weights_all, 0.0)
    uv_all = np.where(finite[:, :, None], uv_all, np.nan)
    usable = (w_all > 0).any(axis=1)
    views: list[View] = []
    for k, cam in enumerate(cams):
        if not usable[k]:
            problems.append(f"camera {cam.camera_id!r}: no usable keypoints")
            continue
        views.append(View(cam, uv_all[k], w_all[k]))
    return views, problems


def _estimate(frame_set: FrameSet, site: Site, prior: PlanarPose | None,
              config: SolverConfig, prior_covariance: np.ndarray | None = None) -> PoseResult:
    th = site.thresholds
    try:
        model = site.robot_model(frame_set.robot_id or None)
    except KeyError as exc:
        return _fail(f"robot model: {exc.args[0] if exc.args else exc}")
    kp_base = np.asarray(model.keypoints_base_m, dtype=np.float64)
    min_score = th.min_keypoint_score if config.min_keypoint_score is None \
        else config.min_keypoint_score
    views, problems = _prepare_views(frame_set, site, kp_base, float(min_score),
                                     config.sigma_floor_px)
    if not views:
        detail = "; ".join(problems) if problems else "empty frame-set"
        return _fail(f"no usable view: {detail}")
    total = int(sum(v.valid.sum() for v in views))
    if total < MIN_TOTAL_KEYPOINTS or (len(views) == 1 and total < 3):
        return _fail(f"only {total} valid keypoints (need >= {MIN_TOTAL_KEYPOINTS}, "
                     "3 for one camera)")
    if prior is not None and not all(math.isfinite(v) for v in (prior.x, prior.y, prior.theta)):
        prior = None

    views.sort(key=lambda v: v.camera.camera_id)  # one formulation per camera *set*
    cameras = [v.camera for v in views]
    problem = get_problem(cameras, kp_base, config.dof, config.robust_loss)
    uv = np.stack([v.keypoints_px for v in views])
    w = np.stack([np.where(v.valid, v.weights, 0.0) for v in views])
    p = problem.pack(uv, w, config.robust_scale_px)

    flags: list[str] = []
    attempts: list[tuple[str, np.ndarray, np.ndarray | None]] = []
    if prior is not None:
        attempts.append(("prior_init", _q0(init_from_prior(prior), None, config.dof), None))
    pnp_reason = ""

    def pnp_attempt() -> tuple[str, np.ndarray, np.ndarray | None] | None:
        nonlocal pnp_reason
        init = init_without_prior(views, kp_base, th.min_keypoints)
        if init.pose is None:
            pnp_reason = init.reason
            return None
        q0 = _q0(init_from_prior(init.pose), init.T_world_robot, config.dof)
        return ("pnp_init", q0, init.T_world_robot)

    if prior is None:
        first = pnp_attempt()
        if first is None:
            return _fail(f"no prior and no initialization: {pnp_reason}")
        attempts.append(first)

    best: tuple[np.ndarray, float, int, str] | None = None  # q, rmse, iterations, init flag
    last_reason = ""
    tried_pnp = prior is None
    i = 0
    while i < len(attempts):
        init_flag, q0, _ = attempts[i]
        i += 1
        outcome = _solve_once(problem, p, q0, config, th.max_reprojection_rmse_px)
        if isinstance(outcome, str):
            last_reason = outcome
        elif best is None or outcome[1] < best[1] - 1e-6:  # a tie keeps the prior start
            best = (*outcome, init_flag)
        good = best is not None and best[1] <= th.max_reprojection_rmse_px
        # one view under a robust loss has far-away wrong minima that fit "well enough" (the
        # robot shrunk to a dot, half its keypoints inside the loss's inlier band): always
        # compare with the PnP start there and keep the better fit
        single_robust = len(views) == 1 and config.robust_loss != "none"
        if (not good or single_robust) and not tried_pnp and config.try_pnp_fallback:
            tried_pnp = True
            nxt = pnp_attempt()
            if nxt is not None:
                attempts.append(nxt)
    if best is None:
        return _fail(last_reason or "solver failed")
    q, rmse, iterations, best_flag = best
    if rmse > th.max_reprojection_rmse_px:
        return _fail(f"reprojection RMSE {rmse:.1f} px > {th.max_reprojection_rmse_px} px")
    flags.append(best_flag)
    if config.robust_loss != "none":
        flags.append("robust_loss")
    if config.dof == 6:
        flags.append("6dof")

    parts_q = _covariance(problem, p, q, config, cameras, kp_base, w)
    if parts_q is None:
        return _fail("degenerate geometry: the information matrix is singular")
    idx = [0, 1, 2] if config.dof == 3 else [0, 1, 5]
    parts = parts_q.sub(idx)
    pose = PlanarPose(float(q[idx[0]]), float(q[idx[1]]), wrap_angle(float(q[idx[2]])))
    T_world_robot = _T_from_q(q, config.dof)

    if len(views) == 1:
        flags.append("single_camera")
        stacked = stacked_cameras(tuple(cameras))

        def residual_fn(qb: np.ndarray) -> np.ndarray:
            return weighted_residuals(stacked, kp_base, qb, uv, w)

        prior_cov = valid_covariance(prior_covariance)
        if prior is not None and config.single_camera == "map" and prior_cov is not None:
            fused = fuse_with_prior(pose.as_array(), parts, prior.as_array(), prior_cov)
            if fused.used:
                flags.append("map_prior")
                pose = PlanarPose(*(float(v) for v in fused.q))
                parts = fused.parts
                T_world_robot = pose.T()
                rmse = _weighted_rmse(residual_fn(pose.as_array()[None])[0], w, config)
            else:
                flags.append("prior_rejected")
        elif prior is not None and config.single_camera == "paper":
            outcome = apply_single_camera_heuristic(
                cameras[0], prior, pose, math.radians(th.single_camera_max_dtheta_deg),
                th.single_camera_max_ddepth_m, residual_fn)
            if outcome.applied:
                flags.append("lateral_only")
                pose = outcome.pose
                T_world_robot = pose.T()
                cov = _lateral_only_covariance(cameras[0], pose, parts.total,
                                               th.single_camera_max_ddepth_m,
                                               math.radians(th.single_camera_max_dtheta_deg))
                parts = CovarianceParts(cov - parts.systematic, parts.systematic)
                rmse = _weighted_rmse(residual_fn(pose.as_array()[None])[0], w, config)

    cov = parts.total
    cov = 0.5 * (cov + cov.T)
    estimate = PoseEstimate(
        robot_id=frame_set.robot_id or next(iter(site.robots)),
        stamp_ns=max(int(frame_set.stamp_ns), 0),
        seq=0,
        x=pose.x,
        y=pose.y,
        theta=pose.theta,
        covariance=cov,
        source="cameras",
        camera_ids=tuple(v.camera.camera_id for v in views),
        reprojection_rmse_px=float(rmse),
        flags=tuple(flags),
        frame_id=site.world_frame,
    )
    return PoseResult(estimate, pose, "", T_world_robot, iterations, parts)


def _q0(start: np.ndarray, T_world_robot: np.ndarray | None, dof: int) -> np.ndarray:
    if dof == 3:
        return start
    if T_world_robot is None:
        return np.array([start[0], start[1], 0.0, 0.0, 0.0, start[2]])
    roll, pitch, yaw = rpy_from_rotation(T_world_robot[:3, :3])
    t = T_world_robot[:3, 3]
    return np.array([t[0], t[1], t[2], roll, pitch, yaw])


def _T_from_q(q: np.ndarray, dof: int) -> np.ndarray:
    if dof == 3:
        return PlanarPose(float(q[0]), float(q[1]), float(q[2])).T()
    T = np.eye(4)
    T[:3, :3] = rotation_from_rpy(float(q[3]), float(q[4]), float(q[5]))
    T[:3, 3] = q[:3]
    return T


def _inlier_share(r: np.ndarray, w: np.ndarray, config: SolverConfig) -> float:
    """Share of the valid keypoints within ``_INLIER_SCALES`` robust scales."""
    s = r[0::2] ** 2 + r[1::2] ** 2
    wf = w.reshape(-1)
    valid = wf > 0
    if not valid.any():
        return 0.0
    e = np.sqrt(s[valid] / wf[valid])
    return float(np.mean(e <= _INLIER_SCALES * config.robust_scale_px))


def _weighted_rmse(r: np.ndarray, w: np.ndarray, config: SolverConfig) -> float:
    """sqrt(sum w e^2 / sum w) over valid keypoints; under a robust loss only over keypoints
    within a few robust scales (the outliers the loss ignored would dominate otherwise)."""
    s = r[0::2] ** 2 + r[1::2] ** 2  # w * |e|^2 per keypoint
    wf = w.reshape(-1)
    valid = wf > 0
    if config.robust_loss != "none":
        e = np.sqrt(s[valid] / wf[valid])
        keep = e <= _INLIER_SCALES * config.robust_scale_px
        if keep.sum() >= 2:
            valid_idx = np.flatnonzero(valid)[keep]
            return float(math.sqrt(s[valid_idx].sum() / wf[valid_idx].sum()))
    return float(math.sqrt(s[valid].sum() / max(wf[valid].sum(), 1e-12)))


def _solve_once(problem: PoseProblem, p: np.ndarray, q0: np.ndarray, config: SolverConfig,
                max_rmse_px: float) -> tuple[np.ndarray, float, int] | str:
    outcome = _solve_with(problem, p, q0, config, config.method)
    if config.method in _NLP_METHODS and (isinstance(outcome, str) or outcome[1] > max_rmse_px
                                          or not outcome[3]):
        # sqpmethod/IPOPT occasionally stall on the non-smooth robust losses (seen with Huber
        # and gross outliers); the IRLS Levenberg-Marquardt path is the safety net. The
        # numpy-driven methods are already damped least squares: a retry would repeat them.
        retry = _solve_with(problem, p, q0, config, "lm")
        if not isinstance(retry, str) and (isinstance(outcome, str) or retry[1] < outcome[1]):
            outcome = retry
    if isinstance(outcome, str):
        return outcome
    return outcome[0], outcome[1], outcome[2]


def _solve_with(problem: PoseProblem, p: np.ndarray, q0: np.ndarray, config: SolverConfig,
                method: str) -> tuple[np.ndarray, float, int, bool] | str:
    out = problem.solve(q0, p, method, config.max_iterations)
    q = out.q
    if not np.all(np.isfinite(q)):
        return "solver returned a non-finite pose"
    if config.dof == 3:
        q = np.array([q[0], q[1], wrap_angle(float(q[2]))])
    r, _, depth = problem.evaluate(q, p)
    w = p[problem.num_cameras * problem.num_keypoints * 2:-1]
    if np.any(depth[w > 0] < MIN_DEPTH_M):
        return "robot behind a camera: no solution in front of every camera that sees it"
    if not np.all(np.isfinite(r)):
        return "non-finite reprojection residuals"
    if config.robust_loss != "none":
        share = _inlier_share(r, w, config)
        if share < MIN_INLIER_SHARE:
            # a robust loss can make a wrong minimum look good (e.g. the robot slid far away
            # along the viewing ray, every keypoint an "outlier"): most keypoints must fit
            return (f"only {share:.0%} of the keypoints fit this solution (robust loss): "
                    "a wrong minimum")
    return q, _weighted_rmse(r, w, config), out.iterations, out.success


def _covariance(problem: PoseProblem, p: np.ndarray, q: np.ndarray, config: SolverConfig,
                cameras: Sequence[CameraModel], kp_base: np.ndarray,
                w: np.ndarray) -> CovarianceParts | None:
    """Covariance of the solution ``q`` in its own parameters: s^2 (J^T W J)^-1 for the
    independent keypoint noise (s^2 the residual variance, floored) plus the correlated errors
    of ``config.error_model`` propagated through the solve (:mod:`.covariance`)."""
    r, J, _ = problem.evaluate(q, p)
    sw = np.ones_like(r)
    if config.robust_loss != "none":
        s = r[0::2] ** 2 + r[1::2] ** 2
        sw = np.repeat(np.sqrt(robust_weights(s, config.robust_loss, config.robust_scale_px)), 2)
        r, J = r * sw, J * sw[:, None]
    H = J.T @ J
    n_res = int(np.count_nonzero(np.abs(J).sum(axis=1) > 0))
    dof_res = n_res - J.shape[1]
    s2 = float(r @ r) / dof_res if dof_res > 0 else 0.0
    s2 = max(s2, config.covariance_floor_px**2)
    try:
        if np.linalg.cond(H) > 1e12:
            return None
        H_inv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    frame = s2 * H_inv
    systematic = np.zeros_like(frame)
    model = config.error_model
    if model.any:
        # sensitivity to the raw pixel errors: dq = -H^-1 J^T (sqrt(w) * robust sqrt-weight) de
        a = np.repeat(np.sqrt(np.clip(w.reshape(-1), 0.0, None)), 2) * sw
        A = H_inv @ (J.T * a[None, :])
        T = _T_from_q(q, config.dof)
        pts_world = kp_base @ T[:3, :3].T + T[:3, 3]
        extra_frame, systematic = propagate_correlated(A, cameras, pts_world, w, model)
        frame = frame + extra_frame
    return CovarianceParts(0.5 * (frame + frame.T), 0.5 * (systematic + systematic.T))


def _lateral_only_covariance(camera: CameraModel, pose: PlanarPose, cov: np.ndarray,
                             depth_std_m: float, theta_std_rad: float) -> np.ndarray:
    """Covariance of a heuristic pose: the along-ray and orientation components come from the
    prior, not from this frame-set, so they get at least the heuristic's thresholds as std."""
    c_xy = camera.position_world[:2]
    ray = np.array([pose.x - c_xy[0], pose.y - c_xy[1]])
    ray /= max(np.linalg.norm(ray), 1e-9)
    lat = np.array([-ray[1], ray[0]])
    var_lat = float(lat @ cov[:2, :2] @ lat)
    var_ray = max(float(ray @ cov[:2, :2] @ ray), depth_std_m**2)
    B = np.stack([ray, lat], axis=1)
    out = np.zeros((3, 3))
    out[:2, :2] = B @ np.diag([var_ray, var_lat]) @ B.T
    out[2, 2] = max(float(cov[2, 2]), theta_std_rad**2)
    return out
