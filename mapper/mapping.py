"""Semantic mapping: semantic clouds in, one allocentric voxel map out. Transport-free, one object.

:class:`SemanticMapping` is what the mapper service (:mod:`mapper.service`),
``smartedge evaluate paper`` and tests drive, the same way (the paper's Sec. III-C):

1. **where the cloud is**: a static edge sensor's cloud comes in the site's world frame (or in
   the camera's own frame, placed with its calibrated ``T_world_cam``); a robot's cloud comes in
   the robot's base frame (``robot_base_frame``, default ``base_link``) and is placed with the
   robot's fused pose at the cloud's stamp (interpolated between the two fused poses around it,
   at most ``max_pose_gap_s`` apart, from a :class:`~core.history.StampedHistory` per robot);
2. **ICP gate** (robot clouds): the placed cloud is aligned to the map with coarse-to-fine
   point-to-plane ICP (:func:`~mapper.alignment.align_to_map`) and fused only when
   fitness, inlier RMSE, offset and geometry pass the gate; the alignment offset (how far the
   fused pose put the cloud from where the map says it is) is reported per robot: a measure of
   the localization's quality;
3. **fusion**: :meth:`SemanticVoxelMap.integrate` (recursive Bayesian class log-probabilities,
   occupancy, geometry).

The map starts from a prior geometric model of the empty room without semantics (the paper), or
from a saved map. Bad input never raises out of :meth:`SemanticMapping.on_cloud`: the cloud is
rejected, the reason is logged once per sensor and reason and counted (``rejected.<reason>``),
and the map is unchanged. Time comes from message stamps and the ``now_ns`` the caller passes,
judged by the site's clock policy (``site.clock``, :class:`~core.site.ClockPolicy`).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import time
from collections.abc import Mapping
from typing import Final

import numpy as np

from core.geometry import se3_from_planar
from core.history import StampedHistory, lerp_se2
from core.site import Site
from mapper.alignment import (
    AlignmentConfig,
    AlignmentResult,
    align_to_map,
    consistency,
)
from mapper.semantic_map import MapError, SemanticMapConfig, SemanticVoxelMap
from protocol.messages import PoseEstimate, SemanticCloud

log = logging.getLogger(__name__)

#: Fused poses kept per robot for the stamp lookup (50 Hz odometry: about 80 s).
POSE_BUFFER: Final = 4096
#: A semantic cloud may be this many times the site's ``clock.max_age_ms`` old (30 s by
#: default): it describes the static scene, and segmentation on an edge board is slow.
CLOUD_AGE_FACTOR: Final = 30
#: Where a cloud comes from: a static edge sensor or a robot.
CLOUD_SCOPES: Final = ("edge", "robot")
#: Where a robot cloud is fused: as the fused pose places it, or moved by the ICP correction.
PLACEMENTS: Final = ("fused", "icp")
#: ICP outcomes that say nothing about the pose (nothing to align to), as opposed to those that
#: contradict it (low fitness, high RMSE, large offset); a degenerate alignment is judged by
#: how well the cloud fits the map as placed
_UNVERIFIABLE: Final = ("too_few_map_points", "too_few_points")


@dataclasses.dataclass(frozen=True)
class MappingConfig:
    """The site file's ``map:`` section (with :class:`SemanticMapConfig`'s and
    :class:`AlignmentConfig`'s scalar keys in the same flat mapping).

    ``prior_model``: a PLY point cloud (x, y, z and optionally nx, ny, nz; world frame, metres;
    a path relative to the site file) of the empty room without semantics that the map starts
    from; empty: none (the map grows from the clouds alone, and robot clouds are fused only
    where static sensors have mapped enough to align them to). ``snapshot_path``: where the
    mapper service keeps the map (``.npz``; relative to the site file; loaded at start, written
    every ``snapshot_period_s`` and on shutdown; empty: not kept). ``publish_period_s``: how often
    the service publishes the map's semantic voxels for viewers (0: never).
    ``robot_base_frame``: the ``frame_id`` of robot clouds placed with the fused pose.
    ``max_pose_gap_s``: a robot cloud needs fused poses within this of its stamp. Clouds
    stamped more than the site's ``clock.max_future_ms`` ahead of the clock, or more than
    :data:`CLOUD_AGE_FACTOR` times ``clock.max_age_ms`` behind it, are rejected.
    ``align_robot_clouds``: ICP-gate robot clouds (off: fuse them as the pose puts
    them, for the comparison of Fig. 7). ``placement``: ``"fused"`` (default) fuses an accepted
    robot cloud where the fused pose puts it and uses ICP as the gate (a cloud that ICP finds
    elsewhere, or that does not fit, is rejected; one the map cannot check (nothing mapped there
    yet, or floor only: then it must fit the map as placed) is fused when the fused pose's
    position standard deviation is at most ``max_unverified_std_m``); ``"icp"`` moves it by the
    ICP correction and rejects what ICP cannot check. Measured on the simulated lab
    (docs/semantic_mapping.md): against the prior model of the empty room plus the static
    cameras' clouds, ICP moves clouds taken at the true pose by 5-20 cm (furniture the map lacks
    pulls it), more than the fused pose's error,
    hence ``fused``. ``max_voxels_published``: cap of the published map.
    """

    prior_model: str = ""
    snapshot_path: str = ""
    snapshot_period_s: float = 60.0
    publish_period_s: float = 5.0
    robot_base_frame: str = "base_link"
    max_pose_gap_s: float = 0.5
    align_robot_clouds: bool = True
    placement: str = "fused"
    max_unverified_std_m: float = 0.10
    max_voxels_published: int = 200_000
    map: SemanticMapConfig = dataclasses.field(default_factory=SemanticMapConfig)
    alignment: AlignmentConfig = dataclasses.field(default_factory=AlignmentConfig)

    def __post_init__(self) -> None:
        for name in ("snapshot_period_s", "publish_period_s", "max_pose_gap_s",
                     "max_unverified_std_m"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise MapError(f"map config: {name}: must be a finite number >= 0, got {value!r}")
        if self.placement not in PLACEMENTS:
            raise MapError(f"map config: placement: one of {PLACEMENTS}, got {self.placement!r}")
        if not (math.isfinite(self.max_unverified_std_m) and self.max_unverified_std_m >= 0):
            raise MapError("map config: max_unverified_std_m: must be a finite number >= 0")
        if not self.robot_base_frame:
            raise MapError("map config: robot_base_frame: must not be empty")
        if not 1 <= self.max_voxels_published <= 2_000_000:
            raise MapError("map config: max_voxels_published: must be in [1, 2000000], got "
                           f"{self.max_voxels_published}")

    @classmethod
    def from_site(cls, site: Site, **overrides: object) -> MappingConfig:
        """The site file's ``map`` section; errors name the file and key. Paths stay as written
        (resolve them with :meth:`resolve`)."""
        reader = site.section_reader()
        node = site.section("map")
        own = {f.name for f in dataclasses.fields(cls)} - {"map", "alignment"}
        map_fields = {f.name for f in dataclasses.fields(SemanticMapConfig)}
        align_fields = {f.name for f in dataclasses.fields(AlignmentConfig)
                        if not isinstance(f.default, tuple)}
        reader.no_unknown("map", node, own | map_fields | align_fields)
        try:
            map_cfg = reader.section("map", {k: v for k, v in node.items() if k in map_fields},
                                     SemanticMapConfig, int_lo=2)
            align_cfg = reader.section(
                "map", {k: v for k, v in node.items() if k in align_fields}, AlignmentConfig,
                int_lo=1)
            base = reader.section("map", {k: v for k, v in node.items() if k in own}, cls,
                                  int_lo=1, base=cls(map=map_cfg, alignment=align_cfg))
        except MapError as exc:
            raise reader.fail("map", str(exc)) from None
        return dataclasses.replace(base, **overrides)  # type: ignore[arg-type]


@dataclasses.dataclass(frozen=True, eq=False)
class CloudOutcome:
    """What :meth:`SemanticMapping.on_cloud` did with one cloud.

    ``scope`` (``edge``/``robot``) and ``sensor_id`` name the source; ``accepted``: fused;
    ``reason``: why not (a stable token first: ``unknown_sensor``, ``wrong_frame``,
    ``future_stamp``, ``stale``, ``no_pose``, ``empty``, ``bad_cloud``, ``alignment``);
    ``points_fused``; ``T_world_sensor`` (4, 4) where the cloud was placed (after alignment);
    ``alignment``: the ICP result for robot clouds; ``fuse_s``: wall time of placing, aligning
    and fusing (for the status only).
    """

    scope: str
    sensor_id: str
    stamp_ns: int
    accepted: bool
    reason: str = ""
    points_fused: int = 0
    T_world_sensor: np.ndarray | None = None
    alignment: AlignmentResult | None = None
    fuse_s: float = 0.0


@dataclasses.dataclass(frozen=True)
class AlignmentReport:
    """The latest ICP alignment of one robot's cloud: offset of the robot's fused pose from
    where the map puts its observations (``dx_m``, ``dy_m`` in the world frame, ``dyaw_deg``),
    ``fitness`` / ``inlier_rmse_m``, and whether the gate accepted it."""

    robot_id: str
    stamp_ns: int
    dx_m: float
    dy_m: float
    dyaw_deg: float
    fitness: float
    inlier_rmse_m: float
    accepted: bool


def _lerp_poses(a: PoseEstimate, b: PoseEstimate, fraction: float) -> tuple[float, float, float]:
    return lerp_se2((a.x, a.y, a.theta), (b.x, b.y, b.theta), fraction)


def interpolate_pose(poses: StampedHistory[PoseEstimate], stamp_ns: int,
                     max_gap_ns: int) -> tuple[float, float, float] | None:
    """(x, y, theta) (world frame; m, rad) at ``stamp_ns`` from a history of fused poses:
    linear between the two around it (the angle along the shorter arc) when they are at most
    ``max_gap_ns`` apart, the nearest one when it is within ``max_gap_ns / 2``, else ``None``."""
    pose = poses.interpolate(stamp_ns, _lerp_poses, max_gap_ns=max_gap_ns)
    if pose is not None:
        return pose
    near = poses.nearest(stamp_ns, max_gap_ns=max_gap_ns // 2)
    return None if near is None else (near.item.x, near.item.y, near.item.theta)


class SemanticMapping:
    """The site's semantic map and what feeds it (see the module docstring). Not thread-safe:
    one worker drives it."""

    def __init__(self, site: Site, config: MappingConfig | None = None, *,
                 prior_points_world: np.ndarray | None = None,
                 prior_normals_world: np.ndarray | None = None,
                 initial_map: SemanticVoxelMap | None = None) -> None:
        self.site = site
        self.config = config if config is not None else MappingConfig()
        if initial_map is not None:
            if initial_map.config != self.config.map:
                raise MapError("initial map: its configuration differs from the site's map "
                               f"section ({initial_map.config} vs {self.config.map})")
            self.map = initial_map
        elif prior_points_world is not None:
            self.map = SemanticVoxelMap.from_prior_points(prior_points_world, self.config.map,
                                                          prior_normals_world)
        else:
            self.map = SemanticVoxelMap(self.config.map)
        self.counters: collections.Counter[str] = collections.Counter()
        self.alignments: dict[str, AlignmentReport] = {}
        # fused poses per robot; messages may overtake each other on the way
        self._poses: dict[str, StampedHistory[PoseEstimate]] = {
            rid: StampedHistory(POSE_BUFFER, out_of_order="insert") for rid in site.robots}
        self._warned: set[tuple[str, str]] = set()

    # -- inputs --------------------------------------------------------------------------------

    def on_pose(self, est: PoseEstimate) -> None:
        """A fused pose of a robot (``source`` ``fused``; others are counted and ignored)."""
        if est.source != "fused":
            self.counters["pose_wrong_source"] += 1
            return
        buf = self._poses.get(est.robot_id)
        if buf is None:
            self.counters["pose_unknown_robot"] += 1
            return
        buf.insert(est.stamp_ns, est)

    def on_cloud(self, msg: SemanticCloud, scope: str, sensor_id: str,
                 now_ns: int) -> CloudOutcome:
        """Place, gate and fuse one cloud that arrived on ``scope``'s key of ``sensor_id`` (the
        key's camera or robot id, not the message's own ``sensor_id``, which any sender can
        write). Never raises for bad input."""
        t0 = time.perf_counter()
        out = self._on_cloud(msg, scope, sensor_id, now_ns)
        out = dataclasses.replace(out, fuse_s=time.perf_counter() - t0)
        if out.accepted:
            self.counters[f"fused.{scope}"] += 1
            self.counters["points_fused"] += out.points_fused
        else:
            token = out.reason.split(":")[0]
            self.counters["rejected"] += 1
            self.counters[f"rejected.{token}"] += 1
            if (sensor_id, token) not in self._warned:
                self._warned.add((sensor_id, token))
                log.warning("cloud of %s %s rejected (logged once per sensor and reason): %s",
                            scope, sensor_id, out.reason)
        return out

    def _on_cloud(self, msg: SemanticCloud, scope: str, sensor_id: str,
                  now_ns: int) -> CloudOutcome:
        cfg = self.config

        def reject(reason: str, **kw: object) -> CloudOutcome:
            return CloudOutcome(scope, sensor_id, msg.stamp_ns, False, reason, **kw)  # type: ignore[arg-type]

        if scope not in CLOUD_SCOPES:
            return reject(f"unknown_sensor: scope {scope!r} not in {CLOUD_SCOPES}")
        known = self.site.cameras if scope == "edge" else self.site.robots
        if sensor_id not in known:
            return reject(f"unknown_sensor: {scope} {sensor_id!r} is not in the site file")
        clock = self.site.clock
        if clock.too_far_ahead(msg.stamp_ns, now_ns):
            return reject(f"future_stamp: {(msg.stamp_ns - now_ns) * 1e-9:.3f} s ahead of the "
                          f"clock (max {clock.max_future_ms * 1e-3:g} s)")
        if now_ns - msg.stamp_ns > CLOUD_AGE_FACTOR * clock.max_age_ns:
            return reject(f"stale: {(now_ns - msg.stamp_ns) * 1e-9:.1f} s old (max "
                          f"{CLOUD_AGE_FACTOR * clock.max_age_ms * 1e-3:g} s)")
        if len(msg.points_xyz) == 0:
            return reject("empty: no points")
        placed = self._frame_pose(msg, scope, sensor_id)
        if isinstance(placed, str):
            return reject(placed)
        T_world_frame, pose_std_m = placed
        points = msg.points_xyz.astype(np.float64)
        if not np.isfinite(points).all():
            return reject("bad_cloud: points_xyz has NaN or inf")
        points_world = points @ T_world_frame[:3, :3].T + T_world_frame[:3, 3]
        T_world_sensor = (T_world_frame @ msg.T_frame_sensor if msg.T_frame_sensor is not None
                          else T_world_frame)
        alignment = None
        if scope == "robot" and cfg.align_robot_clouds:
            map_points, map_normals = self._map_geometry(points_world)
            alignment = align_to_map(points_world, map_points, map_normals, cfg.alignment,
                                     pivot_world=T_world_sensor[:3, 3].copy())
            self._report_alignment(sensor_id, msg.stamp_ns, alignment, T_world_sensor)
            if not alignment.accepted:
                failed = [r.split(":")[0].strip() for r in alignment.reason.split(";")]
                if "degenerate" in failed:
                    # ICP had nothing to hold on to in some direction (floor only): its offset
                    # and fitness mean nothing; the cloud as placed must agree with the map
                    fit, _ = consistency(points_world, map_points,
                                         cfg.alignment.max_correspondence_m[-1])
                    unverifiable = fit >= cfg.alignment.min_fitness
                else:
                    unverifiable = all(f in _UNVERIFIABLE for f in failed)
                if not (unverifiable and cfg.placement == "fused"
                        and pose_std_m <= cfg.max_unverified_std_m):
                    return reject(f"alignment: {alignment.reason}",
                                  T_world_sensor=T_world_sensor, alignment=alignment)
                self.counters["fused.robot_unverified"] += 1
            elif cfg.placement == "icp":
                T = alignment.T_correction
                points_world = points_world @ T[:3, :3].T + T[:3, 3]
                T_world_sensor = T @ T_world_sensor
        try:
            report = self.map.integrate(points_world, msg.class_ids, msg.confidences,
                                        sensor_origin_world=T_world_sensor[:3, 3].copy())
        except MapError as exc:
            return reject(f"bad_cloud: {exc}", T_world_sensor=T_world_sensor,
                          alignment=alignment)
        return CloudOutcome(scope, sensor_id, msg.stamp_ns, True, "", report.points_fused,
                            T_world_sensor, alignment)

    def _frame_pose(self, msg: SemanticCloud, scope: str, sensor_id: str
                    ) -> tuple[np.ndarray, float] | str:
        """T_world_frame (4, 4) of the cloud's ``frame_id`` and the standard deviation (m) of its
        position (0 for the world frame and calibrated cameras), or the reason it is unknown."""
        world = self.site.world_frame
        if msg.frame_id == world:
            return np.eye(4), 0.0
        if scope == "edge":
            if msg.frame_id == sensor_id:  # the camera's own optical frame
                return self.site.camera(sensor_id).T_world_cam.copy(), 0.0
            return (f"wrong_frame: an edge cloud must be in {world!r} or the camera's frame "
                    f"{sensor_id!r}, got {msg.frame_id!r}")
        if msg.frame_id != self.config.robot_base_frame:
            return (f"wrong_frame: a robot cloud must be in {self.config.robot_base_frame!r} or "
                    f"{world!r}, got {msg.frame_id!r}")
        buf = self._poses[sensor_id]
        pose = interpolate_pose(buf, msg.stamp_ns, round(self.config.max_pose_gap_s * 1e9))
        if pose is None:
            return (f"no_pose: no fused pose of {sensor_id!r} within "
                    f"{self.config.max_pose_gap_s} s of the cloud's stamp")
        nearest = buf.nearest(msg.stamp_ns)
        assert nearest is not None  # interpolate_pose found one
        cov = np.asarray(nearest.item.covariance, dtype=np.float64)[:2, :2]
        std = math.sqrt(max(float(np.trace(cov)), 0.0)) if np.isfinite(cov).all() else math.inf
        return se3_from_planar(*pose), std

    def _map_geometry(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Voxel means and normals of the occupied voxels the ICP gate can use for a cloud:
        those within its crop margin (plus a voxel) of the cloud's bounding box, a superset of
        what :func:`align_to_map` keeps."""
        a = self.config.alignment
        margin = (a.crop_margin_m if a.crop_margin_m is not None
                  else a.max_offset_m + max(a.max_correspondence_m))
        margin += self.map.config.voxel_size_m
        lo = np.array([points_world[:, k].min() for k in range(3)]) - margin
        hi = np.array([points_world[:, k].max() for k in range(3)]) + margin
        return self.map.geometry_in_box(lo, hi)

    def _report_alignment(self, robot_id: str, stamp_ns: int, res: AlignmentResult,
                          T_world_sensor: np.ndarray) -> None:
        if not math.isfinite(res.inlier_rmse_m) and res.fitness == 0.0:
            return  # rejected before ICP ran: nothing measured
        pivot = T_world_sensor[:3, 3]
        T = res.T_correction
        d = T[:3, :3] @ pivot + T[:3, 3] - pivot
        self.alignments[robot_id] = AlignmentReport(
            robot_id, stamp_ns, float(d[0]), float(d[1]), res.yaw_deg, res.fitness,
            res.inlier_rmse_m, res.accepted)

    # -- outputs -------------------------------------------------------------------------------

    def voxels_message(self, stamp_ns: int, seq: int, source_id: str = "map"
                       ) -> SemanticCloud | None:
        """The map's voxels with semantic information as a :class:`SemanticCloud` in the world
        frame (voxel means, most probable class, its probability), at most
        ``max_voxels_published`` of them (the most confident); ``None`` when there are none."""
        sem = self.map.has_semantics()
        if not sem.any():
            return None
        rows = np.flatnonzero(sem)
        conf = self.map.confidence()[rows]
        cap = self.config.max_voxels_published
        if len(rows) > cap:
            keep = np.argpartition(-conf, cap - 1)[:cap]
            rows, conf = rows[keep], conf[keep]
        return SemanticCloud(
            sensor_id=source_id, stamp_ns=int(stamp_ns), seq=int(seq),
            frame_id=self.site.world_frame,
            points_xyz=self.map.means()[rows].astype(np.float32),
            class_ids=self.map.labels()[rows].astype(np.uint16),
            confidences=np.clip(conf, 0.0, 1.0).astype(np.float32))

    def counter_snapshot(self) -> Mapping[str, int]:
        out = {f"map.{k}": int(v) for k, v in self.counters.items()}
        out["map.voxels"] = len(self.map)
        out["map.voxels_semantic"] = int(self.map.has_semantics().sum())
        return out

    def alignment_summary(self) -> str:
        """One line per robot: the latest alignment offset (for the status detail)."""
        parts = []
        for rid, a in sorted(self.alignments.items()):
            parts.append(f"{rid} icp {'ok' if a.accepted else 'rejected'} offset "
                         f"{math.hypot(a.dx_m, a.dy_m) * 100:.1f} cm / {a.dyaw_deg:+.2f} deg, "
                         f"fitness {a.fitness:.2f}, rmse {a.inlier_rmse_m * 100:.1f} cm")
        return "; ".join(parts)
