"""Live state in the Rerun viewer: the only module that imports ``rerun``.

Entity layout (world frame = site world frame, z up):

- ``world/site/floor_plan`` (room outline and floor), ``world/site/obstacles`` (boxes): the
  static scene when one is known (:class:`StaticScene`; the simulation provides it)
- ``world/cameras/<camera_id>``: camera pose (Transform3D) and ``.../image`` Pinhole (frustum);
  ``.../image/bounds`` the image rectangle; per frame ``.../image/detections`` (boxes),
  ``.../image/keypoints`` (2D keypoints) and ``.../image/reprojection`` (the robot model at the
  camera-only estimate projected back into this camera: what a person checks by eye);
  ``.../image`` also gets the camera's JPEG preview when its edge agent sends one. A saved
  recording stores previews re-encoded smaller (:data:`IMAGE_POLICY`: half size, JPEG 40):
  its camera views, and the pixel coordinates of everything drawn on them, are then at that
  scale (the 3D frustums are unchanged); with it the demo's recording is ~4 MB per minute
  (was ~19 MB with the previews stored as sent)
- ``world/map/voxels/<tile>``: the semantic map (voxel centres, coloured by class through the
  ``world/map`` legend) in :data:`MAP_TILE_M` tiles; a drawing logs only the tiles whose
  voxels changed since the last one
- ``world/robots/<robot_id>/{camera,fused,localization,odometry,ground_truth}``: poses
  (Transform3D + heading arrow); ``.../camera_keypoints`` the 3D keypoints of the model at the
  camera-only estimate; ``.../covariance/{camera,fused}`` 2-sigma position ellipses;
  ``.../corrections`` markers where corrections were pushed (kept for the whole run)
- ``world/trajectories/<robot_id>/<kind>``: trails, logged incrementally (one segment per new
  point; the blueprint shows each trail's whole history up to the time cursor)
- ``metrics/<robot_id>/error_cm/<kind>`` (one plot), ``metrics/<robot_id>/reprojection_rmse_px``,
  ``metrics/latency_ms/<stage>``: series
- ``status/<service>/<id>``: text log of service status

A blueprint (:func:`blueprint`) goes with every recording and live view: a large 3D view, a row
of camera views, one error plot with every source, latency and reprojection plots, the status
log. Rows are batched into large chunks (:data:`BATCHING_S`), so recordings stay compact.

Time: timeline ``stamp`` (sensor time of each message), so a replay shows what happened when.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from core.geometry import (
    rotation_z,
    yaw_from_rotation,
    yaw_to_quaternion,
)
from core.site import Site
from protocol.errors import UsageError
from protocol.messages import (
    CameraImage,
    Odometry,
    PoseEstimate,
    RobotDetections,
    SemanticCloud,
    ServiceStatus,
)
from protocol.semantic_classes import SEMANTIC_CLASS_COLORS, SEMANTIC_CLASSES

log = logging.getLogger(__name__)

TIMELINE: Final = "stamp"
#: a trail gets a new point once the robot moved this far from the last one
TRAIL_SPACING_M: Final = 0.02
#: covariance ellipses are drawn at most this often per robot and source
ELLIPSE_PERIOD_NS: Final = 500_000_000
#: the ellipse's scale: 2 sigma (86 % of the planar mass)
ELLIPSE_SIGMA: Final = 2.0
#: The semantic map is drawn at most this often; each drawing logs only the tiles that changed
#: (a whole map is ~1.4 MB per 100k voxels in a recording).
MAP_PERIOD_NS: Final = 30_000_000_000
#: side of the square map tiles (world x/y, metres): the unit of change of the drawn map
MAP_TILE_M: Final = 1.0
#: how long rows wait to be batched into one chunk: a saved recording is read after the run,
#: so large chunks (few, compact) win; a live view wants a short delay
BATCHING_S: Final = {"save": 5.0, "live": 0.5}


@dataclasses.dataclass(frozen=True)
class ImagePolicy:
    """How camera previews are stored: ``scale`` of the image sides (the camera view's pixel
    space scales with it), a ``blur_px`` Gaussian kernel before encoding (0: none; the sensor
    noise of a frame is what costs JPEG bytes) and the JPEG ``quality``. ``scale`` 1 and
    ``quality`` ``None``: the preview is logged as the edge agent sent it."""

    scale: float = 1.0
    quality: int | None = None
    blur_px: int = 0

    @property
    def passthrough(self) -> bool:
        return self.scale == 1.0 and self.quality is None and self.blur_px == 0


#: previews in a saved recording: measured on the demo's 848x480 frames, 74 kB as sent,
#: ~10 kB at half size, 3x3 blur, JPEG 40 (4 cameras at 1 Hz: ~2.4 MB per minute, of a budget
#: of 5 MB per minute for the whole recording); a live view shows them as sent
IMAGE_POLICY: Final = {"save": ImagePolicy(0.5, 40, 3), "live": ImagePolicy()}
KINDS: Final = ("camera", "fused", "localization", "odometry", "ground_truth")
COLORS: Final = {
    "camera": (230, 120, 20),
    "fused": (30, 160, 230),
    "localization": (150, 60, 220),
    "odometry": (150, 150, 150),
    "ground_truth": (40, 200, 60),
    "correction": (220, 40, 200),
    "floor": (70, 70, 80),
    "wall": (200, 200, 210),
    "obstacle": (160, 120, 90),
}
NAMES: Final = {
    "camera": "cameras (one frame-set)",
    "fused": "fused (pose graph)",
    "localization": "robot's own localization",
    "odometry": "odometry",
    "ground_truth": "ground truth",
}


@dataclasses.dataclass(frozen=True)
class ObstacleBox:
    """A box standing in the room: ``center_m`` (3,) and ``size_m`` (3,) in the world frame,
    ``yaw_rad`` about world z."""

    name: str
    center_m: tuple[float, float, float]
    size_m: tuple[float, float, float]
    yaw_rad: float = 0.0


@dataclasses.dataclass(frozen=True)
class StaticScene:
    """What stands still in the room: its outline (``room_min_xy_m``, ``room_max_xy_m``,
    ``room_height_m``; world frame, metres) and obstacles. The simulation's scenario provides
    one; a site without one is drawn without a floor plan."""

    room_min_xy_m: tuple[float, float]
    room_max_xy_m: tuple[float, float]
    room_height_m: float
    obstacles: tuple[ObstacleBox, ...] = ()


@dataclasses.dataclass(frozen=True)
class RerunTarget:
    """Where the recording goes: ``save:PATH.rrd``, ``spawn``, ``connect:URL``, ``serve``,
    or ``none``."""

    kind: str
    arg: str = ""

    @classmethod
    def parse(cls, spec: str) -> RerunTarget:
        kind, _, arg = spec.partition(":")
        if kind == "save":
            if not arg:
                raise UsageError("--rerun save:PATH.rrd needs a path")
            return cls("save", arg)
        if kind == "connect":
            return cls("connect", arg)
        if kind in ("spawn", "serve", "none") and not arg:
            return cls(kind)
        raise UsageError(
            f"--rerun {spec!r}: expected save:PATH.rrd, spawn, connect[:URL], serve or none"
        )


def trail_path(robot_id: str, kind: str) -> str:
    return f"world/trajectories/{robot_id}/{kind}"


def _eye(site: Site, scene: StaticScene | None) -> rrb.EyeControls3D:
    """A view from the south, above the room, at the room's centre (the cameras' when no
    scene is known)."""
    if scene is not None:
        lo, hi = np.array(scene.room_min_xy_m), np.array(scene.room_max_xy_m)
    else:
        xy = np.array([c.T_world_cam[:2, 3] for c in site.cameras.values()] or [[0.0, 0.0]])
        lo, hi = xy.min(axis=0) - 1.0, xy.max(axis=0) + 1.0
    centre = 0.5 * (lo + hi)
    span = float(max(hi - lo))
    return rrb.EyeControls3D(position=[centre[0], lo[1] - 0.55 * span, 0.75 * span],
                             look_target=[centre[0], centre[1], 0.0], eye_up=[0.0, 0.0, 1.0])


def blueprint(site: Site, scene: StaticScene | None = None) -> rrb.Blueprint:
    """The layout every recording and live view gets: the 3D site view (large, with every
    trail and correction kept up to the time cursor), the camera views in a row, one plot of
    every source's error, latency and reprojection plots, the status log."""
    whole_run = rrb.VisibleTimeRanges([rrb.VisibleTimeRange(
        TIMELINE, start=rrb.TimeRangeBoundary.infinite(),
        end=rrb.TimeRangeBoundary.cursor_relative())])
    keep: dict[str, Any] = {}
    for robot_id in site.robots:
        for kind in KINDS:
            keep[trail_path(robot_id, kind)] = whole_run
        keep[f"world/robots/{robot_id}/corrections"] = whole_run
    world = rrb.Spatial3DView(origin="world", name="site", overrides=keep,
                              eye_controls=_eye(site, scene))
    cameras = [rrb.Spatial2DView(origin=f"world/cameras/{c}/image", name=c)
               for c in site.cameras]
    robots = list(site.robots)
    errors = [rrb.TimeSeriesView(origin=f"metrics/{r}/error_cm", name=f"{r}: error (cm)")
              for r in robots]
    plots = rrb.Vertical(
        *errors,
        rrb.TimeSeriesView(origin="metrics/latency_ms", name="latency (ms)"),
        *(rrb.TimeSeriesView(origin=f"metrics/{r}/reprojection_rmse_px",
                             name=f"{r}: reprojection RMS (px)") for r in robots),
        rrb.TextLogView(origin="status", name="service status"),
        row_shares=[3] * len(errors) + [2] + [2] * len(robots) + [2],
    )
    top = rrb.Horizontal(world, plots, column_shares=[3, 2])
    rows: list[Any] = [top]
    if cameras:
        rows.append(rrb.Horizontal(*cameras))
    return rrb.Blueprint(rrb.Vertical(*rows, row_shares=[3, 1.4][:len(rows)]),
                         collapse_panels=True)


def covariance_ellipse(x: float, y: float, covariance: np.ndarray, sigma: float = ELLIPSE_SIGMA,
                       points: int = 33) -> np.ndarray | None:
    """(points, 3) closed ring at z = 0.02 m: the ``sigma`` ellipse of the (x, y) block of a 3x3
    (x, y, theta) ``covariance`` (world frame, m^2) around (x, y); ``None`` when the block is
    not a finite positive semi-definite matrix."""
    cov = np.asarray(covariance, np.float64)
    if cov.shape != (3, 3) or not np.all(np.isfinite(cov[:2, :2])):
        return None
    vals, vecs = np.linalg.eigh(0.5 * (cov[:2, :2] + cov[:2, :2].T))
    if vals[0] < 0:
        return None
    a = np.linspace(0.0, 2 * math.pi, points)
    circle = np.stack([np.cos(a), np.sin(a)], 1) * (sigma * np.sqrt(vals))
    ring = circle @ vecs.T + [x, y]
    return np.column_stack([ring, np.full(points, 0.02)])


def robot_body(model: Any) -> Any:
    """The Rerun archetype of a robot model's body in its base frame: a cylinder of the
    footprint radius and height for a round base (its keypoints' floor distances from the
    centre within 10 % of the radius, the HSR), else the box its keypoints span, from the
    floor to the top keypoint (a box base)."""
    kp = np.asarray(model.keypoints_base_m, np.float64).reshape(-1, 3)
    color = [(*COLORS["fused"], 90)]
    radii = np.hypot(kp[:, 0], kp[:, 1])
    if np.ptp(radii) < 0.1 * model.footprint_radius_m:
        return rr.Cylinders3D(lengths=[model.height_m], radii=[model.footprint_radius_m],
                              centers=[[0.0, 0.0, model.height_m / 2]], colors=color)
    lo, hi = kp.min(axis=0), kp.max(axis=0)
    top = float(hi[2])
    return rr.Boxes3D(centers=[[(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, top / 2]],
                      half_sizes=[[(hi[0] - lo[0]) / 2, (hi[1] - lo[1]) / 2, top / 2]],
                      colors=color)


class RerunView:
    """Logs site, detections, poses, trajectories and metrics to one Rerun recording.

    All methods are cheap and never raise into the caller: a viewer problem must not stop the
    backend (errors are logged once per kind)."""

    def __init__(self, site: Site, target: RerunTarget, app_id: str = "smartedge", *,
                 scene: StaticScene | None = None, images: ImagePolicy | None = None) -> None:
        self.site = site
        self.target = target
        self.scene = scene
        mode = "save" if target.kind == "save" else "live"
        self.images = images or IMAGE_POLICY[mode]
        if not 0.0 < self.images.scale <= 1.0:
            raise UsageError(f"image scale {self.images.scale}: must be in (0, 1]")
        #: camera id -> (width, height) of the stored images (the camera views' pixel space)
        self._image_size = {c.camera_id: (max(1, round(c.width * self.images.scale)),
                                          max(1, round(c.height * self.images.scale)))
                            for c in site.cameras.values()}
        self._map_tiles: dict[str, bytes] = {}
        #: what was not drawn and why (bad input never disappears silently)
        self.counters: dict[str, int] = {}
        batching = BATCHING_S[mode]
        self.rec = rr.RecordingStream(app_id, batcher_config=rr.ChunkBatcherConfig(
            flush_tick=batching, flush_num_bytes=8 << 20))
        self._trail_last: dict[tuple[str, str], tuple[float, float]] = {}
        self._ellipse_ns: dict[tuple[str, str], int] = {}
        self._reprojected: dict[str, bool] = {}
        self._failed: set[str] = set()
        self._styled: set[str] = set()
        self._map_drawn_ns: int | None = None
        self.url: str | None = None
        if target.kind == "save":
            Path(target.arg).parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(target.arg)
        elif target.kind == "spawn":
            self.rec.spawn()
        elif target.kind == "connect":
            self.rec.connect_grpc(target.arg or None)
        elif target.kind == "serve":
            self.url = self.rec.serve_grpc()
            rr.serve_web_viewer(connect_to=self.url, open_browser=False)
            log.info("rerun: gRPC at %s, web viewer on http://localhost:9090", self.url)
        if target.kind != "none":
            self.rec.send_blueprint(blueprint(site, scene))
        self._log_static()

    # ---------------------------------------------------------------------------------------

    def _guard(self, what: str, fn: Any, *args: Any) -> None:
        try:
            fn(*args)
        except Exception:
            if what not in self._failed:
                self._failed.add(what)
                log.exception("rerun logging of %s failed (further failures not reported)", what)

    def _time(self, stamp_ns: int) -> None:
        self.rec.set_time(TIMELINE, timestamp=np.datetime64(int(stamp_ns), "ns"))

    def _log_static(self) -> None:
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._log_legend()
        if self.scene is not None:
            self._log_scene(self.scene)
        for cam in self.site.cameras.values():
            T = cam.T_world_cam
            base = f"world/cameras/{cam.camera_id}"
            rec.log(base, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
            px = self.images.scale
            width, height = self._image_size[cam.camera_id]
            rec.log(
                f"{base}/image",
                rr.Pinhole(
                    image_from_camera=np.diag([px, px, 1.0]) @ cam.K,
                    resolution=[width, height],
                    camera_xyz=rr.ViewCoordinates.RDF,
                    image_plane_distance=0.5,
                ),
                static=True,
            )
            rec.log(f"{base}/image/bounds",
                    rr.Boxes2D(mins=[[0.0, 0.0]], sizes=[[width, height]],
                               colors=[(120, 120, 120)], labels=[cam.camera_id],
                               show_labels=False),
                    static=True)
        for robot_id in self.site.robots:
            model = self.site.robot_model(robot_id)
            names = list(model.keypoint_names)
            rec.log(
                f"world/robots/{robot_id}",
                rr.AnnotationContext(
                    [
                        rr.ClassDescription(
                            info=rr.AnnotationInfo(id=0, label=robot_id),
                            keypoint_annotations=[
                                rr.AnnotationInfo(id=i, label=n) for i, n in enumerate(names)
                            ],
                        )
                    ]
                ),
                static=True,
            )
            # the robot body rides on the fused pose: a round base (keypoints on a circle) as
            # a cylinder of the footprint, any other (a box base) as its keypoints' box
            rec.log(f"world/robots/{robot_id}/fused/body", robot_body(model), static=True)
            rec.log(
                f"world/robots/{robot_id}/fused/keypoints",
                rr.Points3D(
                    model.keypoints_base_m,
                    keypoint_ids=np.arange(model.num_keypoints),
                    class_ids=0,
                    radii=0.01,
                    show_labels=False,
                ),
                static=True,
            )
            for kind in KINDS:
                rec.log(trail_path(robot_id, kind),
                        rr.LineStrips3D.from_fields(colors=[COLORS[kind]], radii=[0.02]),
                        static=True)

    def _log_legend(self) -> None:
        """The semantic classes' names and colours, for the map's points (shown in the
        selection panel and on hover)."""
        self.rec.log("world/map", rr.AnnotationContext([
            rr.AnnotationInfo(id=i, label=name, color=tuple(int(c) for c in color))
            for i, (name, color) in enumerate(zip(SEMANTIC_CLASSES, SEMANTIC_CLASS_COLORS,
                                                  strict=True))]), static=True)

    def semantic_map(self, msg: SemanticCloud, voxel_size_m: float = 0.05) -> None:
        """The mapper's semantic voxels (world frame), coloured by class; drawn at most every
        :data:`MAP_PERIOD_NS` of message time, each drawing replacing the last."""
        if (self._map_drawn_ns is not None
                and msg.stamp_ns - self._map_drawn_ns < MAP_PERIOD_NS):
            return
        self._map_drawn_ns = msg.stamp_ns
        self._guard("semantic map", self._semantic_map, msg, voxel_size_m)

    def _semantic_map(self, msg: SemanticCloud, voxel_size_m: float) -> None:
        """Logs the tiles whose voxels changed since the last drawing and clears the tiles
        that became empty."""
        self._time(msg.stamp_ns)
        tiles = map_tiles(np.asarray(msg.points_xyz, np.float32),
                          np.asarray(msg.class_ids).astype(np.uint16), voxel_size_m)
        for name, (points, class_ids) in tiles.items():
            digest = hashlib.blake2b(points.tobytes() + class_ids.tobytes(),
                                     digest_size=16).digest()
            if self._map_tiles.get(name) == digest:
                continue
            self._map_tiles[name] = digest
            self.rec.log(f"world/map/voxels/{name}", rr.Points3D(
                points, class_ids=class_ids, radii=0.5 * voxel_size_m))
        for name in [n for n in self._map_tiles if n not in tiles]:
            del self._map_tiles[name]
            self.rec.log(f"world/map/voxels/{name}", rr.Clear(recursive=False))

    def _log_scene(self, scene: StaticScene) -> None:
        (x0, y0), (x1, y1) = scene.room_min_xy_m, scene.room_max_xy_m
        h = scene.room_height_m
        corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]], np.float64)
        self.rec.log("world/site/floor_plan", rr.LineStrips3D(
            [np.column_stack([corners, np.zeros(5)]), np.column_stack([corners, np.full(5, h)]),
             *(np.array([[x, y, 0.0], [x, y, h]]) for x, y in corners[:4])],
            colors=[COLORS["wall"]], radii=0.01), static=True)
        self.rec.log("world/site/floor", rr.Boxes3D(
            mins=[[x0, y0, -0.02]], sizes=[[x1 - x0, y1 - y0, 0.02]],
            colors=[(*COLORS["floor"], 255)], fill_mode="solid"), static=True)
        if scene.obstacles:
            self.rec.log("world/site/obstacles", rr.Boxes3D(
                centers=[b.center_m for b in scene.obstacles],
                half_sizes=[[0.5 * v for v in b.size_m] for b in scene.obstacles],
                quaternions=[yaw_to_quaternion(b.yaw_rad) for b in scene.obstacles],
                colors=[(*COLORS["obstacle"], 200)], labels=[b.name for b in scene.obstacles],
                fill_mode="solid", show_labels=False), static=True)

    # ---------------------------------------------------------------------------------------

    def detections(self, msg: RobotDetections) -> None:
        self._guard("detections", self._detections, msg)

    def _detections(self, msg: RobotDetections) -> None:
        self._time(msg.stamp_ns)
        base = f"world/cameras/{msg.camera_id}/image"
        boxes = [d.bbox_xyxy for d in msg.detections]
        px = self.images.scale
        if boxes:
            arr = px * np.asarray(boxes, np.float64)
            self.rec.log(
                f"{base}/detections",
                rr.Boxes2D(
                    array=arr,
                    array_format=rr.Box2DFormat.XYXY,
                    labels=[f"{d.score:.2f}" for d in msg.detections],
                ),
            )
            pts = px * np.concatenate([d.keypoints_px for d in msg.detections])
            scores = np.concatenate([d.keypoint_scores for d in msg.detections])
            kp_ids = np.concatenate([np.arange(len(d.keypoints_px)) for d in msg.detections])
            colors = np.stack([255 * (1 - scores), 255 * scores, np.zeros_like(scores)], 1)
            self.rec.log(
                f"{base}/keypoints",
                rr.Points2D(pts, keypoint_ids=kp_ids, colors=colors.astype(np.uint8),
                            radii=max(1.0, 3.0 * px),
                            show_labels=False),
            )
        else:
            self.rec.log(f"{base}/detections", rr.Clear(recursive=False))
            self.rec.log(f"{base}/keypoints", rr.Clear(recursive=False))

    def image(self, msg: CameraImage) -> None:
        """A camera's preview frame (JPEG; Rerun decodes it), re-encoded by the
        :class:`ImagePolicy` first. A preview that does not decode is counted
        (``image_errors``) and logged once per camera; one of an unknown camera is counted
        (``image_unknown_camera``)."""
        self._guard("image", self._image, msg)

    def _count(self, what: str) -> None:
        self.counters[what] = self.counters.get(what, 0) + 1

    def _image(self, msg: CameraImage) -> None:
        if msg.camera_id not in self.site.cameras:
            self._count("image_unknown_camera")
            return
        data = msg.data.tobytes()
        if not self.images.passthrough:
            try:
                data = reencode_jpeg(data, self._image_size[msg.camera_id], self.images)
            except ValueError as exc:
                self._count("image_errors")
                if f"image.{msg.camera_id}" not in self._failed:
                    self._failed.add(f"image.{msg.camera_id}")
                    log.warning("camera %s: preview not drawn (further ones not reported): %s",
                                msg.camera_id, exc)
                return
        self._time(msg.stamp_ns)
        self.rec.log(f"world/cameras/{msg.camera_id}/image",
                     rr.EncodedImage(contents=data, media_type="image/jpeg"))
        self._count("images")

    def pose(self, est: PoseEstimate, kind: str | None = None) -> None:
        """A camera-only (``kind='camera'``) or fused (``'fused'``) estimate."""
        self._guard(f"pose.{kind or est.source}", self._pose, est, kind)

    def _pose(self, est: PoseEstimate, kind: str | None) -> None:
        kind = kind or ("camera" if est.source == "cameras" else "fused")
        self._time(est.stamp_ns)
        self._pose_entity(est.robot_id, kind, est.x, est.y, est.theta)
        self._ellipse(est, kind)
        if kind == "camera":
            model = self.site.robot_model(est.robot_id)
            pts = model.keypoints_base_m @ rotation_z(est.theta).T + [est.x, est.y, 0.0]
            self.rec.log(
                f"world/robots/{est.robot_id}/camera_keypoints",
                rr.Points3D(pts, keypoint_ids=np.arange(len(pts)), class_ids=0, radii=0.015,
                            show_labels=False),
            )
            self._reproject(pts)
            if math.isfinite(est.reprojection_rmse_px):
                self.rec.log(
                    f"metrics/{est.robot_id}/reprojection_rmse_px",
                    rr.Scalars([est.reprojection_rmse_px]),
                )

    def _ellipse(self, est: PoseEstimate, kind: str) -> None:
        key = (est.robot_id, kind)
        if est.stamp_ns - self._ellipse_ns.get(key, -ELLIPSE_PERIOD_NS) < ELLIPSE_PERIOD_NS:
            return
        ring = covariance_ellipse(est.x, est.y, est.covariance)
        if ring is None:
            return
        self._ellipse_ns[key] = est.stamp_ns
        self.rec.log(f"world/robots/{est.robot_id}/covariance/{kind}",
                     rr.LineStrips3D([ring], colors=[COLORS.get(kind, (255, 255, 255))],
                                     radii=0.006))

    def _reproject(self, points_world: np.ndarray) -> None:
        """The model keypoints at the camera-only estimate, projected into every camera that
        sees them (cleared in the others)."""
        px = self.images.scale
        for cam in self.site.cameras.values():
            uv, depth = cam.project(points_world)
            ok = (depth > 0) & cam.in_image(uv)
            path = f"world/cameras/{cam.camera_id}/image/reprojection"
            if ok.any():
                self.rec.log(path, rr.Points2D(px * uv[ok], keypoint_ids=np.flatnonzero(ok),
                                               colors=[COLORS["camera"]],
                                               radii=max(1.0, 4.0 * px), show_labels=False))
                self._reprojected[cam.camera_id] = True
            elif self._reprojected.get(cam.camera_id):
                self.rec.log(path, rr.Clear(recursive=False))
                self._reprojected[cam.camera_id] = False

    def odometry_pose(
        self, robot_id: str, stamp_ns: int, x: float, y: float, theta: float, kind: str = "odometry"
    ) -> None:
        """A pose from the robot itself (``odometry`` or its own localization) or ground truth
        (``ground_truth``), already in the world frame."""

        def fn() -> None:
            self._time(stamp_ns)
            self._pose_entity(robot_id, kind, x, y, theta)

        self._guard(f"pose.{kind}", fn)

    def _pose_entity(self, robot_id: str, kind: str, x: float, y: float, theta: float) -> None:
        self.rec.log(
            f"world/robots/{robot_id}/{kind}",
            rr.Transform3D(translation=[x, y, 0.0], quaternion=list(yaw_to_quaternion(theta))),
        )
        if (robot_id, kind) not in self._trail_last:  # the marker rides on the transform
            self.rec.log(
                f"world/robots/{robot_id}/{kind}/marker",
                rr.Arrows3D(origins=[[0, 0, 0.02]], vectors=[[0.3, 0, 0]],
                            colors=[COLORS.get(kind, (255, 255, 255))]),
                static=True,
            )
        self._trail(robot_id, kind, x, y)

    def _trail(self, robot_id: str, kind: str, x: float, y: float) -> None:
        """One new segment from the trail's last point: the trail is never logged whole."""
        last = self._trail_last.get((robot_id, kind))
        if last is not None and math.hypot(last[0] - x, last[1] - y) < TRAIL_SPACING_M:
            return
        self._trail_last[(robot_id, kind)] = (x, y)
        if last is None:
            return
        self.rec.log(trail_path(robot_id, kind),
                     rr.LineStrips3D([[[last[0], last[1], 0.01], [x, y, 0.01]]]))

    def odometry(self, msg: Odometry, T_world_odom: np.ndarray | None = None) -> None:
        """Odometry drawn in the world frame through ``T_world_odom`` (3x3 SE(2)) if known."""
        if T_world_odom is None:
            return
        p = T_world_odom @ np.array([msg.x, msg.y, 1.0])
        theta = msg.theta + yaw_from_rotation(T_world_odom)
        self.odometry_pose(msg.robot_id, msg.stamp_ns, float(p[0]), float(p[1]), theta)

    def error(self, robot_id: str, stamp_ns: int, kind: str, error_m: float) -> None:
        def fn() -> None:
            path = f"metrics/{robot_id}/error_cm/{kind}"
            if path not in self._styled:  # the series style goes on the series' own path
                self._styled.add(path)
                self.rec.log(path, rr.SeriesLines(colors=[COLORS.get(kind, (255, 255, 255))],
                                                  names=[NAMES.get(kind, kind)]), static=True)
            self._time(stamp_ns)
            self.rec.log(path, rr.Scalars([100.0 * error_m]))

        self._guard(f"error.{kind}", fn)

    def latency(self, stamp_ns: int, stage: str, latency_s: float) -> None:
        def fn() -> None:
            self._time(stamp_ns)
            self.rec.log(f"metrics/latency_ms/{stage}", rr.Scalars([1e3 * latency_s]))

        self._guard(f"latency.{stage}", fn)

    def correction(self, robot_id: str, stamp_ns: int, x: float, y: float, theta: float) -> None:
        def fn() -> None:
            self._time(stamp_ns)
            self.rec.log(
                f"world/robots/{robot_id}/corrections",
                rr.Arrows3D(origins=[[x, y, 0.05]],
                            vectors=[[0.35 * math.cos(theta), 0.35 * math.sin(theta), 0.0]],
                            colors=[COLORS["correction"]], radii=0.02),
            )

        self._guard("correction", fn)

    def status(self, msg: ServiceStatus) -> None:
        def fn() -> None:
            self._time(msg.stamp_ns)
            counters = ", ".join(f"{k}={v}" for k, v in sorted(msg.counters.items()))
            level = {"ok": "INFO", "degraded": "WARN", "error": "ERROR"}.get(msg.state, "INFO")
            self.rec.log(
                f"status/{msg.service}/{msg.instance_id}",
                rr.TextLog(f"{msg.state} {msg.detail} {counters}".strip(), level=level),
            )

        self._guard("status", fn)

    def close(self) -> None:
        try:
            self.rec.flush()
            if self.target.kind == "save":
                self.rec.disconnect()
        except Exception:
            log.exception("closing the rerun recording failed")
            return
        if self.target.kind == "save":
            compact_recording(Path(self.target.arg))


def reencode_jpeg(data: bytes, size: tuple[int, int], policy: ImagePolicy) -> bytes:
    """A JPEG ``data`` decoded, resized to ``size`` (width, height; area averaging), blurred
    and encoded again by ``policy``. Raises ``ValueError`` when it does not decode or encode."""
    import cv2

    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError(f"a {len(data)}-byte preview is not a decodable JPEG")
    if (image.shape[1], image.shape[0]) != size:
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    if policy.blur_px > 1:
        k = policy.blur_px | 1  # an odd kernel
        image = cv2.GaussianBlur(image, (k, k), 0)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY,
                                           int(policy.quality if policy.quality else 90)])
    if not ok:
        raise ValueError(f"JPEG encoding of a {image.shape} preview failed")
    return buf.tobytes()


def map_tiles(points_xyz: np.ndarray, class_ids: np.ndarray, voxel_size_m: float,
              tile_m: float = MAP_TILE_M) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Map voxels (world frame) split into ``tile_m`` squares of the x/y plane: tile name
    (``x<i>_y<j>``) -> (points (N, 3) float32, class ids (N,) uint16). Each point is drawn at
    the centre of the voxel its mean lies in (the mapper's grid: voxel ``i`` covers
    ``[i, i + 1) * voxel_size_m``), in voxel-index order: an unchanged tile gives the same
    bytes whatever order the mapper sent, and grid values compress to about half in a saved
    recording (measured on the demo's map: 1.7 MB instead of 3.1 MB). Non-finite points are
    left out."""
    pts = np.asarray(points_xyz, np.float32).reshape(-1, 3)
    cls = np.asarray(class_ids, np.uint16).reshape(-1)
    ok = np.isfinite(pts).all(axis=1)
    pts, cls = pts[ok], cls[ok]
    if len(pts) == 0:
        return {}
    voxel = np.floor(pts.astype(np.float64) / voxel_size_m).astype(np.int64)
    tile = np.floor((voxel[:, :2] + 0.5) * voxel_size_m / tile_m).astype(np.int64)
    order = np.lexsort((cls, voxel[:, 2], voxel[:, 1], voxel[:, 0], tile[:, 1], tile[:, 0]))
    voxel, cls, tile = voxel[order], cls[order], tile[order]
    pts = ((voxel + 0.5) * voxel_size_m).astype(np.float32)
    cuts = np.flatnonzero(np.any(np.diff(tile, axis=0) != 0, axis=1)) + 1
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(pts)], strict=True):
        out[f"x{tile[a, 0]}_y{tile[a, 1]}"] = (pts[a:b], cls[a:b])
    return out


def rerun_cli() -> Path:
    """The ``rerun`` command-line tool that ships inside the rerun-sdk package."""
    import rerun_cli as cli

    return Path(cli.__file__).with_name("rerun")


def compact_recording(path: Path, timeout_s: float = 60.0) -> bool:
    """Rewrite a saved recording with its chunks compacted (``rerun rrd optimize``: a few large
    chunks per entity instead of one per batching period), so it loads in seconds. The file is
    replaced only when the compacted one was written completely; on any failure the original
    stays (logged, ``False``)."""
    import subprocess

    tmp = path.with_name(path.name + ".compacting")
    try:
        proc = subprocess.run([str(rerun_cli()), "rrd", "optimize", str(path), "-o", str(tmp)],
                              capture_output=True, text=True, timeout=timeout_s)
        if proc.returncode != 0 or not tmp.is_file() or tmp.stat().st_size == 0:
            log.warning("compacting %s failed (kept as recorded): %s", path,
                        proc.stderr.strip()[-500:])
            tmp.unlink(missing_ok=True)
            return False
        tmp.replace(path)
        return True
    except (OSError, subprocess.SubprocessError) as exc:
        log.warning("compacting %s failed (kept as recorded): %s", path, exc)
        tmp.unlink(missing_ok=True)
        return False


def scene_from_boxes(room_min_xy_m: Sequence[float], room_max_xy_m: Sequence[float],
                     room_height_m: float, boxes: Sequence[Any]) -> StaticScene:
    """A :class:`StaticScene` from a room outline and boxes with ``name``, ``center_xy_m``,
    ``size_m``, ``yaw_rad`` and optionally ``z_min_m`` (the simulation's obstacle boxes)."""
    obstacles = []
    for b in boxes:
        size = tuple(float(v) for v in b.size_m)
        z0 = float(getattr(b, "z_min_m", 0.0))
        cx, cy = (float(v) for v in b.center_xy_m)
        obstacles.append(ObstacleBox(str(b.name), (cx, cy, z0 + 0.5 * size[2]), size,
                                     float(b.yaw_rad)))
    return StaticScene((float(room_min_xy_m[0]), float(room_min_xy_m[1])),
                       (float(room_max_xy_m[0]), float(room_max_xy_m[1])),
                       float(room_height_m), tuple(obstacles))
