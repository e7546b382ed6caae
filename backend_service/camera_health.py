"""Is a camera still where its calibration says? A bumped camera noticed from its residuals.

Every camera's keypoints are compared with the robot pose the *other* cameras agree on. A camera
whose true pose moved by a 6-DoF offset delta (rotation about its optical centre, world axes,
rad; position, world axes, m: the parametrization of
:func:`~backend_service.covariance.project_with_extrinsic_jacobian`) shows residuals
e ~= J dq + G delta, with the same delta in every frame: a persistent bias the pose dq cannot
absorb. Per judged frame-set (transport-free, pure numpy):

1. residuals e, the robot-pose Jacobian J and the extrinsic Jacobian G (closed form) of every
   camera at the joint solution of the solve; a keypoint far from its view's common shift is
   a wrong keypoint, not an offset, and is left out (a view left with too few is not judged:
   :meth:`CameraHealthMonitor._consistent`);
2. the keypoint noise model ``Sigma``: independent pixel noise s^2 / w (w: the solver's keypoint
   weights, s^2 a running estimate of the residual variance floored at the solver's
   ``covariance_floor_px``; keypoints far from the current offset estimate down-weighted,
   Huber) plus the per-detection shift and scale errors of the solver's error model
   (:class:`~backend_service.pose_solver.SolverConfig`), inverted with Woodbury;
3. each camera's part weighed by how new its view is: the robot's drive and turn since the
   camera's previous judged view against ``independent_motion_m`` / ``independent_turn_deg``
   (at most 1). A CNN's keypoint error belongs to the view (the same view gives nearly the
   same error), so frames of a standing or creeping robot are one piece of evidence, not many;
   counted as independent, the shipped models' view-dependent error named unmoved cameras
   moved in 9 of 12 closed-loop runs of the paper lab (0 of 12 weighed by motion);
4. the robot pose marginalized out (its Schur complement): the frame-set's Gauss-Newton normal
   equations of the offsets of all its cameras together, added into one joint system of every
   camera's offset with exponential forgetting (``forgetting_s`` of judged time).

The decision, once per second of judged time (less often with many cameras), solves the joint
system with every camera held to its calibration (a prior of ``tolerance_m`` / ``tolerance_deg``
per axis: ``P_tol``) and asks per camera what the data alone say of its offset, its own prior
left out: ``d`` with covariance ``P``. That is the residual bias against the pose the others
agree on, each of them allowed its calibration error; and because all offsets are estimated
together, a bump of one camera is not blamed on the cameras whose poses it pulled. The test:
``chi2 = d^T (P + P_tol)^-1 d`` (what an unmoved camera may show: its calibration error plus the
estimate's uncertainty). A camera is judged moved after ``min_evidence_s`` of judged frame-sets
(each counted by the novelty of its view) once chi2 has stayed above ``alarm_chi2`` for
``confirm_s``; of several at once, the most significant only. It stays moved until it is
recalibrated (its calibrated pose in the site changes), :meth:`CameraHealthMonitor.reset` or a
restart; with ``action: report`` (kept in the solve) it also clears when chi2 falls below
``clear_chi2`` (hysteresis). A frame-set is judged only with at least ``min_other_cameras`` + 1
cameras in it: with one camera there is nothing to compare it with, and two cameras that
disagree say which of them moved only through the frame-sets each shares with others."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Final

import numpy as np

from backend_service.covariance import project_with_extrinsic_jacobian
from core.camera import CameraModel
from core.site import Site

log = logging.getLogger(__name__)

__all__ = ["CameraHealthConfig", "CameraHealthMonitor", "CameraState", "MovedCamera"]

#: what the pipeline does with a moved camera
ACTIONS: Final = ("exclude", "report")
#: weak prior on the offset (rad, m per axis): keeps the normal equations invertible when the
#: views so far cannot tell a rotation from a translation (the robot seen from one place)
PRIOR_ROTATION_RAD: Final = math.radians(10.0)
PRIOR_TRANSLATION_M: Final = 0.5
#: Huber threshold of a keypoint's residual against the current offset estimate (sigmas)
HUBER_K: Final = 4.0
#: weight of a frame-set in the running estimate of the residual variance
NOISE_EMA: Final = 0.02
#: the judged time one frame-set adds at most (s): a gap in visibility is not evidence
MAX_STEP_S: Final = 0.5
#: the others' pose information must be this well conditioned to judge a camera
MAX_CONDITION: Final = 1e10
#: keypoints further than this from where the joint pose puts them are not used (px)
MAX_RESIDUAL_PX: Final = 80.0
#: cameras of one frame-set judged together at most (the least judged first)
MAX_JUDGED_VIEWS: Final = 8
#: a camera is named only when its test statistic is this many times every other camera's
DOMINANCE: Final = 2.0
#: judged time between two decisions (s): the joint equations are solved this often
DECISION_PERIOD_S: Final = 1.0
#: a frame-set whose views all repeat the previous ones by more than this is not judged
MIN_NOVELTY: Final = 0.02
#: a keypoint further than this many noise sigmas (and at least INLIER_MIN_PX) from its view's
#: common shift is a wrong keypoint, not evidence of an offset (a small offset moves a view's
#: keypoints together: a rotation shifts them, a translation adds a little scale and parallax)
INLIER_SIGMAS: Final = 5.0
INLIER_MIN_PX: Final = 6.0


@dataclasses.dataclass(frozen=True)
class CameraHealthConfig:
    """Watching every camera for a persistent bias of its keypoints against the pose the
    other cameras agree on (a bumped camera; :mod:`backend_service.camera_health`).

    ``enabled``: watch at all. ``action``: ``exclude`` (a moved camera is left out of the solve
    until it is recalibrated) or ``report`` (only named in the status). ``min_other_cameras``:
    a camera is judged only in frame-sets where at least this many other cameras saw the robot.
    ``min_keypoints``: and where it has this many usable keypoints. ``max_rate_hz``: frame-sets
    judged per robot and second at most (the CPU cost; evidence hardly grows faster).
    ``forgetting_s``: evidence older than this (judged time) weighs 1/e. ``tolerance_m`` /
    ``tolerance_deg``: per-axis offset an unmoved camera may show (its calibration error and
    what the other cameras' calibration errors make it look like). ``alarm_chi2``: the offset
    is judged moved above this (6 degrees of freedom, against its covariance plus the
    tolerance) for ``confirm_s`` of judged time after at least ``min_evidence_s``;
    ``clear_chi2``: below this a reported (not excluded) camera is healthy again.
    ``independent_motion_m`` / ``independent_turn_deg``: how far the robot drives or turns
    between two views of one camera before their keypoint errors count as independent: a CNN's
    keypoint error depends on the view, so frames of a standing or creeping robot repeat the
    same error, and counted as independent evidence they name an unmoved camera moved. A
    camera's frame-set counts as the fraction of this it moved since the camera's previous one
    (at most 1; a standing robot adds nothing).
    """

    enabled: bool = True
    action: str = "exclude"
    min_other_cameras: int = 1
    min_keypoints: int = 6
    max_rate_hz: float = 2.0
    forgetting_s: float = 30.0
    tolerance_m: float = 0.02
    tolerance_deg: float = 0.15
    alarm_chi2: float = 16.0
    clear_chi2: float = 8.0
    min_evidence_s: float = 5.0
    confirm_s: float = 3.0
    independent_motion_m: float = 0.25
    independent_turn_deg: float = 10.0

    def __post_init__(self) -> None:
        if self.action not in ACTIONS:
            raise ValueError(f"CameraHealthConfig.action {self.action!r} not in {ACTIONS}")
        for name in ("max_rate_hz", "forgetting_s", "tolerance_m", "tolerance_deg",
                     "alarm_chi2", "independent_motion_m", "independent_turn_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"CameraHealthConfig.{name} must be > 0, got {value!r}")
        if not (math.isfinite(self.clear_chi2) and 0 <= self.clear_chi2 <= self.alarm_chi2):
            raise ValueError(f"CameraHealthConfig.clear_chi2 must be in [0, alarm_chi2], got "
                             f"{self.clear_chi2!r}")
        for name in ("min_evidence_s", "confirm_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"CameraHealthConfig.{name} must be >= 0, got {value!r}")
        if self.min_other_cameras < 1:
            raise ValueError("CameraHealthConfig.min_other_cameras must be >= 1")
        if self.min_keypoints < 3:
            raise ValueError("CameraHealthConfig.min_keypoints must be >= 3")

    @classmethod
    def from_site(cls, site: Site) -> CameraHealthConfig:
        """The site file's ``camera_health`` section; errors name the file and key."""
        return site.section_reader().section("camera_health", site.section("camera_health"),
                                             cls, int_lo=1)


@dataclasses.dataclass(frozen=True)
class NoiseModel:
    """The keypoint noise the monitor weighs residuals with (the solver's, see
    :class:`~backend_service.pose_solver.SolverConfig`): ``floor_px`` the least independent
    pixel noise, ``shift_px`` / ``scale`` the per-detection common shift and relative scale."""

    floor_px: float = 1.0
    shift_px: float = 0.45
    scale: float = 0.017


@dataclasses.dataclass(frozen=True)
class MovedCamera:
    """A camera judged moved: the offset estimate when it was (``translation_m``: norm of the
    position offset; ``rotation_deg``: rotation angle), the ``chi2`` and the ``stamp_ns`` of
    the frame-set that decided it."""

    camera_id: str
    translation_m: float
    rotation_deg: float
    chi2: float
    stamp_ns: int

    def text(self, excluded: bool) -> str:
        out = (f"{self.camera_id} moved ~{self.translation_m * 100:.0f} cm / "
               f"{self.rotation_deg:.1f} deg since calibration")
        if excluded:
            out += " (left out of the solve until it is recalibrated)"
        return out


@dataclasses.dataclass(frozen=True)
class CameraState:
    """A snapshot of one camera's evidence: ``offset`` (6,) the estimate (rotation rad, position
    m; world axes), ``covariance`` (6, 6), ``chi2``, ``evidence_s`` (judged time since the last
    reset), ``judged`` frame-sets, ``moved`` (or ``None``)."""

    camera_id: str
    offset: np.ndarray
    covariance: np.ndarray
    chi2: float
    evidence_s: float
    judged: int
    moved: MovedCamera | None

    @property
    def translation_m(self) -> float:
        return float(np.linalg.norm(self.offset[3:]))

    @property
    def rotation_deg(self) -> float:
        return math.degrees(float(np.linalg.norm(self.offset[:3])))


def ids_of(cameras: Sequence[CameraModel]) -> list[str]:
    return [c.camera_id for c in cameras]


class _Camera:
    """One camera's place in the joint normal equations and its test state."""

    def __init__(self, index: int, T_cam_world: np.ndarray) -> None:
        self.index = index
        self.T_cam_world = T_cam_world  # the calibration it is judged against
        self.offset = np.zeros(6)  # the data's estimate (its tolerance prior left out)
        self.covariance = np.diag([PRIOR_ROTATION_RAD**2] * 3 + [PRIOR_TRANSLATION_M**2] * 3)
        self.chi2 = 0.0
        self.evidence_s = 0.0
        self.over_s = 0.0
        self.judged = 0
        self.moved: MovedCamera | None = None
        #: the robot's planar pose (x m, y m, yaw rad) at this camera's last judged view
        self.view: tuple[float, float, float] | None = None

    def novelty(self, view: tuple[float, float, float], motion_m: float,
                turn_rad: float) -> float:
        """How much of an independent view ``view`` is after the previous one: the robot's
        drive and turn since then against ``motion_m`` / ``turn_rad``, at most 1 (the first
        view: 1)."""
        if self.view is None:
            return 1.0
        dxy = math.hypot(view[0] - self.view[0], view[1] - self.view[1])
        dyaw = abs(math.remainder(view[2] - self.view[2], math.tau))
        return min(1.0, max(dxy / motion_m, dyaw / turn_rad))


class CameraHealthMonitor:
    """Per camera, the bias of its keypoint residuals against the pose the other cameras agree
    on, and the sequential test that names a moved camera (module docstring). Transport-free;
    time comes from frame-set stamps. Not thread-safe (the pipeline's worker drives it)."""

    def __init__(self, config: CameraHealthConfig | None = None,
                 noise: NoiseModel | None = None) -> None:
        self.config = config or CameraHealthConfig()
        self.noise = noise or NoiseModel()
        self.counters: Counter[str] = Counter()
        self._cams: dict[str, _Camera] = {}
        self._L = np.zeros((0, 0))  # joint information of every camera's offset (6 per camera)
        self._eta = np.zeros(0)
        self._last_judged: dict[str, int] = {}  # robot id -> stamp of its last judged frame-set
        self._last_ns: int | None = None  # stamp of the last judged frame-set (any robot)
        self._since_decision_s = 0.0
        self._touched: set[str] = set()  # cameras judged since the last decision
        self._s2 = self.noise.floor_px ** 2
        c = self.config
        self._tol_info = np.diag([math.radians(c.tolerance_deg) ** -2] * 3
                                 + [c.tolerance_m ** -2] * 3)
        self._P_tol = np.linalg.inv(self._tol_info)
        self._A_prior = np.diag([PRIOR_ROTATION_RAD ** -2] * 3 + [PRIOR_TRANSLATION_M ** -2] * 3)

    # -- what the pipeline asks ----------------------------------------------------------------

    @property
    def excluded(self) -> frozenset[str]:
        """Cameras left out of the solve (moved, ``action: exclude``)."""
        if self.config.action != "exclude":
            return frozenset()
        return frozenset(cid for cid, cam in self._cams.items() if cam.moved is not None)

    @property
    def moved(self) -> dict[str, MovedCamera]:
        return {cid: cam.moved for cid, cam in sorted(self._cams.items())
                if cam.moved is not None}

    def problems(self) -> list[str]:
        """One status line per moved camera (``cam3 moved ~4 cm / 1.1 deg since calibration``)
        with its offset as estimated now (a camera left out of the solve is still compared
        with the pose the others give, so the estimate keeps improving)."""
        excluding = self.config.action == "exclude"
        out = []
        for cid, moved in self.moved.items():
            st = self._cams[cid]
            if st.evidence_s < self.config.min_evidence_s:  # just named: the naming's estimate
                out.append(moved.text(excluding))
                continue
            now = dataclasses.replace(moved, translation_m=float(np.linalg.norm(st.offset[3:])),
                                      rotation_deg=math.degrees(float(np.linalg.norm(
                                          st.offset[:3]))))
            out.append(now.text(excluding))
        return out

    def state(self, camera_id: str) -> CameraState | None:
        cam = self._cams.get(camera_id)
        if cam is None:
            return None
        return CameraState(camera_id, cam.offset.copy(), cam.covariance.copy(), cam.chi2,
                           cam.evidence_s, cam.judged, cam.moved)

    def reset(self, camera_id: str | None = None) -> None:
        """Forget one camera's evidence (and its verdict), or every camera's."""
        ids = list(self._cams) if camera_id is None else [camera_id]
        for cid in ids:
            if cid in self._cams:
                self._forget(cid)
                self.counters["reset"] += 1
                log.info("camera health: %s reset", cid)

    def check_calibration(self, cameras: Mapping[str, CameraModel]) -> None:
        """A camera whose calibrated pose differs from the one its evidence was gathered
        against was recalibrated: its state starts afresh (and a moved camera is back)."""
        for cid in list(self._cams):
            cam = cameras.get(cid)
            state = self._cams[cid]
            if cam is None or cam.T_cam_world is state.T_cam_world:
                continue
            if not np.array_equal(cam.T_cam_world, state.T_cam_world):
                moved = state.moved is not None
                self._forget(cid)
                self.counters["recalibrated"] += 1
                if moved:
                    log.warning("camera health: %s was recalibrated; back in the solve", cid)
            else:
                state.T_cam_world = cam.T_cam_world

    def _forget(self, cid: str) -> None:
        """Drop a camera from the joint equations, marginalizing its offset out (what the
        others learnt jointly with it stays consistent)."""
        cam = self._cams.pop(cid)
        n = self._L.shape[0] // 6
        keep = np.array([i for i in range(n) if i != cam.index], dtype=int)
        k6 = (keep[:, None] * 6 + np.arange(6)).reshape(-1)
        c6 = cam.index * 6 + np.arange(6)
        L_oo = self._L[np.ix_(k6, k6)]
        L_oc = self._L[np.ix_(k6, c6)]
        L_cc = self._L[np.ix_(c6, c6)] + self._tol_info
        gain = np.linalg.solve(L_cc, L_oc.T).T
        self._L = L_oo - gain @ L_oc.T
        self._eta = self._eta[k6] - gain @ self._eta[c6]
        for other in self._cams.values():
            other.index = int(np.flatnonzero(keep == other.index)[0])

    def _camera(self, camera: CameraModel) -> _Camera:
        cam = self._cams.get(camera.camera_id)
        if cam is None:
            n = self._L.shape[0]
            L = np.zeros((n + 6, n + 6))
            L[:n, :n] = self._L
            self._L = L
            self._eta = np.concatenate([self._eta, np.zeros(6)])
            cam = self._cams[camera.camera_id] = _Camera(n // 6, camera.T_cam_world)
        return cam

    # -- evidence ------------------------------------------------------------------------------

    def select(self, camera_ids: Sequence[str]) -> list[str]:
        """The cameras of a frame-set to judge: all of them, or at most
        :data:`MAX_JUDGED_VIEWS`, those judged least so far first (on a site where dozens of
        cameras see the robot, each frame-set's cost stays that of a few; every camera gets
        its turn)."""
        if len(camera_ids) <= MAX_JUDGED_VIEWS:
            return list(camera_ids)

        def judged(cid: str) -> int:
            st = self._cams.get(cid)
            return 0 if st is None else st.judged

        return sorted(camera_ids, key=lambda c: (judged(c), c))[:MAX_JUDGED_VIEWS]

    def due(self, robot_id: str, stamp_ns: int) -> bool:
        """Whether a frame-set of ``robot_id`` at ``stamp_ns`` is judged (``max_rate_hz``)."""
        if not self.config.enabled:
            return False
        last = self._last_judged.get(robot_id)
        return last is None or stamp_ns - last >= 1e9 / self.config.max_rate_hz \
            or stamp_ns < last

    def observe(self, robot_id: str, stamp_ns: int, cameras: Sequence[CameraModel],
                keypoints_base_m: np.ndarray, T_world_robot: np.ndarray,
                keypoints_px: np.ndarray, weights: np.ndarray) -> list[MovedCamera]:
        """One solved frame-set: ``cameras`` (C) the views the solve used (and those of
        cameras it left out as moved, which are still compared), ``keypoints_px``
        (C, M, 2) and ``weights`` (C, M) as the solver weighed them (0: not used),
        ``T_world_robot`` (4, 4) the joint solution, ``keypoints_base_m`` (M, 3). Returns the
        cameras judged moved by this frame-set. Bad input is counted (``skipped.<why>``),
        never raised, and never reaches the accumulated evidence."""
        if not self.config.enabled:
            return []
        try:
            out = self._observe(robot_id, int(stamp_ns), list(cameras), keypoints_base_m,
                                T_world_robot, keypoints_px, weights)
        except (ValueError, TypeError, IndexError, np.linalg.LinAlgError) as exc:
            self.counters["skipped"] += 1
            self.counters["skipped.error"] += 1
            log.debug("camera health: frame-set skipped: %s", exc)
            return []
        return out

    def _skip(self, why: str) -> list[MovedCamera]:
        self.counters["skipped"] += 1
        self.counters[f"skipped.{why}"] += 1
        return []

    def _observe(self, robot_id: str, stamp_ns: int, cameras: list[CameraModel],
                 keypoints_base_m: np.ndarray, T_world_robot: np.ndarray,
                 keypoints_px: np.ndarray, weights: np.ndarray) -> list[MovedCamera]:
        cfg = self.config
        healthy = [c.camera_id for c in cameras
                   if c.camera_id not in self._cams or self._cams[c.camera_id].moved is None]
        if len(healthy) < cfg.min_other_cameras + (len(healthy) == len(cameras)):
            return []
        C = len(cameras)
        kp = np.asarray(keypoints_base_m, dtype=np.float64)
        T = np.asarray(T_world_robot, dtype=np.float64)
        uv_obs = np.asarray(keypoints_px, dtype=np.float64)
        w = np.asarray(weights, dtype=np.float64)
        M = kp.shape[0]
        if kp.shape != (M, 3) or T.shape != (4, 4) or uv_obs.shape != (C, M, 2) \
                or w.shape != (C, M):
            return self._skip("shape")
        if not (np.all(np.isfinite(T)) and np.all(np.isfinite(kp))):
            return self._skip("non_finite_pose")
        self._last_judged[robot_id] = stamp_ns
        P = kp @ T[:3, :3].T + T[:3, 3]  # (M, 3) keypoints at the joint solution, world
        uv_hat, G = project_with_extrinsic_jacobian(cameras, P)  # (C, M, 2), (C, M, 2, 6)
        with np.errstate(invalid="ignore", over="ignore"):
            e = uv_obs - uv_hat
            # a keypoint this far from where the pose puts it is not evidence of a small
            # offset but a wrong detection (or garbage); weights above 1 are not the solver's
            valid = (np.isfinite(e).all(axis=2) & (np.abs(e) <= MAX_RESIDUAL_PX).all(axis=2)
                     & np.isfinite(w) & (w > 0) & np.isfinite(G).all(axis=(2, 3)))
        valid = self._consistent(e, valid)
        w = np.where(valid, np.minimum(w, 1.0), 0.0)
        e = np.where(valid[..., None], e, 0.0)
        G = np.where(valid[..., None, None], G, 0.0)
        # d(u, v)/d(robot x, y, theta): the keypoint moves with the robot (planar pose)
        d_uv_dp = -G[..., 3:]  # d(u, v)/d(world point), (C, M, 2, 3)
        dP = np.zeros((M, 3, 3))
        dP[:, 0, 0] = 1.0
        dP[:, 1, 1] = 1.0
        dP[:, 0, 2] = -(P[:, 1] - T[1, 3])
        dP[:, 1, 2] = P[:, 0] - T[0, 3]
        J = np.einsum("cmij,mjk->cmik", d_uv_dp, dP)  # (C, M, 2, 3)

        states = [self._camera(c) for c in cameras]
        # residuals against each camera's current offset estimate: Huber weights and the noise
        offsets = np.stack([st.offset for st in states])
        eps = e - np.einsum("cmij,cj->cmi", G, offsets)
        s2 = self._s2
        z2 = w * np.sum(eps ** 2, axis=2)  # w |eps|^2, px^2
        with np.errstate(divide="ignore", invalid="ignore"):
            r_norm = np.sqrt(z2 / s2)
            huber = np.where(r_norm > HUBER_K, HUBER_K / r_norm, 1.0)
        huber = np.where(valid, huber, 0.0)
        n_valid = valid.sum(axis=1)
        if int(n_valid.sum()) > 6:
            frame_s2 = float(np.sum(huber * z2) / max(2 * n_valid.sum() - 3, 1))
            if math.isfinite(frame_s2):
                self._s2 = max((1 - NOISE_EMA) * s2 + NOISE_EMA * min(frame_s2, 25.0 * s2),
                               self.noise.floor_px ** 2)

        # Sigma^-1 = D^-1 - D^-1 U (I + U^T D^-1 U)^-1 U^T D^-1: independent + rank-3 per detection
        omega = np.repeat((w * huber / s2)[..., None], 2, axis=2).reshape(C, 2 * M)
        U = np.zeros((C, M, 2, 3))
        U[:, :, 0, 0] = self.noise.shift_px
        U[:, :, 1, 1] = self.noise.shift_px
        cnt = np.maximum(n_valid, 1)[:, None]
        # the scale error's direction from the predicted keypoints: from the observed ones it
        # would correlate with their noise and bias the offset along the viewing ray
        uv_pred = np.where(valid[..., None], uv_hat, 0.0)
        centroid = uv_pred.sum(axis=1) / cnt  # (C, 2)
        U[..., 2] = self.noise.scale * (uv_pred - centroid[:, None, :])
        Uf = np.where(valid[..., None, None], U, 0.0).reshape(C, 2 * M, 3)
        K = np.concatenate([J.reshape(C, 2 * M, 3), G.reshape(C, 2 * M, 6),
                            e.reshape(C, 2 * M, 1)], axis=2)  # (C, 2M, 10)
        KW = K * omega[..., None]
        UW = Uf * omega[..., None]
        KtK = np.einsum("cni,cnj->cij", KW, K)
        KtU = np.einsum("cni,cnj->cij", KW, Uf)
        UtU = np.einsum("cni,cnj->cij", UW, Uf)
        inner = np.linalg.inv(np.eye(3) + UtU)
        Q = KtK - KtU @ inner @ KtU.transpose(0, 2, 1)  # (C, 10, 10): K^T Sigma^-1 K
        # a view that repeats the camera's previous one repeats its keypoint errors: it counts
        # as the fraction of an independent view the robot moved since (Sigma / novelty)
        view = (float(T[0, 3]), float(T[1, 3]), math.atan2(T[1, 0], T[0, 0]))
        novelty = np.array([st.novelty(view, cfg.independent_motion_m,
                                       math.radians(cfg.independent_turn_deg))
                            for st in states])
        novelty = np.where(n_valid > 0, novelty, 0.0)
        if float(novelty.max(initial=0.0)) < MIN_NOVELTY:
            return self._skip("same_view")
        Q = Q * novelty[:, None, None]
        Hc = Q[:, :3, :3]
        H = Hc.sum(axis=0)
        if not np.all(np.isfinite(Q)) or np.linalg.cond(H) > MAX_CONDITION:
            return self._skip("degenerate")
        for k, st in enumerate(states):
            if novelty[k] > 0:
                st.view = view
        # the pose marginalized out: this frame-set's normal equations of the cameras' offsets
        B = Q[:, :3, 3:9]  # (C, 3, 6) J^T Sigma^-1 G
        HiB = np.linalg.solve(H, B.transpose(1, 0, 2).reshape(3, C * 6))  # (3, 6C)
        lam_k = -B.transpose(0, 2, 1).reshape(C * 6, 3) @ HiB  # (6C, 6C)
        for k in range(C):
            lam_k[6 * k:6 * k + 6, 6 * k:6 * k + 6] += Q[k, 3:9, 3:9]
        eta_k = Q[:, 3:9, 9].reshape(-1) - HiB.T @ Q[:, :3, 9].sum(axis=0)
        if not (np.all(np.isfinite(lam_k)) and np.all(np.isfinite(eta_k))):
            return self._skip("non_finite")
        # exponential forgetting in judged time, then this frame-set's equations
        dt = 1.0 / cfg.max_rate_hz if self._last_ns is None else \
            min(max((stamp_ns - self._last_ns) * 1e-9, 0.0), MAX_STEP_S)
        self._last_ns = stamp_ns
        decay = math.exp(-dt / cfg.forgetting_s)
        self._L *= decay
        self._eta *= decay
        idx = (np.array([st.index for st in states])[:, None] * 6 + np.arange(6)).reshape(-1)
        self._L[np.ix_(idx, idx)] += 0.5 * (lam_k + lam_k.T)
        self._eta[idx] += eta_k
        self.counters["judged"] += 1
        for k, st in enumerate(states):
            others = len(healthy) - (cameras[k].camera_id in healthy)
            if n_valid[k] >= cfg.min_keypoints and others >= cfg.min_other_cameras:
                st.evidence_s += dt * float(novelty[k])
                st.judged += 1
        self._touched.update(ids_of(cameras))
        self._since_decision_s += dt
        # the decision solves the joint equations: on a site with many cameras, less often
        if self._since_decision_s < DECISION_PERIOD_S * max(1.0, len(self._cams) / 8):
            return []
        self._since_decision_s = 0.0
        return self._decide(stamp_ns)

    def _consistent(self, e: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """``valid`` (C, M) less the keypoints that do not move with their view: further than
        :data:`INLIER_SIGMAS` noise sigmas (at least :data:`INLIER_MIN_PX`) from the view's
        common shift (the median residual, ``e`` (C, M, 2)), and less every keypoint of a view
        left with fewer than ``min_keypoints``. A network's gross keypoint errors (an occluded
        bottom keypoint put on an obstacle's edge, a robot cut by the image border) are tens
        of pixels on a few keypoints, coherent across a stretch of frames; weighed as
        residuals, they named unmoved cameras moved by tens of centimetres. Counted
        ``outlier_keypoints`` and ``inconsistent_views``."""
        n_valid = valid.sum(axis=1)
        with np.errstate(invalid="ignore"):
            masked = np.where(valid[..., None], e, np.nan)
            shift = np.zeros((e.shape[0], 2))
            some = n_valid > 0
            if some.any():
                shift[some] = np.nanmedian(masked[some], axis=1)
            dev = np.linalg.norm(e - shift[:, None, :], axis=2)
            bound = max(INLIER_SIGMAS * math.sqrt(self._s2), INLIER_MIN_PX)
            inlier = valid & (dev <= bound)
        self.counters["outlier_keypoints"] += int((valid & ~inlier).sum())
        need = self.config.min_keypoints
        enough = inlier.sum(axis=1) >= need
        self.counters["inconsistent_views"] += int(((n_valid >= need) & ~enough).sum())
        return inlier & enough[:, None]

    def _decide(self, stamp_ns: int) -> list[MovedCamera]:
        """Every camera's offset from the joint equations, each tested against its tolerance
        with the others held to theirs (module docstring); names the most significant."""
        cfg = self.config
        if not self._cams:
            return []
        # a camera judged moved is no longer held to its calibration
        priors = {cid: self._A_prior if st.moved is not None else self._tol_info
                  for cid, st in self._cams.items()}
        prior = np.zeros_like(self._L)
        for cid, st in self._cams.items():
            prior[6 * st.index:6 * st.index + 6, 6 * st.index:6 * st.index + 6] = priors[cid]
        # only the cameras judged since the last decision (and the moved ones) are tested:
        # one factorization, their 6 columns of the inverse as right-hand sides
        tested = [(cid, st) for cid, st in self._cams.items()
                  if cid in self._touched or st.moved is not None]
        self._touched.clear()
        if not tested:
            return []
        n = self._L.shape[0]
        rhs = np.zeros((n, 1 + 6 * len(tested)))
        rhs[:, 0] = self._eta
        for j, (_, st) in enumerate(tested):
            rhs[6 * st.index:6 * st.index + 6, 1 + 6 * j:7 + 6 * j] = np.eye(6)
        try:
            sol = np.linalg.solve(self._L + prior, rhs)
        except np.linalg.LinAlgError:
            return self._skip("singular")
        offset_post = sol[:, 0]
        candidates: list[tuple[float, _Camera]] = []
        for j, (cid, st) in enumerate(tested):
            sl = slice(6 * st.index, 6 * st.index + 6)
            S = sol[sl, 1 + 6 * j:7 + 6 * j]
            S = 0.5 * (S + S.T)
            # leave this camera's own tolerance prior out: what the data say of its offset
            info = np.linalg.inv(S) - priors[cid] + self._A_prior
            P = np.linalg.inv(info)
            P = 0.5 * (P + P.T)
            offset = P @ (np.linalg.solve(S, offset_post[sl]))
            if not (np.all(np.isfinite(offset)) and np.all(np.isfinite(P))):
                self.counters["skipped.non_finite"] += 1
                continue
            st.offset, st.covariance = offset, P
            st.chi2 = float(offset @ np.linalg.solve(P + self._P_tol, offset))
            if (st.moved is not None and cfg.action == "report" and st.chi2 < cfg.clear_chi2
                    and st.evidence_s >= cfg.min_evidence_s):
                log.info("camera health: %s agrees with the others again", cid)
                st.moved = None
                self.counters["cleared"] += 1
        for cid, st in tested:
            if st.moved is not None:
                continue
            # which camera moved must be clear: a bump drags the cameras it shares frame-sets
            # with along until the views from elsewhere tell them apart
            runner_up = max((o.chi2 for k, o in self._cams.items()
                             if k != cid and o.moved is None), default=0.0)
            if (st.evidence_s >= cfg.min_evidence_s and st.chi2 >= cfg.alarm_chi2
                    and st.chi2 >= DOMINANCE * runner_up):
                st.over_s += DECISION_PERIOD_S
            else:
                st.over_s = 0.0
            if st.over_s >= cfg.confirm_s:
                candidates.append((st.chi2, st))
        if not candidates:
            return []
        # one bump pulls the poses the others are judged against: name the most significant
        chi2, st = max(candidates, key=lambda c: c[0])
        cid = next(k for k, v in self._cams.items() if v is st)
        st.moved = MovedCamera(cid, float(np.linalg.norm(st.offset[3:])),
                               math.degrees(float(np.linalg.norm(st.offset[:3]))), chi2,
                               stamp_ns)
        self.counters["moved"] += 1
        self.counters[f"moved.{cid}"] += 1
        log.warning("camera health: %s", st.moved.text(cfg.action == "exclude"))
        # the bump is a break: what was gathered before it mixes the camera's old and new pose
        # and, through the joint estimate, leaks into its partners; every camera starts afresh
        # (the moved one is still compared, so its offset in the status converges to the bump)
        self._L[:] = 0.0
        self._eta[:] = 0.0
        for other in self._cams.values():
            other.evidence_s = other.over_s = 0.0
            other.chi2 = 0.0
        return [st.moved]
