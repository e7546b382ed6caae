"""Detections to robots: which robot of the site each detection in one camera image is.

The edge agent reports the robots it sees without an identity (identical robots look the same;
``Detection.robot_id == ""``). On a site with several robots the backend tells them apart only by
where each is expected to be: every robot with a **prediction** (its fused pose propagated with
odometry to the image's stamp, else a recent camera estimate, else its own localization from
its bridge with a wide covariance; :class:`RobotPrediction`) has its keypoints reprojected into
the camera, and each (detection, robot) pair gets a cost (:func:`association_costs`):

- the keypoints both visible at the predicted pose (in front of the camera, inside the image)
  and confident in the detection (score ``>= min_keypoint_score``) are compared; each pixel
  residual is normalised by its predicted uncertainty (the pose covariance propagated through
  the projection's pinhole Jacobian, plus the detector's pixel noise: a Mahalanobis distance
  per keypoint);
- the cost is the mean of those distances, each clipped to ``clip_distance`` (an outlier, a
  keypoint the robot's own body hides, moves it by at most ``clip_distance / n``); fewer than
  ``min_keypoints`` shared keypoints, or a detection box that does not overlap the predicted
  one (widened by ``box_margin_sigmas`` of the predicted uncertainty), mean no cost
  (infinite).

A pair whose cost is above ``gate`` is not a candidate. The optimal assignment (Hungarian,
:func:`hungarian`, exact, written here so the backend needs no scipy) gives each robot at most
one detection of the image and each detection at most one robot, assigning as many pairs as
the gate allows with the least total ``cost² / 2`` (the negative log-likelihood of the
assignment when the normalised distances are Gaussian). **Ambiguity**: for each assigned pair
that has a rival within the gate (another robot for the detection, another detection for the
robot) the best assignment without that pair is solved too; when it is at least
``ambiguity_ratio`` times as likely as the best one (its total within ``-ln(ambiguity_ratio)``
of the optimum) the detection is left unassigned and counted (``ambiguous``): two identical
robots that meet while their predictions are too vague to tell them apart, or one robot whose
prediction fits two nearby detections, get no detection rather than a guess. With the default
ratio (1 %) two robots predicted with the same position sigma are told apart once their
predictions differ by about 2 sigma along the line between them. **A robot with no
prediction** could be anywhere: while one robot of a model has none, a robot of that model
known only roughly (position sigma above ``vague_sigma_xy_m``, e.g. only by its own
localization) takes no detection either (``ambiguous``): it might be the other one's. Robots
tracked by the cameras (a few cm) keep theirs; the unknown one's detections are outside their
gates.

Detections that carry a robot id keep it: an id the site does not know is dropped
(``unknown_robot``); a known id whose robot has a prediction that the detection contradicts
(cost above the gate) is still routed to it and counted (``id_contradicted``); a named robot is
not a candidate for the unnamed detections of the same image.

**Several robot types**: a detection that names its robot model (``Detection.robot_model``, set
by an edge that runs one detector per type) is a candidate only for robots of that model, however
close another type's prediction is; a model no robot of the site has is dropped and counted
(``unknown_model``). A detection without a model (``""``) is costed against every robot whose
model has its keypoint count, as before. Everything here is numpy and
plain Python, transport-free; :class:`DetectionRouter` applies it to a
:class:`~protocol.messages.RobotDetections` message and keeps the counters.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Final

import numpy as np

from backend_service.assignment import gated_assignment
from backend_service.projection import pixels_from_camera_frame, stacked_cameras
from core.camera import CameraModel
from core.pose import PlanarPose
from protocol.messages import Detection

#: why a detection went (or did not go) to a robot (the router counts ``detections_<reason>``)
REASONS: Final = ("assigned", "named", "id_contradicted", "unknown_robot", "ambiguous",
                  "unassigned", "no_prediction", "unknown_model")
#: where a prediction came from (:class:`RobotPrediction.source`)
PREDICTION_SOURCES: Final = ("fused", "camera", "localization")
#: a predicted keypoint this close to the camera (or behind it) is not visible, metres
_MIN_DEPTH_M: Final = 0.05


@dataclasses.dataclass(frozen=True)
class AssociationConfig:
    """How detections are matched to robots (units in the names; costs are mean normalised
    reprojection distances, i.e. "sigmas").

    ``gate``: a pair costing more is not a candidate. ``ambiguity_ratio``: a pair is ambiguous
    when the best assignment without it is at least this likely relative to the best one (see
    the module doc). ``vague_sigma_xy_m``: a prediction with a larger position sigma (a robot
    known only by its own localization) takes no detection while a robot of its model has no
    prediction at all. ``min_keypoints``: shared visible, confident keypoints needed for a cost.
    ``min_keypoint_score``: a keypoint below it is not compared. ``detector_sigma_px``: pixel
    noise of a keypoint (floor of the detector's own ``keypoint_sigmas_px``).
    ``clip_distance``: each keypoint's normalised distance is clipped to it before the mean
    (>= ``gate``). ``box_margin_sigmas``: the predicted box is widened by this many pixel
    sigmas before the overlap test. ``unlocalized_sigma_xy_m`` /
    ``unlocalized_sigma_theta_rad``: the smallest covariance given to a prediction from the
    robot's own localization (a robot not yet localized by the cameras). ``min_sigma_xy_m`` /
    ``min_sigma_theta_rad``: the smallest covariance of any prediction. ``max_speed_mps`` /
    ``max_yaw_rate_radps``: growth of the uncertainty per second a prediction is carried
    beyond its stamp.
    """

    gate: float = 4.0
    ambiguity_ratio: float = 0.01
    vague_sigma_xy_m: float = 0.15
    min_keypoints: int = 4
    min_keypoint_score: float = 0.3
    detector_sigma_px: float = 3.0
    clip_distance: float = 6.0
    box_margin_sigmas: float = 3.0
    unlocalized_sigma_xy_m: float = 0.5
    unlocalized_sigma_theta_rad: float = 0.35
    min_sigma_xy_m: float = 0.02
    min_sigma_theta_rad: float = 0.01
    max_speed_mps: float = 1.0
    max_yaw_rate_radps: float = 1.5

    def __post_init__(self) -> None:
        positive = ("gate", "detector_sigma_px", "unlocalized_sigma_xy_m", "vague_sigma_xy_m",
                    "unlocalized_sigma_theta_rad", "min_sigma_xy_m", "min_sigma_theta_rad")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"AssociationConfig.{name} must be > 0")
        for name in ("box_margin_sigmas", "max_speed_mps",
                     "max_yaw_rate_radps", "min_keypoint_score"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"AssociationConfig.{name} must be >= 0")
        if not 0 < self.ambiguity_ratio < 1:
            raise ValueError("AssociationConfig.ambiguity_ratio must be in (0, 1)")
        if not self.clip_distance >= self.gate:
            raise ValueError("AssociationConfig.clip_distance must be >= gate")
        if self.min_keypoints < 1:
            raise ValueError("AssociationConfig.min_keypoints must be >= 1")


@dataclasses.dataclass(frozen=True, eq=False)
class RobotPrediction:
    """Where a robot is expected at some stamp: ``pose`` (world frame), ``covariance`` (3, 3)
    of (x, y, theta) in m², rad², and what it came from (``source``: one of
    :data:`PREDICTION_SOURCES`)."""

    robot_id: str
    pose: PlanarPose
    covariance: np.ndarray
    source: str

    def __post_init__(self) -> None:
        cov = np.asarray(self.covariance, dtype=np.float64)
        if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
            raise ValueError(f"RobotPrediction({self.robot_id!r}).covariance: expected a finite "
                             f"(3, 3) array, got shape {cov.shape}")
        if self.source not in PREDICTION_SOURCES:
            raise ValueError(f"RobotPrediction.source {self.source!r} not in "
                             f"{PREDICTION_SOURCES}")
        object.__setattr__(self, "covariance", cov)

    def sigma_xy_m(self) -> float:
        """The largest position standard deviation (m): the square root of the largest
        eigenvalue of the (x, y) covariance."""
        return math.sqrt(max(float(np.linalg.eigvalsh(self.covariance[:2, :2])[-1]), 0.0))


def predicted_covariance(covariance: np.ndarray | None, dt_s: float, source: str,
                         config: AssociationConfig) -> np.ndarray:
    """The covariance of a prediction: ``covariance`` (``None``, non-finite or not 3 x 3: zero)
    made symmetric positive semi-definite (negative eigenvalues, which a faulty sender may
    give, clipped to zero), grown by the motion possible over ``dt_s`` seconds
    (``max_speed_mps``, ``max_yaw_rate_radps``), and floored (``min_sigma_*``; for
    ``source == "localization"`` the ``unlocalized_sigma_*``)."""
    cov = np.zeros((3, 3)) if covariance is None else np.asarray(covariance, np.float64)
    if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
        cov = np.zeros((3, 3))
    cov = 0.5 * (cov + cov.T)
    eigval, eigvec = np.linalg.eigh(cov)
    if eigval[0] < 0.0:
        cov = (eigvec * np.maximum(eigval, 0.0)) @ eigvec.T
    dt = abs(float(dt_s))
    grow = np.array([config.max_speed_mps * dt, config.max_speed_mps * dt,
                     config.max_yaw_rate_radps * dt]) ** 2
    cov = cov + np.diag(grow)
    if source == "localization":
        floor = np.array([config.unlocalized_sigma_xy_m, config.unlocalized_sigma_xy_m,
                          config.unlocalized_sigma_theta_rad]) ** 2
    else:
        floor = np.array([config.min_sigma_xy_m, config.min_sigma_xy_m,
                          config.min_sigma_theta_rad]) ** 2
    diag = np.diag(cov)
    return cov + np.diag(np.maximum(floor - diag, 0.0))


@dataclasses.dataclass(frozen=True)
class DetectionOutcome:
    """What became of one detection: ``robot_id`` it goes to (``""``: none), ``reason`` (one of
    :data:`REASONS`), ``cost`` to that robot (or to its best candidate when unassigned; ``inf``
    when none could be computed)."""

    robot_id: str
    reason: str
    cost: float

    @property
    def used(self) -> bool:
        """Whether the detection goes to a robot's pipeline."""
        return bool(self.robot_id)


@dataclasses.dataclass(frozen=True, eq=False)
class Association:
    """The association of one image: ``outcomes`` per detection (input order), ``robot_ids``
    the robots costed (column order of ``costs``), ``costs`` (D, R) (``inf``: not computable),
    ``by_robot`` robot id → index of its detection (robots without one are absent)."""

    outcomes: tuple[DetectionOutcome, ...]
    robot_ids: tuple[str, ...]
    costs: np.ndarray
    by_robot: Mapping[str, int]

    def detection_of(self, robot_id: str) -> int | None:
        """Index of the detection that goes to ``robot_id``, or ``None``."""
        return self.by_robot.get(robot_id)

    def count(self, reason: str) -> int:
        return sum(1 for o in self.outcomes if o.reason == reason)


# -- the assignment ---------------------------------------------------------------------------


# -- the costs --------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class PredictedView:
    """R predicted robots of one keypoint model (M keypoints) as one camera should see them:
    ``uv`` (R, M, 2) pixels, ``visible`` (R, M) in front of the camera and inside the image,
    ``sigma_uv`` (R, M, 2, 2) the pixel covariance the pose covariance gives each keypoint
    (the pinhole Jacobian of the projection; zero for a robot with no keypoint in the image,
    which takes no detection of this camera), ``box_lo`` / ``box_hi`` (R, 2) the box of the
    visible keypoints widened by ``box_margin_sigmas`` pixel sigmas (pose and detector; inf /
    -inf without a visible keypoint),
    ``info`` (3, R, M) the entries (uu, uv, vv) of the inverse of ``sigma_uv`` plus the
    detector's pixel noise ``detector_sigma_px`` (the common case's information matrix)."""

    uv: np.ndarray
    visible: np.ndarray
    sigma_uv: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    info: np.ndarray

    def rows(self, index: Sequence[int]) -> PredictedView:
        idx = np.asarray(index, dtype=np.intp)
        return PredictedView(self.uv[idx], self.visible[idx], self.sigma_uv[idx],
                             self.box_lo[idx], self.box_hi[idx], self.info[:, idx])


def predicted_views(cameras: Sequence[CameraModel], keypoints_base_m: np.ndarray,
                    predictions: Sequence[RobotPrediction], config: AssociationConfig
                    ) -> list[PredictedView]:
    """:class:`PredictedView` of ``predictions`` (robots of one model, ``keypoints_base_m``
    (M, 3)) in each of ``cameras``, vectorized over cameras, robots and keypoints. The pixels
    are the solver's projection (:func:`~backend_service.projection.project_planar`, with
    distortion); the pose covariance reaches the pixels through the pinhole Jacobian of the
    projection (lens distortion, a few per cent of it at the image edges, left out of this
    uncertainty)."""
    cams = stacked_cameras(tuple(cameras))
    q0 = np.array([[p.pose.x, p.pose.y, p.pose.theta] for p in predictions], dtype=np.float64)
    kp = np.asarray(keypoints_base_m, dtype=np.float64)
    n_cam, n_rob, m = len(cameras), len(q0), len(kp)
    c, s = np.cos(q0[:, 2])[:, None], np.sin(q0[:, 2])[:, None]
    # world points (R, M, 3) and their derivative by theta (x and y move them by unit vectors)
    pw = np.stack([c * kp[:, 0] - s * kp[:, 1] + q0[:, 0, None],
                   s * kp[:, 0] + c * kp[:, 1] + q0[:, 1, None],
                   np.broadcast_to(kp[:, 2], (n_rob, m))], axis=-1)
    dpw_dtheta = np.stack([-s * kp[:, 0] - c * kp[:, 1], c * kp[:, 0] - s * kp[:, 1],
                           np.zeros((n_rob, m))], axis=-1)
    # camera frame (N, R, M, 3); one matrix product (small einsums are slow)
    pc = (np.matmul(pw.reshape(1, -1, 3), np.swapaxes(cams.R_cw, 1, 2))
          + cams.t_cw[:, None, :]).reshape(n_cam, n_rob, m, 3)
    # the pixels as the solver projects them (N, R, M, 2), depths (N, R, M)
    uv0, depth = pixels_from_camera_frame(pc, cams.K[:, None, None], cams.dist[:, None, None, :])
    u, v = uv0[..., 0], uv0[..., 1]
    w = np.array([cam.width - 1.0 for cam in cameras])[:, None, None]
    h = np.array([cam.height - 1.0 for cam in cameras])[:, None, None]
    visible = ((depth > _MIN_DEPTH_M) & (u >= 0.0) & (u <= w) & (v >= 0.0) & (v <= h)
               & np.isfinite(u) & np.isfinite(v))  # (N, R, M)
    # The pixel covariance only for the (camera, robot) pairs with a keypoint in the image:
    # a pair without one costs inf whatever its covariance (no shared keypoint, no box), and
    # on a large site most robots are in few cameras (zero for the others).
    sigma_uv = np.zeros((n_cam, n_rob, m, 2, 2))
    lo = np.full((n_cam, n_rob, 2), np.inf)
    hi = np.full((n_cam, n_rob, 2), -np.inf)
    cam_i, rob_i = np.nonzero(visible.any(axis=-1))
    if cam_i.size:
        sigma = _pixel_covariance(pc[cam_i, rob_i], cams.R_cw[cam_i], dpw_dtheta[rob_i],
                                  cams.K[cam_i],
                                  np.stack([p.covariance for p in predictions])[rob_i])
        sigma_uv[cam_i, rob_i] = sigma
        # the box of the visible keypoints, widened by the pose's and the detector's sigmas
        sig_px = np.sqrt(np.maximum(np.maximum(sigma[..., 0, 0], sigma[..., 1, 1]), 0.0)
                         + config.detector_sigma_px ** 2)  # (P, M)
        pad = config.box_margin_sigmas * sig_px[..., None]
        vis, uv_p = visible[cam_i, rob_i][..., None], uv0[cam_i, rob_i]
        lo[cam_i, rob_i] = np.where(vis, uv_p - pad, np.inf).min(axis=1)
        hi[cam_i, rob_i] = np.where(vis, uv_p + pad, -np.inf).max(axis=1)
    info = _information(sigma_uv, config.detector_sigma_px ** 2)  # (3, N, R, M)
    return [PredictedView(uv0[i], visible[i], sigma_uv[i], lo[i], hi[i], info[:, i])
            for i in range(len(cameras))]


def _pixel_covariance(pc: np.ndarray, R_cw: np.ndarray, dpw_dtheta: np.ndarray, K: np.ndarray,
                      cov: np.ndarray) -> np.ndarray:
    """(P, M, 2, 2) pixel covariance ``J cov J^T`` of M keypoints for P (camera, pose) pairs:
    ``pc`` (P, M, 3) the keypoints in the camera frame, ``R_cw`` (P, 3, 3) and ``K`` (P, 3, 3)
    the cameras, ``dpw_dtheta`` (P, M, 3) the world points' derivative by the heading, ``cov``
    (P, 3, 3) the poses' covariances; ``J`` the pinhole Jacobian of the pixels by (x, y,
    theta)."""
    # camera-frame derivatives (P, M, 3) by x, y (the world axes' images) and theta
    d_by = (np.broadcast_to(R_cw[:, None, :, 0], pc.shape),
            np.broadcast_to(R_cw[:, None, :, 1], pc.shape),
            np.matmul(dpw_dtheta, np.swapaxes(R_cw, 1, 2)))
    z = np.maximum(pc[..., 2], _MIN_DEPTH_M)
    fx, fy = K[:, 0, 0][:, None], K[:, 1, 1][:, None]
    xz, yz = pc[..., 0] / z, pc[..., 1] / z
    J = np.empty((*pc.shape[:2], 2, 3))  # (P, M, 2, 3): pixels by (x, y, theta)
    for k, d in enumerate(d_by):
        J[..., 0, k] = fx * (d[..., 0] - xz * d[..., 2]) / z
        J[..., 1, k] = fy * (d[..., 1] - yz * d[..., 2]) / z
    cov = cov[:, None, :, :]  # (P, 1, 3, 3)
    # J cov J^T, written out: batched 2x3 matrix products are slower
    JC = [[sum(J[..., i, r] * cov[..., r, k] for r in range(3)) for k in range(3)]
          for i in range(2)]
    out = np.empty((*pc.shape[:2], 2, 2))
    for i in range(2):
        for j in range(i, 2):
            out[..., i, j] = sum(JC[i][k] * J[..., j, k] for k in range(3))
    out[..., 1, 0] = out[..., 0, 1]
    return out


def _information(sigma_uv: np.ndarray, var_px2: float | np.ndarray) -> np.ndarray:
    """Entries (uu, uv, vv) of the inverse of ``sigma_uv`` (..., 2, 2) plus ``var_px2`` times
    the identity (positive definite: ``sigma_uv`` is semi-definite, ``var_px2`` > 0)."""
    a = sigma_uv[..., 0, 0] + var_px2
    b = sigma_uv[..., 0, 1]
    c = sigma_uv[..., 1, 1] + var_px2
    det = a * c - b * b
    return np.stack([c / det, -b / det, a / det])


class ViewCache:
    """The predicted views of a set of predictions in every camera of a site, computed in one
    projection when the predictions change (they are the same objects for all the images of a
    frame-set: :meth:`~backend_service.robot_track.RobotTrack.prediction` reuses them) and
    reused for each camera's image. The last ``keep`` sets are kept per keypoint model: the
    images of neighbouring frame-sets may arrive interleaved."""

    def __init__(self, cameras: Sequence[CameraModel], config: AssociationConfig,
                 keep: int = 4) -> None:
        self.cameras = tuple(cameras)
        self.config = config
        self._index = {c.camera_id: i for i, c in enumerate(self.cameras)}
        #: keypoint model (by identity) -> recent (predictions, their row, views per camera)
        self._entries: dict[int, collections.deque[tuple[
            tuple[RobotPrediction, ...], dict[int, int], list[PredictedView]]]] = {}
        self._keep = int(keep)
        self.computed = 0  # projections made (for tests and benchmarks)

    def view(self, camera: CameraModel, keypoints_base_m: np.ndarray,
             predictions: Sequence[RobotPrediction]) -> PredictedView:
        cam_i = self._index.get(camera.camera_id)
        if cam_i is None or self.cameras[cam_i] is not camera:
            return predicted_views([camera], keypoints_base_m, predictions, self.config)[0]
        views, idx = self._views(keypoints_base_m, predictions)
        return views[cam_i] if idx is None else views[cam_i].rows(idx)

    def cameras_seeing(self, keypoints_base_m: np.ndarray,
                       predictions: Sequence[RobotPrediction], row: int) -> frozenset[str]:
        """The cameras of this cache in whose image ``predictions[row]`` has a keypoint
        predicted: the only ones of them whose detections :func:`associate` can give that
        robot (a pair with no shared keypoint costs ``inf``)."""
        views, idx = self._views(keypoints_base_m, predictions)
        r = row if idx is None else idx[row]
        return frozenset(cam.camera_id for cam, v in zip(self.cameras, views, strict=True)
                         if v.box_lo[r, 0] <= v.box_hi[r, 0])

    def _views(self, keypoints_base_m: np.ndarray, predictions: Sequence[RobotPrediction]
               ) -> tuple[list[PredictedView], list[int] | None]:
        """The views of ``predictions`` in every camera of the cache, and the rows of
        ``predictions`` in them (``None``: the same rows)."""
        entries = self._entries.setdefault(id(keypoints_base_m),
                                           collections.deque(maxlen=self._keep))
        if entries:  # the common case: the same predictions as the image before
            preds, _, views = entries[-1]
            if len(preds) == len(predictions) and all(
                    a is b for a, b in zip(preds, predictions, strict=True)):
                return views, None
        for preds, rows, views in entries:
            idx = [rows.get(id(p), -1) for p in predictions]
            if all(i >= 0 and preds[i] is p for i, p in zip(idx, predictions, strict=True)):
                same = len(idx) == len(preds) and idx == sorted(idx)
                return views, None if same else idx
        preds = tuple(predictions)
        views = predicted_views(self.cameras, keypoints_base_m, preds, self.config)
        self.computed += 1
        entries.append((preds, {id(p): i for i, p in enumerate(preds)}, views))
        return views, None


def association_costs(camera: CameraModel, detections: Sequence[Detection],
                      predictions: Sequence[RobotPrediction],
                      keypoints_base_m: Mapping[str, np.ndarray],
                      config: AssociationConfig, views: ViewCache | None = None) -> np.ndarray:
    """(D, R) cost of each detection (keypoints in ``camera``'s calibrated pixels) being each
    predicted robot (``keypoints_base_m``: robot id → its model's (M, 3) keypoints); ``inf``
    where the pair cannot be judged (keypoint count differs from the robot's model, too few
    shared keypoints, boxes apart). ``views``: where the predicted views come from (default:
    projected now). See the module doc."""
    n_det, n_rob = len(detections), len(predictions)
    costs = np.full((n_det, n_rob), np.inf)
    if n_det == 0 or n_rob == 0:
        return costs
    # robots grouped by keypoint model (one projection per model)
    groups: dict[int, list[int]] = collections.defaultdict(list)
    models: dict[int, np.ndarray] = {}
    for j, p in enumerate(predictions):
        kp = keypoints_base_m[p.robot_id]
        groups[id(kp)].append(j)
        models[id(kp)] = kp
    for key, cols in groups.items():
        kp = models[key]
        m = kp.shape[0]
        dets = [i for i, d in enumerate(detections) if d.keypoints_px.shape[0] == m]
        if not dets:
            continue
        group = [predictions[j] for j in cols]
        view = (views.view(camera, kp, group) if views is not None
                else predicted_views([camera], kp, group, config)[0])
        lo, hi = view.box_lo, view.box_hi
        if len(dets) == 1:
            # the common case, one detection: the box gate over the robots at once, then the
            # few pairs it lets through one by one (the same arithmetic, no (D, R) arrays)
            det = detections[dets[0]]
            x0, y0, x1, y1 = det.bbox_xyxy.tolist()
            inside = ((x0 <= hi[:, 0]) & (x1 >= lo[:, 0]) & (y0 <= hi[:, 1])
                      & (y1 >= lo[:, 1]))
            var_r = (None if det.keypoint_sigmas_px is None else
                     np.maximum(det.keypoint_sigmas_px, config.detector_sigma_px) ** 2)
            for r in np.flatnonzero(inside).tolist():
                costs[dets[0], cols[r]] = _pair_cost(det, view, r, var_r, config)
            continue
        chosen = [detections[i] for i in dets]
        obs = np.stack([d.keypoints_px for d in chosen])  # (D, M, 2)
        scores = np.stack([d.keypoint_scores for d in chosen])
        boxes = np.stack([d.bbox_xyxy for d in chosen])  # (D, 4)
        # the information matrix of each keypoint's residual: the pose-induced pixel covariance
        # plus the detector's pixel noise (its own sigmas where it sends them)
        info = view.info[:, None]  # (3, 1, R, M)
        if any(d.keypoint_sigmas_px is not None for d in chosen):
            var = np.full(scores.shape, config.detector_sigma_px ** 2)
            for row, d in enumerate(chosen):
                if d.keypoint_sigmas_px is not None:
                    var[row] = np.maximum(d.keypoint_sigmas_px, config.detector_sigma_px) ** 2
            info = _information(view.sigma_uv[None], var[:, None, :])  # (3, D, R, M)
        # keypoints are finite (the message's validation); a dropped one has score 0
        confident = scores >= config.min_keypoint_score
        res = obs[:, None] - view.uv  # (D, R, M, 2)
        rx, ry = res[..., 0], res[..., 1]
        d2 = info[0] * rx * rx + 2.0 * info[1] * rx * ry + info[2] * ry * ry
        shared = confident[:, None, :] & view.visible  # (D, R, M)
        n_shared = np.count_nonzero(shared, axis=-1)
        # robust mean: each keypoint's distance clipped, so one outlier moves it little
        clipped = np.minimum(np.sqrt(np.maximum(d2, 0.0)), config.clip_distance)
        mean = np.where(shared, clipped, 0.0).sum(axis=-1) / np.maximum(n_shared, 1)
        # the box sanity gate: the detection's box overlaps the widened predicted one
        overlap = ((boxes[:, None, 0] <= hi[..., 0]) & (boxes[:, None, 2] >= lo[..., 0])
                   & (boxes[:, None, 1] <= hi[..., 1]) & (boxes[:, None, 3] >= lo[..., 1]))
        block = np.where(overlap & (n_shared >= config.min_keypoints), mean, np.inf)
        if len(dets) == n_det and len(cols) == n_rob:
            costs = block
        else:
            costs[np.ix_(dets, cols)] = block
    return costs


def _pair_cost(det: Detection, view: PredictedView, r: int, var_px2: np.ndarray | None,
               config: AssociationConfig) -> float:
    """:func:`association_costs` of one detection whose box overlaps row ``r`` of ``view``
    (``var_px2``: the detection's own keypoint variances, floored, or ``None``): the same rules
    and arithmetic without the (D, R) arrays."""
    shared = (det.keypoint_scores >= config.min_keypoint_score) & view.visible[r]
    n_shared = int(np.count_nonzero(shared))
    if n_shared < config.min_keypoints:
        return math.inf
    info = view.info[:, r] if var_px2 is None else _information(view.sigma_uv[r], var_px2)
    res = det.keypoints_px - view.uv[r]
    rx, ry = res[:, 0], res[:, 1]
    d2 = info[0] * rx * rx + 2.0 * info[1] * rx * ry + info[2] * ry * ry
    clipped = np.minimum(np.sqrt(np.maximum(d2, 0.0)), config.clip_distance)
    return float(np.where(shared, clipped, 0.0).sum()) / max(n_shared, 1)


# -- one image --------------------------------------------------------------------------------


def associate(camera: CameraModel, detections: Sequence[Detection],
              predictions: Sequence[RobotPrediction],
              keypoints_base_m: Mapping[str, np.ndarray],
              config: AssociationConfig | None = None,
              site_robots: Sequence[str] | None = None,
              views: ViewCache | None = None,
              robot_models: Mapping[str, str] | None = None) -> Association:
    """Assign the detections of one image of ``camera`` (calibrated pixels) to robots.

    ``predictions``: the robots that may take unnamed detections (a robot with no prediction is
    absent: it takes none). ``site_robots``: every robot id of the site (a named detection with
    another id is ``unknown_robot``; default: the predicted robots). ``views``: a cache of the
    predicted views (:class:`ViewCache`; default: projected now). ``robot_models``: robot id →
    its model's name; when given, a detection that names a model goes only to robots of that
    model, and one naming a model none of them has is ``unknown_model`` (default: models are
    not checked). See the module doc for the rules; returns the outcome of every detection.
    """
    cfg = config or AssociationConfig()
    known = set(site_robots) if site_robots is not None else {p.robot_id for p in predictions}
    by_id = {p.robot_id: p for p in predictions}
    outcomes: list[DetectionOutcome | None] = [None] * len(detections)
    by_robot: dict[str, int] = {}
    named_robots: set[str] = set()
    site_models = set(robot_models.values()) if robot_models is not None else None
    for i, det in enumerate(detections):
        if site_models is not None and det.robot_model and det.robot_model not in site_models:
            outcomes[i] = DetectionOutcome("", "unknown_model", math.inf)
            continue
        rid = det.robot_id
        if not rid:
            continue
        if rid not in known:
            outcomes[i] = DetectionOutcome("", "unknown_robot", math.inf)
        elif rid in named_robots:
            # a robot is seen once per image: the higher-scored detection keeps the id
            prev = by_robot[rid]
            if det.score > detections[prev].score:
                outcomes[prev] = DetectionOutcome("", "unassigned", math.inf)
                by_robot[rid] = i
                outcomes[i] = DetectionOutcome(rid, "named", math.nan)
            else:
                outcomes[i] = DetectionOutcome("", "unassigned", math.inf)
        else:
            named_robots.add(rid)
            by_robot[rid] = i
            outcomes[i] = DetectionOutcome(rid, "named", math.nan)
    # named detections checked against their robot's prediction
    named_idx = [i for i in by_robot.values()]
    checked = [by_id[detections[i].robot_id] for i in named_idx
               if detections[i].robot_id in by_id]
    if checked:
        rows = [i for i in named_idx if detections[i].robot_id in by_id]
        cost_named = association_costs(camera, [detections[i] for i in rows], checked,
                                       keypoints_base_m, cfg, views)
        for k, i in enumerate(rows):
            cost = float(cost_named[k, k])
            reason = "named" if cost <= cfg.gate else "id_contradicted"
            outcomes[i] = DetectionOutcome(detections[i].robot_id, reason, cost)
    # the unnamed detections among the robots not named in this image
    free = [i for i, o in enumerate(outcomes) if o is None]
    candidates = [p for p in predictions if p.robot_id not in named_robots]
    robot_ids = tuple(p.robot_id for p in candidates)
    # robots of the site with no prediction (and not named here) could be anywhere: a
    # detection near a robot known only roughly may be theirs (their model; None: unknown)
    unpredicted_models = {id(kp) if (kp := keypoints_base_m.get(rid)) is not None else None
                          for rid in known if rid not in by_id and rid not in named_robots}
    costs = association_costs(camera, [detections[i] for i in free], candidates,
                              keypoints_base_m, cfg, views)
    if robot_models is not None and candidates:
        # a typed detection is no candidate for a robot of another model
        cand_models = np.array([robot_models.get(r, "") for r in robot_ids])
        for row, i in enumerate(free):
            model = detections[i].robot_model
            if model:
                costs[row, cand_models != model] = np.inf
    if free and not candidates:
        for i in free:
            outcomes[i] = DetectionOutcome("", "no_prediction", math.inf)
    elif free:
        # one unnamed detection (the common case) in closed form, several by the assignment
        rows = (_one_detection(costs[0], candidates, keypoints_base_m, unpredicted_models, cfg),
                ) if len(free) == 1 else _assign_rows(costs, candidates, keypoints_base_m,
                                                      unpredicted_models, cfg)
        for i, outcome in zip(free, rows, strict=True):
            outcomes[i] = outcome
            if outcome.reason == "assigned":
                by_robot[outcome.robot_id] = i
    final = tuple(o if o is not None else DetectionOutcome("", "unassigned", math.inf)
                  for o in outcomes)
    return Association(final, robot_ids, costs, by_robot)


def _twin_may_be_seen(pred: RobotPrediction, keypoints_base_m: Mapping[str, np.ndarray],
                      unpredicted_models: set[int | None], cfg: AssociationConfig) -> bool:
    """An identical robot without a prediction (one of ``pred``'s model, or of an unknown
    model: ``None`` in ``unpredicted_models``) may be the one seen where ``pred``, known only
    roughly (position sigma above ``vague_sigma_xy_m``), is expected."""
    return (None in unpredicted_models
            or id(keypoints_base_m[pred.robot_id]) in unpredicted_models) and (
            pred.sigma_xy_m() > cfg.vague_sigma_xy_m)


def _assign_rows(costs: np.ndarray, candidates: Sequence[RobotPrediction],
                 keypoints_base_m: Mapping[str, np.ndarray],
                 unpredicted_models: set[int | None], cfg: AssociationConfig
                 ) -> list[DetectionOutcome]:
    """The outcome of each unnamed detection (row of ``costs`` (D, R) over ``candidates``):
    the gated optimal assignment, each pair ambiguous when an identical robot without a
    prediction may be the one seen, or when the best assignment without the pair is within
    ``-ln(ambiguity_ratio)`` of it; rows left out are unassigned (with their least cost)."""
    out: list[DetectionOutcome | None] = [None] * costs.shape[0]
    pairs, total = gated_assignment(costs, cfg.gate)
    threshold = -math.log(cfg.ambiguity_ratio)
    # candidates per detection (row) and per robot (column): a pair has a rival when either
    # has another one; only then can the assignment without it be as good
    gated = costs <= cfg.gate
    per_row = gated.sum(axis=1).tolist()
    per_col = gated.sum(axis=0).tolist()
    for row, col in pairs:
        c1 = float(costs[row, col])
        reason = "assigned"
        pred = candidates[col]
        if _twin_may_be_seen(pred, keypoints_base_m, unpredicted_models, cfg):
            reason = "ambiguous"
        elif per_row[row] > 1 or per_col[col] > 1:
            blocked = costs.copy()
            blocked[row, col] = np.inf
            _, alt_total = gated_assignment(blocked, cfg.gate)
            if alt_total - total < threshold:
                reason = "ambiguous"
        out[row] = (DetectionOutcome(pred.robot_id, "assigned", c1) if reason == "assigned"
                    else DetectionOutcome("", "ambiguous", c1))
    for row in range(costs.shape[0]):
        if out[row] is None:
            best = float(costs[row].min()) if costs.shape[1] else math.inf
            out[row] = DetectionOutcome("", "unassigned", best)
    return out  # type: ignore[return-value]


def _one_detection(costs: np.ndarray, candidates: Sequence[RobotPrediction],
                   keypoints_base_m: Mapping[str, np.ndarray],
                   unpredicted_models: set[int | None], cfg: AssociationConfig
                   ) -> DetectionOutcome:
    """The outcome of a lone unnamed detection with cost row ``costs`` (R,) over
    ``candidates``: exactly what :func:`_assign_rows` decides for one row, without running
    the assignment twice (a camera of a fleet mostly sees one robot at a time).

    The gated assignment of one row takes the first column of least ``cost² / 2`` among those
    within the gate (every other column costs more than any gated one); blocking it, the
    assignment takes the least of the other gated columns, so the pair is ambiguous when a
    second gated column lies within ``-ln(ambiguity_ratio)`` of it. A column has no other row
    to rival it. The same arithmetic (``0.5 * cost²``) as :func:`gated_assignment`, so ties
    and rounding fall the same way (tests/backend_service/test_association.py compares the
    two on random rows)."""
    gated = np.flatnonzero(costs <= cfg.gate)
    if gated.size == 0:
        best = float(costs.min()) if costs.size else math.inf
        return DetectionOutcome("", "unassigned", best)
    nll = 0.5 * np.square(costs[gated])
    k = int(np.argmin(nll))  # the first of the least, as the Hungarian method's scan
    col = int(gated[k])
    c1 = float(costs[col])
    pred = candidates[col]
    if _twin_may_be_seen(pred, keypoints_base_m, unpredicted_models, cfg):
        return DetectionOutcome("", "ambiguous", c1)
    if gated.size > 1:
        rival = float(np.delete(nll, k).min())
        if rival - float(nll[k]) < -math.log(cfg.ambiguity_ratio):
            return DetectionOutcome("", "ambiguous", c1)
    return DetectionOutcome(pred.robot_id, "assigned", c1)


# -- on the wire ------------------------------------------------------------------------------


