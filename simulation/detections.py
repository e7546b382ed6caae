"""Simulated keypoint detections: what an edge camera's detector would report.

For a camera frame captured at a true time, the robot's keypoints are projected through the
camera's *true* pose (the site's calibrated pose perturbed by a fixed calibration error), tested
for visibility (image bounds, range, obstacles, the robot's own body) and corrupted by the
detector error model of :class:`simulation.scenario.NoiseConfig`. Stamps carry each camera's
clock error; arrival times add latency and jitter. Everything random comes from seeded numpy
Generators, so a seed reproduces a run exactly. A camera can be bumped during a run
(:class:`CameraBump`: from a given time on, its true pose is moved; the site file, and so
every service, still has the calibrated one).

The geometry of a frame (projections, visibility tests, the robot's projected hull) depends only
on the camera and the robot's pose, so :class:`DetectionSimulator` keeps it per camera, keyed by
the pose: :meth:`DetectionSimulator.prepare_frames` computes it for all frames of a run at once
(vectorized over frames and keypoints) and a static robot's frames share one entry. Neither
changes a number: the batched arithmetic is the per-frame arithmetic, element by element.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import ClassVar

import numpy as np

from core.camera import CameraModel
from core.geometry import invert_transform, rotation_from_rotvec, se3_from_planar
from protocol.messages import Detection, RobotDetections
from simulation.scenario import Scenario
from simulation.world import World

MODEL_ID = "sim-noise-v1"
#: frames per camera whose geometry :meth:`DetectionSimulator.prepare_frames` keeps (about
#: 1 kB each; 18 min at 15 Hz); later frames are computed when they come
MAX_PREPARED_FRAMES = 16_384
#: frames computed together (bounds the temporaries of a vectorized computation)
GEOMETRY_CHUNK = 1024


@dataclasses.dataclass(frozen=True)
class CameraBump:
    """A camera knocked out of place during a run: from ``at_ns`` (true capture time, common
    clock) on, the true pose of ``camera_id`` is rotated by ``rotation_deg`` (a rotation vector,
    degrees, world axes, about the optical centre) and its optical centre moved by
    ``translation_m`` (world axes, metres): R' = Exp(w) R, c' = c + t, the parametrization of
    :func:`backend_service.covariance.project_with_extrinsic_jacobian`."""

    camera_id: str
    at_ns: int
    translation_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("translation_m", "rotation_deg"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise ValueError(f"CameraBump.{name}: expected 3 finite numbers, got "
                                 f"{getattr(self, name)!r}")

    def apply(self, camera: CameraModel) -> CameraModel:
        """``camera`` with its pose moved by this bump."""
        T_world_cam = camera.T_world_cam.copy()
        dR = rotation_from_rotvec(np.radians(np.asarray(self.rotation_deg, np.float64)))
        T_world_cam[:3, :3] = dR @ T_world_cam[:3, :3]
        T_world_cam[:3, 3] += np.asarray(self.translation_m, np.float64)
        return dataclasses.replace(camera, T_cam_world=invert_transform(T_world_cam))


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


@dataclasses.dataclass(frozen=True)
class FrameRequest:
    """One camera frame to detect in (:meth:`DetectionSimulator.detect_many`): the camera, its
    true capture time (common clock, ns), the robot's true planar pose (x, y, theta; world
    frame, metres, radians), the frame's sequence number and the camera's random generator."""

    camera_id: str
    true_capture_ns: int
    pose: np.ndarray
    seq: int
    rng: np.random.Generator


@dataclasses.dataclass(frozen=True)
class FrameGeometry:
    """Everything about one frame that depends only on the camera and the robot's pose:
    ``visibility`` and ``hull_uv`` (H, 2), the pixels of the robot's bounding hull points in
    front of the camera (the detection's box). Arrays are read-only (shared between frames)."""

    visibility: Visibility
    hull_uv: np.ndarray


def _pose_key(pose: np.ndarray) -> bytes:
    """Cache key of a planar pose: its three float64 values, bit for bit."""
    return np.asarray(pose, dtype=np.float64).reshape(-1)[:3].tobytes()


def _readonly(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.setflags(write=False)


class DetectionSimulator:
    """Produces :class:`protocol.RobotDetections` for the cameras of a scenario.

    ``bumps``: cameras knocked out of place during the run (:class:`CameraBump`); a bumped
    camera's frames from the bump on are seen through its moved pose.
    """

    #: whether :meth:`detect_many` costs less than one :meth:`detect` per frame, so that a
    #: runner should hand it the cameras' frames of one capture together (not here)
    batches_frames: ClassVar[bool] = False

    def __init__(self, scenario: Scenario, world: World | None = None,
                 bumps: Sequence[CameraBump] = ()) -> None:
        self.scenario = scenario
        self.world = world or World(scenario)
        self.cameras = true_cameras(scenario)
        for bump in bumps:
            if bump.camera_id not in self.cameras:
                raise ValueError(f"CameraBump: unknown camera {bump.camera_id!r}; the site has "
                                 f"{sorted(self.cameras)}")
        #: per camera, its bumps in time order, each with the true camera after it
        self._bumps: dict[str, list[tuple[int, CameraModel]]] = {}
        for bump in sorted(bumps, key=lambda b: b.at_ns):
            chain = self._bumps.setdefault(bump.camera_id, [])
            before = chain[-1][1] if chain else self.cameras[bump.camera_id]
            chain.append((int(bump.at_ns), bump.apply(before)))
        #: per (camera, bump index): the last frame computed for the bumped camera
        self._last_bumped: dict[tuple[str, int], tuple[bytes, FrameGeometry]] = {}
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
        #: (3,) optical centre of each true camera, world frame, metres
        self._camera_position = {c: cam.position_world for c, cam in self.cameras.items()}
        #: per camera: pose key → the geometry of a frame of the run being prepared
        self._prepared: dict[str, dict[bytes, FrameGeometry]] = {c: {} for c in self.cameras}
        #: per camera: the last frame computed on demand (a static robot repeats it)
        self._last: dict[str, tuple[bytes, FrameGeometry]] = {}

    # -- geometry ------------------------------------------------------------------------------

    def visibility(self, camera_id: str, pose: np.ndarray) -> Visibility:
        """Geometric visibility of the robot at planar ``pose`` from ``camera_id``."""
        return self.frame_geometry(camera_id, pose).visibility

    def frame_geometry(self, camera_id: str, pose: np.ndarray) -> FrameGeometry:
        """The geometry of a frame of ``camera_id`` with the robot at planar ``pose`` (x, y,
        theta; world frame, metres, radians): prepared (:meth:`prepare_frames`), the last one
        computed for this camera when the pose is the same (a static robot), else computed
        now."""
        key = _pose_key(pose)
        geometry = self._prepared[camera_id].get(key)
        if geometry is not None:
            return geometry
        last = self._last.get(camera_id)
        if last is not None and last[0] == key:
            return last[1]
        geometry = self._compute_geometry(camera_id, np.asarray(pose, np.float64)[None, :3])[0]
        self._last[camera_id] = (key, geometry)
        return geometry

    def prepare_frames(self, camera_id: str, poses: np.ndarray) -> None:
        """Compute the geometry of the frames ``camera_id`` will capture with the robot at
        ``poses`` (N, 3) at once (vectorized over frames and keypoints; at most
        :data:`MAX_PREPARED_FRAMES` distinct poses); :meth:`detect` then looks it up. Replaces
        what was prepared for the camera before (one run at a time)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        first: dict[bytes, int] = {}  # distinct poses (a static robot repeats its pose)
        for i, p in enumerate(poses):
            first.setdefault(_pose_key(p), i)
            if len(first) >= MAX_PREPARED_FRAMES:
                break
        keys, rows = list(first), list(first.values())
        prepared: dict[bytes, FrameGeometry] = {}
        for k in range(0, len(rows), GEOMETRY_CHUNK):
            chunk = rows[k:k + GEOMETRY_CHUNK]
            prepared.update(zip(keys[k:k + GEOMETRY_CHUNK],
                                self._compute_geometry(camera_id, poses[chunk]), strict=True))
        self._prepared[camera_id] = prepared

    def true_camera(self, camera_id: str, true_capture_ns: int) -> tuple[int, CameraModel]:
        """The true camera at ``true_capture_ns`` and which bump made it (-1: none yet)."""
        idx, cam = -1, self.cameras[camera_id]
        for i, (at_ns, bumped) in enumerate(self._bumps.get(camera_id, ())):
            if true_capture_ns >= at_ns:
                idx, cam = i, bumped
        return idx, cam

    def _bumped_geometry(self, camera_id: str, bump: int, camera: CameraModel,
                         pose: np.ndarray) -> FrameGeometry:
        """Frame geometry through a bumped camera (computed per frame; a static robot repeats
        the last one)."""
        key = _pose_key(pose)
        last = self._last_bumped.get((camera_id, bump))
        if last is not None and last[0] == key:
            return last[1]
        geometry = self._compute_geometry(camera_id, np.asarray(pose, np.float64)[None, :3],
                                          camera)[0]
        self._last_bumped[(camera_id, bump)] = (key, geometry)
        return geometry

    def _compute_geometry(self, camera_id: str, poses: np.ndarray,
                          camera: CameraModel | None = None) -> list[FrameGeometry]:
        """:class:`FrameGeometry` of (N, 3) ``poses``: each frame's numbers are those of a
        one-frame call (the same operations per element; matrix products row by row).
        ``camera``: the true camera to see through (default: the unbumped one)."""
        cam = self.cameras[camera_id] if camera is None else camera
        cfg = self.scenario.cameras
        n, m = len(poses), len(self._kps_h)
        # (N, 4, 4) T_world_robot per frame
        T = np.stack([se3_from_planar(*p) for p in poses])
        kps_w = (self._kps_h @ T.transpose(0, 2, 1))[:, :, :3]  # (N, M, 3)
        hull_w = (self._hull_h @ T.transpose(0, 2, 1))[:, :, :3]  # (N, H, 3)
        uv, depth = cam.project(kps_w.reshape(-1, 3))
        uv, depth = uv.reshape(n, m, 2), depth.reshape(n, m)
        cam_pos = self._camera_position[camera_id] if camera is None else cam.position_world
        dist = np.hypot(poses[:, 0] - cam_pos[0], poses[:, 1] - cam_pos[1])
        in_view = (cam.in_image(uv.reshape(-1, 2)).reshape(n, m) & (depth > 0.1)
                   & (dist <= cfg.max_range_m)[:, None])
        occluded = self.world.segments_blocked(cam_pos, kps_w.reshape(-1, 3)).reshape(n, m)
        to_cam = cam_pos[:2] - kps_w[:, :, :2]
        to_cam /= np.maximum(np.linalg.norm(to_cam, axis=2, keepdims=True), 1e-9)
        normals_w = self._normals @ T[:, :2, :2].transpose(0, 2, 1)  # (N, M, 2)
        self_occ = np.sum(normals_w * to_cam, axis=2) < -0.05
        # Self-occluded keypoints still count: the detector sees the robot's body and infers
        # them from context (paper Sec. III-A); obstacles hide the robot itself.
        good = in_view & ~occluded
        detectable = np.count_nonzero(good, axis=1) >= cfg.min_visible_keypoints
        huv, hdepth = cam.project(hull_w.reshape(-1, 3))
        h = hull_w.shape[1]
        huv, hdepth = huv.reshape(n, h, 2), hdepth.reshape(n, h)
        hull_ok = np.all(np.isfinite(huv), axis=2) & (hdepth > 0.1)
        _readonly(uv, in_view, occluded, self_occ)
        out = []
        for i in range(n):
            hull_uv = huv[i][hull_ok[i]]
            _readonly(hull_uv)
            vis = Visibility(uv[i], in_view[i], occluded[i], self_occ[i], float(dist[i]),
                             bool(detectable[i]))
            out.append(FrameGeometry(vis, hull_uv))
        return out

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
        bump, cam = self.true_camera(camera_id, true_capture_ns)
        stamp = self.capture_stamp_ns(camera_id, true_capture_ns)
        dets: tuple[Detection, ...] = ()
        geometry = (self.frame_geometry(camera_id, pose) if bump < 0
                    else self._bumped_geometry(camera_id, bump, cam, pose))
        if (geometry.visibility.detectable
                and rng.random() >= self.scenario.cameras.miss_probability):
            dets = (self._noisy_detection(cam, geometry, rng),)
        return RobotDetections(
            camera_id=camera_id, stamp_ns=max(stamp, 0), seq=seq, image_width=cam.width,
            image_height=cam.height, model_id=MODEL_ID, detections=dets,
        )

    def detect_many(self, frames: Sequence[FrameRequest]) -> list[RobotDetections]:
        """:meth:`detect` of each frame, in order (each frame draws from its own ``rng``)."""
        return [self.detect(f.camera_id, f.true_capture_ns, f.pose, f.seq, f.rng)
                for f in frames]

    def _noisy_detection(self, cam: CameraModel, geometry: FrameGeometry,
                         rng: np.random.Generator) -> Detection:
        nz = self.scenario.noise
        vis = geometry.visibility
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
        max_px = np.array([cam.width - 1.0, cam.height - 1.0])
        uv = np.minimum(np.maximum(uv, 0.0), max_px)
        huv = geometry.hull_uv
        box_pts = np.vstack([huv, uv[scores > 0]]) if len(huv) else uv[scores > 0]
        lo = np.minimum(np.maximum(box_pts.min(axis=0) - 4.0, 0.0), max_px)
        hi = np.minimum(np.maximum(box_pts.max(axis=0) + 4.0, 0.0), max_px)
        return Detection(
            bbox_xyxy=np.array([lo[0], lo[1], hi[0], hi[1]]),
            score=min(max(float(rng.normal(0.9, 0.03)), 0.0), 1.0),
            keypoints_px=uv.astype(np.float64),
            keypoint_scores=scores.astype(np.float64),
            robot_id="",
        )
