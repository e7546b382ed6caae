"""Every camera's pose in the robot's map frame, with the robot itself as the calibration target.

While the robot drives with its own localization and odometry, the edge agents publish keypoint
detections of it. The cameras' ``T_world_cam`` (world = the robot's map frame) are estimated
jointly with the robot's trajectory, one planar pose per *node* (every ``node_spacing_s`` of the
drive); a detection between nodes is placed by the odometry increment from its nearest node.

Factors (one sparse least-squares problem, solved by Levenberg-Marquardt in numpy; the normal
equations are dense here, a few thousand unknowns for a 5-minute drive):

- **keypoint reprojection**: the project's camera model (pinhole + OpenCV distortion,
  :mod:`core.geometry`), weighted by the keypoint score (or the detector's own sigma when it
  sends one), Huber loss against outliers, then a gate that drops what still lies far off;
- **odometry between-factors** between consecutive nodes (noise grows with distance and turn);
- **the robot's localization as a weak prior** on every node, with the covariance it reports,
  inflated because its errors are correlated over ``localization_correlation_s``: this alone
  fixes where the whole solution sits in the map frame (x, y, heading: the gauge); its errors
  wander over metres, so that placement is only as good as the localization's average over the
  drive, however good the cameras' geometry relative to each other is;
- cameras that are not recalibrated (``solve_cameras`` names others) but saw the robot: a prior
  at their pose (``held_sigma_m`` / ``held_sigma_deg``); they pin the trajectory and are
  returned unchanged;
- with ``frame="site"``: the recalibrated cameras' mean x, y and heading held at their initial
  poses' instead of the localization's gauge.

Initialisation: the robot poses from its localization; each camera from the site file *or* a
RANSAC PnP of all its sightings against those poses (whichever reprojects better), refined with
the trajectory fixed, then the joint adjustment. A camera given only a rough position and a
look-at point converges this way.

Refusals (:class:`CameraResult.refused` with the reason and the drive that would fix it): too few
sightings (``min_sightings``), or sightings that do not constrain the camera (the weakest
direction of the information of its own sightings, trajectory fixed, exceeds ``max_sigma_m`` /
``max_sigma_deg``, or the robot positions it saw span less than ``min_extent_m``), e.g. the
robot seen only at one place and heading.

The problem itself (factors, Jacobians, normal equations, Levenberg-Marquardt) is
:mod:`calibration.robot_problem`; this module reads the data, initialises, runs
the problem and judges what the drive constrained. Frames: world = map, z up; camera optical
frame (OpenCV, z forward); pixels (u, v). Camera poses are perturbed on the left:
R' = Exp(w) R_world_cam, c' = c + dc (world axes). Transport-free: :class:`CalibrationData`
takes wire messages, :func:`calibrate` returns :class:`CalibrationResult`; reading recordings or
the bus is the caller's (``smartedge calibrate robot``).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np

from calibration.robot_problem import (
    JointProblem,
    Observations,
    adjust,
    robot_points,
    subset_observations,
)
from core.camera import CameraModel
from core.geometry import (
    invert_transform,
    pose_error,
    wrap_angle_array,
)
from core.site import Site
from protocol.errors import SmartedgeError
from protocol.messages import Message, Odometry, PoseEstimate, RobotDetections

log = logging.getLogger(__name__)

__all__ = [
    "CalibrationData",
    "CalibrationError",
    "CalibrationResult",
    "CameraResult",
    "RobotTargetConfig",
    "calibrate",
]


class CalibrationError(SmartedgeError):
    """The data cannot give any calibration (no odometry, no localization, no sightings); the
    message says what is missing."""


@dataclasses.dataclass(frozen=True)
class RobotTargetConfig:
    """Settings of the robot-target calibration (units in the names).

    ``node_spacing_s``: one trajectory node per this much time (more when the drive would need
    more than ``max_nodes``: the normal equations are dense); ``max_frame_rate_hz``: sightings
    per camera kept at most at this rate (15 Hz frames of a slowly moving robot are redundant;
    0 keeps all); ``min_keypoint_score`` / ``min_keypoints``: keypoints below the score are
    ignored, a detection with fewer usable keypoints is skipped; ``min_sightings``: a camera
    with fewer detections is refused; ``max_sigma_m`` / ``max_sigma_deg``: a camera whose own
    sightings leave a direction less constrained than this (1 sigma) is refused, and so is one
    that saw the robot only within ``min_extent_m`` (one place: the information may look
    sufficient, but every systematic keypoint error goes straight into its pose);
    ``held_sigma_m`` / ``held_sigma_deg``: how well the cameras that are not recalibrated
    are known (the site's calibration); they are adjusted within these inside the problem, so
    that their small disagreements do not bend the trajectory the recalibrated camera is fitted
    to, and are reported and written unchanged; ``huber_px``: the robust loss's threshold;
    ``gate_px``: after convergence, keypoints further off than max(gate_px, gate_sigmas x the
    RMS) are dropped and the problem re-solved;
    odometry noise per step: ``odom_sigma_m`` + ``odom_sigma_per_m`` x distance,
    ``odom_sigma_rad`` + ``odom_sigma_rad_per_rad`` x turn + ``odom_sigma_rad_per_m`` x
    distance; ``localization_sigma_scale`` multiplies the reported localization sigmas, and
    ``localization_correlation_s`` is how long its errors stay correlated (the priors of the
    nodes within it count together as one: sigmas x sqrt(correlation / node spacing))
    (``localization_default_sigma_m``/``_deg`` when a message has none, floored at
    ``localization_min_sigma_m``/``_deg``); ``max_odometry_gap_s``: a sighting farther than this
    from odometry on either side is not used.
    """

    node_spacing_s: float = 0.5
    max_frame_rate_hz: float = 5.0
    min_keypoint_score: float = 0.3
    min_keypoints: int = 6
    min_sightings: int = 30
    max_sigma_m: float = 0.01
    max_sigma_deg: float = 0.1
    min_extent_m: float = 1.0
    held_sigma_m: float = 0.015
    held_sigma_deg: float = 0.1
    huber_px: float = 3.0
    gate_px: float = 8.0
    gate_sigmas: float = 5.0
    odom_sigma_m: float = 0.002
    odom_sigma_per_m: float = 0.02
    odom_sigma_rad: float = 0.002
    odom_sigma_rad_per_rad: float = 0.02
    odom_sigma_rad_per_m: float = 0.01
    localization_sigma_scale: float = 1.0
    localization_correlation_s: float = 60.0
    localization_default_sigma_m: float = 0.2
    localization_default_sigma_deg: float = 2.0
    localization_min_sigma_m: float = 0.01
    localization_min_sigma_deg: float = 0.2
    max_odometry_gap_s: float = 0.5
    max_iterations: int = 40
    max_nodes: int = 1200
    pnp_threshold_px: float = 12.0
    init_max_sightings: int = 300

    def __post_init__(self) -> None:
        for name in ("node_spacing_s", "localization_correlation_s", "huber_px", "gate_px",
                     "gate_sigmas", "max_sigma_m", "max_sigma_deg", "localization_sigma_scale",
                     "max_odometry_gap_s", "pnp_threshold_px"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"RobotTargetConfig.{name} must be > 0, got {value!r}")
        if self.min_sightings < 1 or self.min_keypoints < 4 or self.max_iterations < 1:
            raise ValueError("RobotTargetConfig: min_sightings >= 1, min_keypoints >= 4 and "
                             "max_iterations >= 1 are needed")


# --------------------------------------------------------------------------------------------
# input
# --------------------------------------------------------------------------------------------


class CalibrationData:
    """The drive as the calibration needs it, filled from wire messages in any order.

    Detections of cameras the site does not know, of other robots, with the wrong keypoint
    count or with non-finite keypoints are not used and are counted (:attr:`counters`; the
    unknown ids in :attr:`unknown_cameras`). Detection stamps are moved onto the common clock
    with the camera's ``clock_offset_ns``.
    """

    def __init__(self, site: Site, robot_id: str | None = None) -> None:
        self.site = site
        if robot_id is None:
            if len(site.robots) != 1:
                raise CalibrationError(f"site {site.name!r} has {len(site.robots)} robots "
                                       f"({sorted(site.robots)}); name the one that drove")
            robot_id = next(iter(site.robots))
        if robot_id not in site.robots:
            raise CalibrationError(f"robot {robot_id!r} is not in site {site.name!r}; known: "
                                   f"{sorted(site.robots)}")
        self.robot_id = robot_id
        self.keypoints_base_m = np.asarray(site.robot_model(robot_id).keypoints_base_m, float)
        self.counters: collections.Counter[str] = collections.Counter()
        self.unknown_cameras: collections.Counter[str] = collections.Counter()
        #: camera id → list of (common-clock stamp ns, keypoints (M, 2), weights (M,),
        #: scores (M,)); unusable keypoints have weight 0
        self.sightings: dict[str, list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]] = {
            c: [] for c in site.cameras}
        self._odom: list[tuple[int, float, float, float]] = []
        self._loc: list[tuple[int, float, float, float, np.ndarray | None]] = []

    def add(self, message: Message) -> None:
        """One decoded wire message; other types and other robots are counted and ignored."""
        if isinstance(message, RobotDetections):
            self.add_detections(message)
        elif isinstance(message, Odometry):
            if message.robot_id != self.robot_id:
                self.counters["other_robot"] += 1
                return
            self._odom.append((message.stamp_ns, message.x, message.y, message.theta))
            self.counters["odometry"] += 1
        elif isinstance(message, PoseEstimate):
            if message.robot_id != self.robot_id:
                self.counters["other_robot"] += 1
            elif message.source != "robot":
                self.counters["ignored_pose_source"] += 1
            elif message.frame_id != self.site.world_frame:
                self.counters["localization_wrong_frame"] += 1
            else:
                self._loc.append((message.stamp_ns, message.x, message.y, message.theta,
                                  np.asarray(message.covariance, float)))
                self.counters["localization"] += 1
        else:
            self.counters["ignored_message"] += 1

    def add_detections(self, msg: RobotDetections) -> None:
        cam = self.site.cameras.get(msg.camera_id)
        if cam is None:
            self.unknown_cameras[msg.camera_id] += 1
            self.counters["unknown_camera"] += 1
            return
        self.counters["detection_messages"] += 1
        mine = [d for d in msg.detections if d.robot_id in ("", self.robot_id)]
        if not mine:
            self.counters["no_robot_seen"] += 1
            return
        if len(mine) > 1:
            # two candidates for this robot in one image: ambiguous, not a calibration target
            self.counters["ambiguous_detection"] += 1
            return
        det = mine[0]
        M = self.keypoints_base_m.shape[0]
        uv = np.asarray(det.keypoints_px, float)
        scores = np.asarray(det.keypoint_scores, float)
        if uv.shape != (M, 2):
            self.counters["wrong_keypoint_count"] += 1
            return
        finite = np.isfinite(uv).all(axis=1) & np.isfinite(scores)
        if not finite.all():
            self.counters["non_finite_keypoints"] += 1
        if det.keypoint_sigmas_px is not None:
            sig = np.asarray(det.keypoint_sigmas_px, float)
            w = np.where(np.isfinite(sig) & (sig > 0), 1.0 / np.maximum(sig, 1e-6) ** 2, 0.0)
        else:
            w = np.clip(scores, 0.0, 1.0)
        w = np.where(finite & (scores > 0) & np.isfinite(w), w, 0.0)
        self.sightings[msg.camera_id].append(
            (int(msg.stamp_ns) + int(cam.clock_offset_ns), np.where(finite[:, None], uv, 0.0),
             w, np.where(finite, scores, 0.0)))
        self.counters["sightings"] += 1

    def odometry_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps ns (N,), poses (N, 3)) sorted, duplicates removed."""
        return _sorted_poses([(t, x, y, th) for t, x, y, th in self._odom])

    def localization_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(stamps (N,), poses (N, 3), covariances (N, 3, 3); NaN where none was valid)."""
        if not self._loc:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))
        items = sorted(self._loc, key=lambda r: r[0])
        stamps = np.array([r[0] for r in items], np.int64)
        keep = np.concatenate([[True], np.diff(stamps) > 0])
        poses = np.array([r[1:4] for r in items], float)
        covs = np.full((len(items), 3, 3), np.nan)
        for i, r in enumerate(items):
            c = r[4]
            if c is not None and c.shape == (3, 3) and np.all(np.isfinite(c)):
                c = 0.5 * (c + c.T)
                if np.all(np.linalg.eigvalsh(c) > 0):
                    covs[i] = c
        return stamps[keep], poses[keep], covs[keep]


def _sorted_poses(rows: Sequence[tuple[int, float, float, float]]
                  ) -> tuple[np.ndarray, np.ndarray]:
    if not rows:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    rows = sorted(rows, key=lambda r: r[0])
    stamps = np.array([r[0] for r in rows], np.int64)
    keep = np.concatenate([[True], np.diff(stamps) > 0])
    return stamps[keep], np.array([r[1:] for r in rows], float)[keep]


def _interp_poses(stamps: np.ndarray, poses: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Planar poses at ``t`` (linear in x, y and the unwrapped heading), clamped at the ends."""
    ts = (stamps - stamps[0]).astype(np.float64)
    tq = (np.asarray(t, np.int64) - stamps[0]).astype(np.float64)
    th = np.unwrap(poses[:, 2])
    return np.stack([np.interp(tq, ts, poses[:, 0]), np.interp(tq, ts, poses[:, 1]),
                     wrap_angle_array(np.interp(tq, ts, th))], axis=-1)


def _gap_ok(stamps: np.ndarray, t: np.ndarray, max_gap_ns: int) -> np.ndarray:
    """True where ``t`` lies within the stamps' span with neighbours at most ``max_gap_ns``
    away on both sides."""
    i = np.searchsorted(stamps, t)
    inside = (i > 0) & (i < len(stamps))
    i_c = np.clip(i, 1, max(len(stamps) - 1, 1))
    exact = np.isin(t, stamps)
    gap = stamps[i_c] - stamps[i_c - 1] if len(stamps) > 1 else np.zeros_like(t)
    return exact | (inside & (gap <= max_gap_ns))


# --------------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class CameraResult:
    """One camera's outcome.

    ``T_world_cam``: the estimate (the initial pose when not solved). ``correction_m`` /
    ``correction_deg``: how far it moved from its initial pose (the site file's by default).
    ``sigma_m`` / ``sigma_deg``: 1-sigma of its largest direction from the whole problem's
    information (trajectory, odometry and localization included); ``covariance`` (6, 6):
    rotation (rad, world axes) then position (m). ``own_sigma_m`` / ``own_sigma_deg``: the
    same from its own sightings with the trajectory fixed (what decides a refusal).
    ``sightings``: detections used; ``rms_px``: RMS reprojection error of its kept keypoints.
    ``refused``: the reason (and what drive would fix it), empty when the result may be
    written. ``fixed``: held at its initial pose (``--camera`` names others). ``init``: which
    initial guess the refinement started from (``given`` or ``pnp``).
    """

    camera_id: str
    T_world_cam: np.ndarray
    correction_m: float = 0.0
    correction_deg: float = 0.0
    sigma_m: float = math.nan
    sigma_deg: float = math.nan
    own_sigma_m: float = math.nan
    own_sigma_deg: float = math.nan
    sightings: int = 0
    rms_px: float = math.nan
    covariance: np.ndarray | None = None
    refused: str = ""
    fixed: bool = False
    init: str = ""

    @property
    def ok(self) -> bool:
        return not self.refused and not self.fixed


@dataclasses.dataclass(frozen=True)
class CalibrationResult:
    """All cameras (:class:`CameraResult` by id), the trajectory (node stamps (K,) ns, poses
    (K, 3)), the solver's summary and the input counters."""

    cameras: dict[str, CameraResult]
    node_stamps_ns: np.ndarray
    node_poses: np.ndarray
    iterations: int
    rms_px: float
    counters: dict[str, int]
    seconds: dict[str, float] = dataclasses.field(default_factory=dict)

    @property
    def refused(self) -> dict[str, str]:
        return {c: r.refused for c, r in self.cameras.items() if r.refused}

    @property
    def solved(self) -> dict[str, np.ndarray]:
        """``T_world_cam`` of every camera that was solved and not refused."""
        return {c: r.T_world_cam for c, r in self.cameras.items() if r.ok}


# --------------------------------------------------------------------------------------------
# initialisation of one camera
# --------------------------------------------------------------------------------------------


def _pnp_candidate(cam: CameraModel, pw: np.ndarray, uv: np.ndarray, threshold_px: float,
                   rng: np.random.Generator) -> np.ndarray | None:
    """``T_world_cam`` from a RANSAC PnP of world points against pixels (many frames at once),
    or ``None``."""
    import cv2

    if len(pw) < 12:
        return None
    if len(pw) > 3000:
        sel = rng.choice(len(pw), 3000, replace=False)
        pw, uv = pw[sel], uv[sel]
    dist = cam.dist if cam.dist.size else np.zeros(4)
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            pw.astype(np.float64), uv.astype(np.float64), cam.K, dist, iterationsCount=300,
            reprojectionError=threshold_px, confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error as exc:
        log.debug("PnP failed for %s: %s", cam.camera_id, exc)
        return None
    if not ok or inliers is None or len(inliers) < 12:
        return None
    R_cw, _ = cv2.Rodrigues(rvec)
    T_cw = np.eye(4)
    T_cw[:3, :3] = R_cw
    T_cw[:3, 3] = tvec.ravel()
    return invert_transform(T_cw)


# --------------------------------------------------------------------------------------------
# the calibration
# --------------------------------------------------------------------------------------------


#: where the solution's map frame comes from: the robot's localization, or the site file
FRAMES = ("localization", "site")


def calibrate(data: CalibrationData, config: RobotTargetConfig | None = None, *,
              solve_cameras: Iterable[str] | None = None, frame: str = "localization",
              initial_T_world_cam: Mapping[str, np.ndarray] | None = None,
              progress: Callable[[str], None] | None = None) -> CalibrationResult:
    """Estimate the cameras' ``T_world_cam`` (all, or those in ``solve_cameras``; the others are
    held at their site pose and still constrain the trajectory) jointly with the trajectory.

    ``initial_T_world_cam``: initial poses by camera id (default: the site file's; held
    cameras stay at theirs). ``frame``: ``"localization"`` (the robot's localization places
    the solution in the map frame) or ``"site"`` (the recalibrated cameras keep the mean
    position (x, y) and mean heading of their initial poses; the drive fixes their geometry
    relative to each other, their heights and tilts: for a site whose cameras were surveyed in
    the map frame as a whole, or whose localization is worse than that survey). Raises
    :class:`CalibrationError` when the drive carries no usable odometry, localization or
    sightings; cameras the data does not constrain come back refused, with the reason."""
    import time

    config = config or RobotTargetConfig()
    if frame not in FRAMES:
        raise CalibrationError(f"frame {frame!r}: expected one of {FRAMES}")
    say = progress or (lambda _msg: None)
    t_start = time.perf_counter()
    site = data.site
    cam_ids = sorted(site.cameras)
    wanted = set(cam_ids if solve_cameras is None else solve_cameras)
    unknown = sorted(wanted - set(cam_ids))
    if unknown:
        raise CalibrationError(f"camera(s) {unknown} are not in site {site.name!r}; known: "
                               f"{cam_ids}")
    cams = [site.cameras[c] for c in cam_ids]
    init_T = {c: site.cameras[c].T_world_cam for c in cam_ids}
    for c, T in (initial_T_world_cam or {}).items():
        if c in init_T:
            init_T[c] = np.asarray(T, float)
    counters = dict(data.counters)
    drive = _Drive.build(data, cam_ids, config, counters)
    say(f"{drive.detections} sightings "
        f"({', '.join(f'{c} {drive.per_camera[c]}' for c in cam_ids)}), {drive.n_nodes} "
        f"trajectory nodes, {counters.get('localization', 0)} localization messages")

    # which cameras are solved: the wanted ones with enough sightings; the others that saw
    # the robot are held near their poses (they pin the trajectory); the rest are left out
    R_wc = np.stack([init_T[c][:3, :3] for c in cam_ids])
    c_w = np.stack([init_T[c][:3, 3] for c in cam_ids])
    n_seen = np.array([drive.per_camera[c] for c in cam_ids])
    recal = np.array([c in wanted for c in cam_ids]) & (n_seen >= config.min_sightings)
    held = np.array([c not in wanted for c in cam_ids]) & (n_seen > 0)
    refused = {c: (f"{c} saw the robot in {drive.per_camera[c]} usable frames (minimum "
                   f"{config.min_sightings}): drive the robot through its view for longer, at "
                   f"two distances, and turn in place there")
               for c in cam_ids if c in wanted and drive.per_camera[c] < config.min_sightings}
    obs = drive.obs
    problem = JointProblem(cams, recal | held, obs, drive.node_odom, drive.node_loc,
                       drive.prior_sqrt_info, config)
    problem.keep &= (recal | held)[obs.cam]
    held_inv_sigma = 1.0 / np.array([math.radians(config.held_sigma_deg)] * 3
                                    + [config.held_sigma_m] * 3)
    for ci in np.flatnonzero(held):
        problem.cam_prior[int(ci)] = (R_wc[ci].copy(), c_w[ci].copy(), held_inv_sigma)
    if frame == "site" and recal.any():
        idx = np.flatnonzero(recal)
        problem.gauge_prior = (idx, R_wc[idx].copy(), c_w[idx].copy(),
                               1.0 / np.array([1e-4, 1e-4, math.radians(0.001)]))
    t_setup = time.perf_counter()

    # each recalibrated camera alone against the trajectory from localization
    rng = np.random.default_rng(0)
    init_src: dict[str, str] = {}
    for ci in np.flatnonzero(recal):
        init_src[cam_ids[ci]], med_px = _initialise_camera(problem, cams, int(ci), R_wc, c_w,
                                                           drive.init_nodes, rng)
        say(f"{cam_ids[ci]}: initial pose from the {init_src[cam_ids[ci]]} guess, median "
            f"reprojection {med_px:.1f} px with the trajectory from localization")
    t_init = time.perf_counter()

    # joint adjustment, then gate outliers and re-solve
    nodes = drive.init_nodes.copy()
    R_wc, c_w, nodes, it1 = adjust(problem, R_wc, c_w, nodes,
                                                 config.max_iterations)
    err, z, *_ = problem.reprojection(R_wc, c_w, nodes)
    e = np.sqrt(np.sum(err * err, axis=1))
    used = problem.keep & (z > 0.05)
    rms = float(np.sqrt(np.average(e[used] ** 2, weights=obs.w[used])))
    gate = max(config.gate_px, config.gate_sigmas * rms)
    problem.keep = problem.keep & (e <= gate)
    counters["gated_keypoints"] = int(np.count_nonzero(used & (e > gate)))
    R_wc, c_w, nodes, it2 = adjust(problem, R_wc, c_w, nodes,
                                                 config.max_iterations)
    say(f"joint adjustment: {it1} + {it2} iterations, {counters['gated_keypoints']} keypoints "
        f"gated (> {gate:.1f} px)")
    t_solve = time.perf_counter()

    # noise level from the residuals, then the information matrix at the solution
    err, z, *_ = problem.reprojection(R_wc, c_w, nodes)
    e2 = np.sum(err * err, axis=1)
    used = problem.keep & (z > 0.05)
    n_used = int(np.count_nonzero(used))
    dof = max(2 * n_used - problem.n, 1)
    problem.pixel_sigma = max(math.sqrt(float(np.sum(
        obs.w[used] * problem.robust[used] * e2[used])) / dof), 1e-3)
    rms_all = float(np.sqrt(np.average(e2[used], weights=obs.w[used]))) if n_used else math.nan
    H, _, own, _ = problem.normal_equations(R_wc, c_w, nodes)
    try:
        cov_all = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov_all = np.full_like(H, np.nan)
    t_cov = time.perf_counter()

    results: dict[str, CameraResult] = {}
    for ci, c in enumerate(cam_ids):
        sel = used & (obs.cam == ci)
        rms_c = float(np.sqrt(np.average(e2[sel], weights=obs.w[sel]))) if sel.any() \
            else math.nan
        common = {"sightings": drive.per_camera[c], "rms_px": rms_c}
        if c not in wanted:
            results[c] = CameraResult(c, init_T[c], fixed=True, **common)
        elif c in refused:
            results[c] = CameraResult(c, init_T[c], refused=refused[c], **common)
        else:
            col = problem.cam_col[ci]
            results[c] = _camera_result(c, ci, cams[ci], init_T[c], R_wc, c_w, nodes, obs,
                                        cov_all[col:col + 6, col:col + 6], own[ci], config,
                                        init=init_src.get(c, ""), **common)
    t_end = time.perf_counter()
    seconds = {"setup": t_setup - t_start, "init": t_init - t_setup, "solve": t_solve - t_init,
               "covariance": t_cov - t_solve, "total": t_end - t_start}
    counters["keypoints_used"] = n_used
    return CalibrationResult(results, drive.node_stamps_ns, nodes, it1 + it2, rms_all, counters,
                             seconds)


@dataclasses.dataclass
class _Drive:
    """The drive prepared for the problem: trajectory nodes (stamps (K,) ns, odometry (K, 3),
    localization (K, 3) with its square-root information (K, 3, 3), initial poses (K, 3)),
    the keypoint observations and the usable detections per camera."""

    node_stamps_ns: np.ndarray
    node_odom: np.ndarray
    node_loc: np.ndarray
    prior_sqrt_info: np.ndarray
    init_nodes: np.ndarray
    obs: Observations
    per_camera: dict[str, int]
    detections: int

    @property
    def n_nodes(self) -> int:
        return len(self.node_stamps_ns)

    @classmethod
    def build(cls, data: CalibrationData, cam_ids: list[str], config: RobotTargetConfig,
              counters: dict[str, int]) -> _Drive:
        odo_t, odo_q = data.odometry_arrays()
        if len(odo_t) < 2:
            raise CalibrationError(f"the drive has {len(odo_t)} odometry message(s) of robot "
                                   f"{data.robot_id!r}: odometry is needed between the "
                                   f"sightings")
        loc_t, loc_q, loc_cov = data.localization_arrays()
        if len(loc_t) == 0:
            raise CalibrationError(f"the drive has no localization of robot {data.robot_id!r} "
                                   f"in frame {data.site.world_frame!r}: without it the map "
                                   f"frame is unknown")
        max_gap_ns = int(config.max_odometry_gap_s * 1e9)
        # the normal equations are dense: a long drive gets sparser nodes, not a huge matrix
        span_ns = int(odo_t[-1] - odo_t[0])
        spacing_ns = max(int(config.node_spacing_s * 1e9),
                         -(-span_ns // max(config.max_nodes - 1, 1)))
        if spacing_ns > int(config.node_spacing_s * 1e9):
            counters["node_spacing_ms"] = spacing_ns // 1_000_000
            log.info("drive of %.0f s: trajectory nodes every %.2f s (max_nodes %d)",
                     span_ns * 1e-9, spacing_ns * 1e-9, config.max_nodes)
        n_nodes = span_ns // spacing_ns + 1
        node_t = odo_t[0] + spacing_ns * np.arange(n_nodes, dtype=np.int64)
        node_odom = _interp_poses(odo_t, odo_q, node_t)

        det_cam, det_t, det_uv, det_w, per_camera = _usable_sightings(data, cam_ids, config,
                                                                      counters)
        ok_t = _gap_ok(odo_t, det_t, max_gap_ns) if len(det_t) else np.zeros(0, bool)
        if len(det_t) and not ok_t.all():
            counters["outside_odometry"] = int(np.count_nonzero(~ok_t))
            for ci in det_cam[~ok_t]:
                per_camera[cam_ids[ci]] -= 1
        if not ok_t.any():
            raise CalibrationError("no usable sightings: no camera saw the robot while "
                                   f"odometry was recorded (counters: {counters})")
        det_cam, det_t, det_uv, det_w = det_cam[ok_t], det_t[ok_t], det_uv[ok_t], det_w[ok_t]
        # each detection hangs on its nearest node, offset by the odometry in between
        det_node = np.clip(np.round((det_t - node_t[0]) / spacing_ns).astype(int), 0,
                           n_nodes - 1)
        odo_at_det = _interp_poses(odo_t, odo_q, det_t)
        a = node_odom[det_node]
        ca, sa = np.cos(a[:, 2]), np.sin(a[:, 2])
        dxw, dyw = odo_at_det[:, 0] - a[:, 0], odo_at_det[:, 1] - a[:, 1]
        det_delta = np.stack([ca * dxw + sa * dyw, -sa * dxw + ca * dyw,
                              wrap_angle_array(odo_at_det[:, 2] - a[:, 2])], axis=-1)
        D, M = len(det_t), data.keypoints_base_m.shape[0]
        obs = Observations(
            cam=np.repeat(det_cam, M), node=np.repeat(det_node, M),
            delta=np.repeat(det_delta, M, axis=0), kp=np.tile(data.keypoints_base_m, (D, 1)),
            uv=det_uv.reshape(-1, 2), w=det_w.reshape(-1), det=np.repeat(np.arange(D), M))

        node_loc, sqrt_info, loc_ok = _localization_prior(
            loc_t, loc_q, loc_cov, node_t, spacing_ns * 1e-9, max(max_gap_ns, int(2e9)), config)
        counters["nodes"] = n_nodes
        counters["nodes_with_localization"] = int(np.count_nonzero(loc_ok))
        if not loc_ok.any():
            raise CalibrationError("the localization does not overlap the odometry in time "
                                   "(check the robot's clocks)")
        # initial nodes: localization where there is one; elsewhere odometry carried from the
        # nearest node that has one
        ok_idx = np.flatnonzero(loc_ok)
        nearest = ok_idx[np.clip(np.searchsorted(ok_idx, np.arange(n_nodes)), 0,
                                 len(ok_idx) - 1)]
        init_nodes = _carry(node_loc, node_odom, nearest)
        return cls(node_t, node_odom, node_loc, sqrt_info, init_nodes, obs, per_camera, D)


def _usable_sightings(data: CalibrationData, cam_ids: list[str], config: RobotTargetConfig,
                      counters: dict[str, int]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, int]]:
    """Detections with enough keypoints above the score, at most ``max_frame_rate_hz`` per
    camera: camera index (D,), stamps (D,), pixels (D, M, 2), weights (D, M), and the count
    per camera."""
    min_period_ns = int(1e9 / config.max_frame_rate_hz) if config.max_frame_rate_hz > 0 else 0
    M = data.keypoints_base_m.shape[0]
    det_cam: list[int] = []
    det_t: list[int] = []
    det_uv: list[np.ndarray] = []
    det_w: list[np.ndarray] = []
    per_camera: dict[str, int] = {}
    for ci, c in enumerate(cam_ids):
        last: int | None = None
        used = 0
        for t, uv, w, scores in sorted(data.sightings.get(c, []), key=lambda r: r[0]):
            wk = np.where((w > 0) & (scores >= config.min_keypoint_score), w, 0.0)
            if np.count_nonzero(wk) < config.min_keypoints:
                counters["too_few_keypoints"] = counters.get("too_few_keypoints", 0) + 1
                continue
            if last is not None and t - last < min_period_ns:
                counters["subsampled"] = counters.get("subsampled", 0) + 1
                continue
            det_cam.append(ci)
            det_t.append(t)
            det_uv.append(uv)
            det_w.append(wk)
            last = t
            used += 1
        per_camera[c] = used
    return (np.array(det_cam, int), np.array(det_t, np.int64),
            np.array(det_uv, float).reshape(-1, M, 2), np.array(det_w, float).reshape(-1, M),
            per_camera)


def _localization_prior(loc_t: np.ndarray, loc_q: np.ndarray, loc_cov: np.ndarray,
                        node_t: np.ndarray, spacing_s: float, max_gap_ns: int,
                        config: RobotTargetConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The localization at every node (K, 3), the prior's square-root information (K, 3, 3;
    zero where the localization has a gap) and where it is valid (K,)."""
    loc_ok = _gap_ok(loc_t, node_t, max_gap_ns)
    node_loc = _interp_poses(loc_t, loc_q, node_t)
    idx_near = np.clip(np.searchsorted(loc_t, node_t), 0, len(loc_t) - 1)
    default = np.diag([config.localization_default_sigma_m ** 2] * 2
                      + [math.radians(config.localization_default_sigma_deg) ** 2])
    cov = np.where(np.isfinite(loc_cov[idx_near]).all(axis=(1, 2))[:, None, None],
                   np.nan_to_num(loc_cov[idx_near]), default[None])
    floor = np.diag([config.localization_min_sigma_m ** 2] * 2
                    + [math.radians(config.localization_min_sigma_deg) ** 2])
    # errors correlated over localization_correlation_s count about once per that time
    inflation = max(1.0, config.localization_correlation_s / spacing_s)
    cov = (cov * config.localization_sigma_scale ** 2 + floor[None]) * inflation
    sqrt_info = np.linalg.cholesky(np.linalg.inv(cov)).transpose(0, 2, 1)
    sqrt_info[~loc_ok] = 0.0
    return node_loc, sqrt_info, loc_ok


def _initialise_camera(problem: JointProblem, cams: list[CameraModel], ci: int, R_wc: np.ndarray,
                       c_w: np.ndarray, nodes: np.ndarray, rng: np.random.Generator
                       ) -> tuple[str, float]:
    """Camera ``ci``'s start for the joint adjustment (written into ``R_wc``/``c_w``): the
    given pose and a RANSAC PnP against the trajectory ``nodes``, each refined alone on a
    subset of its sightings; the one with the smaller median reprojection error wins.
    Returns (which, its median error px)."""
    config, obs = problem.config, problem.obs
    dets = np.unique(obs.det[obs.cam == ci])
    if len(dets) > config.init_max_sightings:
        dets = np.sort(rng.choice(dets, config.init_max_sightings, replace=False))
    sub = subset_observations(obs, np.isin(obs.det, dets))
    sel = sub.w > 0
    pw_sub, _ = robot_points(nodes, sub)
    candidates = {"given": (R_wc[ci].copy(), c_w[ci].copy())}
    T_pnp = _pnp_candidate(cams[ci], pw_sub[sel], sub.uv[sel], config.pnp_threshold_px, rng)
    if T_pnp is not None:
        candidates["pnp"] = (T_pnp[:3, :3], T_pnp[:3, 3])
    single = JointProblem(cams, np.arange(len(cams)) == ci, sub, problem.node_odom_input,
                      problem.node_prior, problem.prior_sqrt_info, config)
    best, best_px = "given", math.inf
    R_best, c_best = R_wc[ci].copy(), c_w[ci].copy()
    for name, (R, c) in candidates.items():
        Rt, ct = R_wc.copy(), c_w.copy()
        Rt[ci], ct[ci] = R, c
        Rt, ct, _, _ = adjust(single, Rt, ct, nodes, 15, fix_nodes=True)
        err, z, *_ = single.reprojection(Rt, ct, nodes)
        e = np.sqrt(np.sum(err[sel] ** 2, axis=1))
        med = float(np.median(np.where(z[sel] > 0, e, 1e6)))
        if med < best_px:
            best, best_px, R_best, c_best = name, med, Rt[ci], ct[ci]
    R_wc[ci], c_w[ci] = R_best, c_best
    return best, best_px


def _camera_result(c: str, ci: int, cam: CameraModel, T_init: np.ndarray, R_wc: np.ndarray,
                   c_w: np.ndarray, nodes: np.ndarray, obs: Observations, P: np.ndarray,
                   own_info: np.ndarray, config: RobotTargetConfig, *, init: str,
                   sightings: int, rms_px: float) -> CameraResult:
    """A solved camera's result: its uncertainty, and the refusal when its own sightings do
    not constrain it."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_wc[ci], c_w[ci]
    sig_rot, sig_pos = _max_sigma(P)
    try:
        own_rot, own_pos = _max_sigma(np.linalg.inv(own_info))
    except np.linalg.LinAlgError:
        own_rot, own_pos = math.inf, math.inf
    own_deg = math.degrees(own_rot)
    extent = _extent_m(nodes[obs.node[obs.cam == ci]][:, :2])
    reason = ""
    if not (own_pos <= config.max_sigma_m and own_deg <= config.max_sigma_deg
            and extent >= config.min_extent_m):
        reason = _degenerate_reason(c, cam, c_w[ci], nodes, obs, ci, sightings, own_pos,
                                    own_deg, config)
    dt, dr = pose_error(T_init, T)
    return CameraResult(c, T if not reason else T_init, dt, dr, sig_pos, math.degrees(sig_rot),
                        own_pos, own_deg, sightings, rms_px, P, reason, init=init)


def _carry(node_loc: np.ndarray, node_odom: np.ndarray, nearest: np.ndarray) -> np.ndarray:
    """Poses of every node: the localization of its ``nearest`` node carried by odometry."""
    src_loc, src_odo = node_loc[nearest], node_odom[nearest]
    dth = src_loc[:, 2] - src_odo[:, 2]
    c, s = np.cos(dth), np.sin(dth)
    dx, dy = node_odom[:, 0] - src_odo[:, 0], node_odom[:, 1] - src_odo[:, 1]
    return np.stack([src_loc[:, 0] + c * dx - s * dy, src_loc[:, 1] + s * dx + c * dy,
                     wrap_angle_array(node_odom[:, 2] + dth)], axis=-1)


def _extent_m(xy: np.ndarray) -> float:
    """Spread of planar positions (m): twice the largest distance from their centroid."""
    if len(xy) == 0:
        return 0.0
    return float(np.max(np.linalg.norm(xy - xy.mean(axis=0), axis=1)) * 2)


def _max_sigma(P: np.ndarray) -> tuple[float, float]:
    """(rotation rad, position m) 1-sigma along the weakest direction of a (6, 6) covariance."""
    if not np.all(np.isfinite(P)):
        return math.inf, math.inf
    ev_r = np.linalg.eigvalsh(0.5 * (P[:3, :3] + P[:3, :3].T))
    ev_t = np.linalg.eigvalsh(0.5 * (P[3:, 3:] + P[3:, 3:].T))
    return float(math.sqrt(max(ev_r[-1], 0.0))), float(math.sqrt(max(ev_t[-1], 0.0)))


def _degenerate_reason(c: str, cam: CameraModel, centre: np.ndarray,
                       nodes: np.ndarray, obs: Observations, ci: int, n_sight: int,
                       own_pos: float, own_deg: float, config: RobotTargetConfig) -> str:
    """Why camera ``c``'s sightings do not constrain it, and the drive that would."""
    sel = obs.cam == ci
    det_nodes = nodes[obs.node[sel]]
    xy = det_nodes[:, :2]
    extent = _extent_m(xy)
    heading_range = 0.0
    if len(xy):
        th = np.sort(np.mod(det_nodes[:, 2], 2 * math.pi))
        gaps = np.diff(np.concatenate([th, [th[0] + 2 * math.pi]]))
        heading_range = math.degrees(2 * math.pi - float(gaps.max()))
    rng = np.linalg.norm(np.c_[xy, np.zeros(len(xy))] - centre, axis=1) if len(xy) \
        else np.zeros(1)
    return (f"{c} saw the robot in {n_sight} frames, all within {extent:.1f} m "
            f"({rng.min():.1f}-{rng.max():.1f} m from the camera, headings over "
            f"{heading_range:.0f} deg; its own sightings constrain it to {own_pos * 100:.1f} cm / "
            f"{own_deg:.2f} deg, limits {config.max_sigma_m * 100:.1f} cm / "
            f"{config.max_sigma_deg:.2f} deg and {config.min_extent_m:.1f} m of robot "
            f"positions): drive through its view at two distances and turn in place there")
