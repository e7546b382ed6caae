"""Simulated keypoint detections: what an edge camera's detector would report.

For a camera frame captured at a true time, the robot's keypoints are projected through the
camera's *true* pose (the site's calibrated pose perturbed by a fixed calibration error), tested
for visibility (image bounds, range, obstacles, the robot's own body) and corrupted by the
detector error model of :class:`simulation.scenario.NoiseConfig`. Stamps carry each camera's
clock error; arrival times add latency and jitter. Everything random comes from seeded numpy
Generators, so a seed reproduces a run exactly.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from protocol.camera import CameraModel
from protocol.geometry import invert_transform, rotation_from_rotvec, se3_from_planar
from protocol.messages import Detection, RobotDetections
from simulation.scenario import Scenario
from simulation.world import World

MODEL_ID = "sim-noise-v1"


def true_cameras(scenario: Scenario) -> dict[str, CameraModel]:
    """The cameras as they really are: the site's calibrated extrinsics perturbed by the
    scenario's calibration error (seeded by ``seeds.calibration``, so it is a property of the
    site, the same in every run). Intrinsics are taken as exact."""
    rng = np.random.default_rng(scenario.seeds.calibration)
    cfg = scenario.cameras
    out: dict[str, CameraModel] = {}
    for cam_id in sorted(scenario.site.cameras):
        cam = scenario.site.cameras[cam_id]
        T_world_cam = cam.T_world_cam.copy()
        dR = rotation_from_rotvec(rng.normal(0.0, math.radians(cfg.calib_rotation_sigma_deg), 3))
        T_world_cam[:3, :3] = dR @ T_world_cam[:3, :3]
        T_world_cam[:3, 3] += rng.normal(0.0, cfg.calib_translation_sigma_m, 3)
        out[cam_id] = dataclasses.replace(cam, T_cam_world=invert_transform(T_world_cam))
    return out


@dataclasses.dataclass(frozen=True)
class Visibility:
    """Geometric visibility of the robot from one camera (no randomness).

    ``in_view``: (M,) keypoint in the image, in front of the camera and within range;
    ``occluded``: (M,) line of sight blocked by an obstacle; ``self_occluded``: (M,) keypoint on
    the far side of the robot's body; ``detectable``: enough unoccluded keypoints in view.
    """

    uv: np.ndarray
    in_view: np.ndarray
    occluded: np.ndarray
    self_occluded: np.ndarray
    distance_m: float
    detectable: bool


class DetectionSimulator:
    """Produces :class:`protocol.RobotDetections` for the cameras of a scenario."""

    def __init__(self, scenario: Scenario, world: World | None = None) -> None:
        self.scenario = scenario
        self.world = world or World(scenario)
        self.cameras = true_cameras(scenario)
        self.model = scenario.site.robot_model(scenario.robot_id)
        kps = self.model.keypoints_base_m
        self._kps_h = np.column_stack([kps, np.ones(len(kps))])
        # Outward horizontal normal of each keypoint on the (round) base, for self-occlusion.
        n = kps[:, :2].copy()
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        self._normals = np.where(norm > 1e-6, n / np.maximum(norm, 1e-9), 0.0)
        r, h = self.model.footprint_radius_m, self.model.height_m
        ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
        hull = [[r * math.cos(a), r * math.sin(a), z] for a in ang for z in (0.0, h)]
        self._hull_h = np.column_stack([np.array(hull), np.ones(len(hull))])
        clk = np.random.default_rng([scenario.seeds.calibration, 1])
        cfg = scenario.cameras
        #: true clock error left after the site's clock_offset_ns (ns), per camera
        self.clock_residual_ns: Mapping[str, int] = {
            c: round(clk.normal(0.0, cfg.clock_residual_ms) * 1e6) for c in self.cameras
        }

    # -- geometry ------------------------------------------------------------------------------

    def visibility(self, camera_id: str, pose: np.ndarray) -> Visibility:
        """Geometric visibility of the robot at planar ``pose`` from ``camera_id``."""
        cam = self.cameras[camera_id]
        cfg = self.scenario.cameras
        T = se3_from_planar(*pose)
        kps_w = (self._kps_h @ T.T)[:, :3]
        uv, depth = cam.project(kps_w)
        cam_pos = cam.position_world
        dist = float(np.hypot(pose[0] - cam_pos[0], pose[1] - cam_pos[1]))
        in_view = cam.in_image(uv) & (depth > 0.1) & (dist <= cfg.max_range_m)
        occluded = self.world.segments_blocked(cam_pos, kps_w)
        to_cam = cam_pos[:2] - kps_w[:, :2]
        to_cam /= np.maximum(np.linalg.norm(to_cam, axis=1, keepdims=True), 1e-9)
        R2 = T[:2, :2]
        normals_w = self._normals @ R2.T
        self_occ = np.sum(normals_w * to_cam, axis=1) < -0.05
        # Self-occluded keypoints still count: the detector sees the robot's body and infers
        # them from context (paper Sec. III-A); obstacles hide the robot itself.
        good = in_view & ~occluded
        detectable = bool(np.count_nonzero(good) >= cfg.min_visible_keypoints)
        return Visibility(uv, in_view, occluded, self_occ, dist, detectable)

    def cameras_seeing(self, pose: np.ndarray) -> tuple[str, ...]:
        """Ids of the cameras that can detect the robot at ``pose`` (geometry only)."""
        return tuple(c for c in sorted(self.cameras) if self.visibility(c, pose).detectable)

    # -- measurement ---------------------------------------------------------------------------

    def capture_stamp_ns(self, camera_id: str, true_capture_ns: int) -> int:
        """The stamp the camera puts on a frame captured at ``true_capture_ns`` (common clock):
        the receiver adds the site's ``clock_offset_ns`` to get back to the common clock, up to
        the residual clock error."""
        cam = self.scenario.site.cameras[camera_id]
        return int(true_capture_ns - cam.clock_offset_ns + self.clock_residual_ns[camera_id])

    def arrival_delay_ns(self, rng: np.random.Generator) -> int:
        """Capture → arrival delay: mean latency plus half-normal jitter (ns)."""
        cfg = self.scenario.cameras
        return round((cfg.latency_ms + abs(rng.normal(0.0, cfg.jitter_ms))) * 1e6)

    def detect(self, camera_id: str, true_capture_ns: int, pose: np.ndarray, seq: int,
               rng: np.random.Generator) -> RobotDetections:
        """The detections message of one frame of ``camera_id`` with the robot at true planar
        ``pose`` (x, y, theta) at ``true_capture_ns``."""
        cam = self.cameras[camera_id]
        stamp = self.capture_stamp_ns(camera_id, true_capture_ns)
        dets: tuple[Detection, ...] = ()
        vis = self.visibility(camera_id, pose)
        if vis.detectable and rng.random() >= self.scenario.cameras.miss_probability:
            dets = (self._noisy_detection(cam, vis, pose, rng),)
        return RobotDetections(
            camera_id=camera_id, stamp_ns=max(stamp, 0), seq=seq, image_width=cam.width,
            image_height=cam.height, model_id=MODEL_ID, detections=dets,
        )

    def _noisy_detection(self, cam: CameraModel, vis: Visibility, pose: np.ndarray,
                         rng: np.random.Generator) -> Detection:
        nz = self.scenario.noise
        m = len(vis.uv)
        uv = vis.uv.copy()
        valid = vis.in_view & np.all(np.isfinite(uv), axis=1)
        centroid = uv[valid].mean(axis=0)
        # correlated part: crop/bbox error of a top-down detector moves all keypoints together
        scale = 1.0 + rng.normal(0.0, nz.sigma_scale)
        shift = rng.normal(0.0, nz.sigma_shift_px, 2)
        sigma = np.where(vis.self_occluded | vis.occluded, nz.sigma_px * nz.self_occluded_factor,
                         nz.sigma_px)
        uv = centroid + scale * (uv - centroid) + shift + rng.normal(size=(m, 2)) * sigma[:, None]
        scores = np.where(vis.self_occluded, rng.uniform(0.4, 0.7, m), rng.uniform(0.75, 1.0, m))
        scores = np.where(vis.occluded, nz.obstacle_occluded_score * rng.uniform(0.5, 1.0, m),
                          scores)
        outlier = rng.random(m) < nz.outlier_probability
        if np.any(outlier):
            uv[outlier] += rng.uniform(-nz.outlier_max_px, nz.outlier_max_px,
                                       (int(outlier.sum()), 2))
        drop = (rng.random(m) < nz.dropout_probability) | ~valid
        scores = np.where(drop, 0.0, scores)
        # Dropped keypoints keep finite coordinates (the wire requires them); clamp to the image.
        uv = np.where(np.isfinite(uv), uv, centroid)
        uv[:, 0] = np.clip(uv[:, 0], 0.0, cam.width - 1.0)
        uv[:, 1] = np.clip(uv[:, 1], 0.0, cam.height - 1.0)
        hull_w = (self._hull_h @ se3_from_planar(*pose).T)[:, :3]
        huv, hdepth = cam.project(hull_w)
        huv = huv[np.all(np.isfinite(huv), axis=1) & (hdepth > 0.1)]
        box_pts = np.vstack([huv, uv[scores > 0]]) if len(huv) else uv[scores > 0]
        lo = np.clip(box_pts.min(axis=0) - 4.0, 0.0, [cam.width - 1.0, cam.height - 1.0])
        hi = np.clip(box_pts.max(axis=0) + 4.0, 0.0, [cam.width - 1.0, cam.height - 1.0])
        return Detection(
            bbox_xyxy=np.array([lo[0], lo[1], hi[0], hi[1]]),
            score=float(np.clip(rng.normal(0.9, 0.03), 0.0, 1.0)),
            keypoints_px=uv.astype(np.float64),
            keypoint_scores=scores.astype(np.float64),
            robot_id="",
        )
