"""Live state in the Rerun viewer: the only module that imports ``rerun``.

Entity layout (world frame = site world frame, z up):

- ``world/cameras/<camera_id>``: camera pose (Transform3D) and ``.../image`` Pinhole; per-frame
  ``.../image/detections`` (boxes) and ``.../image/keypoints`` (2D keypoints); ``.../image``
  also gets the camera's JPEG preview when its edge agent sends one (``--preview-rate``)
- ``world/robots/<robot_id>/camera``: camera-only estimate (Transform3D) with ``.../keypoints``
  (3D keypoints of the robot model at that pose)
- ``world/robots/<robot_id>/fused``, ``.../odometry``, ``.../ground_truth``: poses
- ``world/trajectories/<robot_id>/{camera,fused,odometry,ground_truth}``: line strips
- ``metrics/<robot_id>/error_cm/{camera,fused,odometry}``, ``metrics/latency_ms/<stage>``: series
- ``status/<service>/<id>``: text log of service status

Time: timeline ``stamp`` (sensor time of each message), so a replay shows what happened when.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
from pathlib import Path
from typing import Any, Final

import numpy as np
import rerun as rr

from protocol.errors import UsageError
from protocol.geometry import (
    rotation_z,
    yaw_from_rotation,
    yaw_to_quaternion,
)
from protocol.messages import (
    CameraImage,
    Odometry,
    PoseEstimate,
    RobotDetections,
    ServiceStatus,
)
from protocol.site import Site

log = logging.getLogger(__name__)

TIMELINE: Final = "stamp"
TRAIL_MAX_POINTS: Final = 5000
COLORS: Final = {
    "camera": (230, 120, 20),
    "fused": (30, 160, 230),
    "odometry": (150, 150, 150),
    "ground_truth": (40, 200, 60),
    "correction": (220, 40, 200),
}


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


class RerunView:
    """Logs site, detections, poses, trajectories and metrics to one Rerun recording.

    All methods are cheap and never raise into the caller: a viewer problem must not stop the
    backend (errors are logged once per kind)."""

    def __init__(self, site: Site, target: RerunTarget, app_id: str = "smartedge") -> None:
        self.site = site
        self.target = target
        self.rec = rr.RecordingStream(app_id)
        self._trails: dict[tuple[str, str], collections.deque[tuple[float, float]]] = {}
        self._failed: set[str] = set()
        self._styled: set[str] = set()
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
        for cam in self.site.cameras.values():
            T = cam.T_world_cam
            base = f"world/cameras/{cam.camera_id}"
            rec.log(base, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
            rec.log(
                f"{base}/image",
                rr.Pinhole(
                    image_from_camera=cam.K,
                    resolution=[cam.width, cam.height],
                    camera_xyz=rr.ViewCoordinates.RDF,
                    image_plane_distance=0.5,
                ),
                static=True,
            )
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
            # the robot body (a cylinder of the footprint) rides on the fused pose
            rec.log(
                f"world/robots/{robot_id}/fused/body",
                rr.Cylinders3D(
                    lengths=[model.height_m],
                    radii=[model.footprint_radius_m],
                    centers=[[0.0, 0.0, model.height_m / 2]],
                    colors=[(*COLORS["fused"], 90)],
                ),
                static=True,
            )
            rec.log(
                f"world/robots/{robot_id}/fused/keypoints",
                rr.Points3D(
                    model.keypoints_base_m,
                    keypoint_ids=np.arange(model.num_keypoints),
                    class_ids=0,
                    radii=0.01,
                ),
                static=True,
            )

    # ---------------------------------------------------------------------------------------

    def detections(self, msg: RobotDetections) -> None:
        self._guard("detections", self._detections, msg)

    def _detections(self, msg: RobotDetections) -> None:
        self._time(msg.stamp_ns)
        base = f"world/cameras/{msg.camera_id}/image"
        boxes = [d.bbox_xyxy for d in msg.detections]
        if boxes:
            arr = np.asarray(boxes)
            self.rec.log(
                f"{base}/detections",
                rr.Boxes2D(
                    array=arr,
                    array_format=rr.Box2DFormat.XYXY,
                    labels=[f"{d.score:.2f}" for d in msg.detections],
                ),
            )
            pts = np.concatenate([d.keypoints_px for d in msg.detections])
            scores = np.concatenate([d.keypoint_scores for d in msg.detections])
            kp_ids = np.concatenate([np.arange(len(d.keypoints_px)) for d in msg.detections])
            colors = np.stack([255 * (1 - scores), 255 * scores, np.zeros_like(scores)], 1)
            self.rec.log(
                f"{base}/keypoints",
                rr.Points2D(pts, keypoint_ids=kp_ids, colors=colors.astype(np.uint8), radii=3.0),
            )
        else:
            self.rec.log(f"{base}/detections", rr.Clear(recursive=False))
            self.rec.log(f"{base}/keypoints", rr.Clear(recursive=False))

    def image(self, msg: CameraImage) -> None:
        """A camera's preview frame (JPEG, logged as is: Rerun decodes it)."""
        self._guard("image", self._image, msg)

    def _image(self, msg: CameraImage) -> None:
        if msg.camera_id not in self.site.cameras:
            return
        self._time(msg.stamp_ns)
        self.rec.log(f"world/cameras/{msg.camera_id}/image",
                     rr.EncodedImage(contents=msg.data.tobytes(), media_type="image/jpeg"))

    def pose(self, est: PoseEstimate, kind: str | None = None) -> None:
        """A camera-only (``kind='camera'``) or fused (``'fused'``) estimate."""
        self._guard(f"pose.{kind or est.source}", self._pose, est, kind)

    def _pose(self, est: PoseEstimate, kind: str | None) -> None:
        kind = kind or ("camera" if est.source == "cameras" else "fused")
        self._time(est.stamp_ns)
        self._pose_entity(est.robot_id, kind, est.x, est.y, est.theta)
        if kind == "camera":
            model = self.site.robot_model(est.robot_id)
            pts = model.keypoints_base_m @ rotation_z(est.theta).T + [est.x, est.y, 0.0]
            self.rec.log(
                f"world/robots/{est.robot_id}/camera_keypoints",
                rr.Points3D(pts, keypoint_ids=np.arange(len(pts)), class_ids=0, radii=0.015),
            )
            self.rec.log(
                f"metrics/{est.robot_id}/reprojection_rmse_px",
                rr.Scalars([est.reprojection_rmse_px]),
            )

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
        self.rec.log(
            f"world/robots/{robot_id}/{kind}/marker",
            rr.Arrows3D(
                origins=[[0, 0, 0.02]],
                vectors=[[0.3, 0, 0]],
                colors=[COLORS.get(kind, (255, 255, 255))],
            ),
        )
        trail = self._trails.setdefault(
            (robot_id, kind), collections.deque(maxlen=TRAIL_MAX_POINTS)
        )
        if not trail or math.hypot(trail[-1][0] - x, trail[-1][1] - y) > 0.01:
            trail.append((x, y))
            strip = np.array([[px, py, 0.01] for px, py in trail])
            self.rec.log(
                f"world/trajectories/{robot_id}/{kind}",
                rr.LineStrips3D([strip], colors=[COLORS.get(kind, (255, 255, 255))]),
            )

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
                                                  names=[kind]), static=True)
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
                rr.Points3D([[x, y, 0.05]], colors=[COLORS["correction"]], radii=0.05),
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
