"""The semantic map for ROS: the mapper's voxels as a ``sensor_msgs/PointCloud2`` and a 2D
``nav_msgs/OccupancyGrid`` of obstacles (for RViz and Nav2's costmap).

The mapper publishes its voxels on ``.../map/<map_id>/voxels`` (a
:class:`protocol.messages.SemanticCloud` in the world frame: voxel means, most probable class,
its probability). :class:`MapOutput` keeps the newest one (a new map replaces one not yet
published), publishes at most ``rate_hz`` (<= 1 Hz) and converts it into a :class:`MapSnapshot`:

* the cloud: ``x``, ``y``, ``z`` float32 (m, world frame), ``rgb`` the class's display colour
  packed as RViz reads it (``0x00RRGGBB`` in the bits of a float32), ``confidence`` float32,
  ``label`` uint16 (:data:`protocol.semantic_classes.SEMANTIC_CLASSES` ids);
* the grid: voxels of the obstacle classes whose height lies in the band
  ``[floor_z_m + band_min_m, floor_z_m + band_max_m]`` mark their cell occupied (100); cells
  holding a voxel of a free class (``floor``) and no obstacle are free (0); the rest unknown
  (-1). The grid covers the map's extent, its origin snapped to ``resolution_m``.

Transport-free: the adapters serialize a snapshot (:func:`serialize_point_cloud`,
:func:`serialize_occupancy_grid`: CDR, or ROS 1 with ``ros1=True``) and put it on their topics.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, Final

import numpy as np

from protocol.messages import NS_PER_S, SemanticCloud
from protocol.semantic_classes import SEMANTIC_CLASS_ID, class_colors

log = logging.getLogger(__name__)

POINT_CLOUD2_TYPE: Final = "sensor_msgs/msg/PointCloud2"
OCCUPANCY_GRID_TYPE: Final = "nav_msgs/msg/OccupancyGrid"
#: sensor_msgs/PointField datatypes
POINT_FIELD_UINT16: Final = 4
POINT_FIELD_FLOAT32: Final = 7
#: (name, byte offset, PointField datatype) of a map point; 24 bytes a point
CLOUD_FIELDS: Final = (
    ("x", 0, POINT_FIELD_FLOAT32),
    ("y", 4, POINT_FIELD_FLOAT32),
    ("z", 8, POINT_FIELD_FLOAT32),
    ("rgb", 12, POINT_FIELD_FLOAT32),
    ("confidence", 16, POINT_FIELD_FLOAT32),
    ("label", 20, POINT_FIELD_UINT16),
)
POINT_STEP: Final = 24
_POINT_DTYPE: Final = np.dtype({
    "names": ["x", "y", "z", "rgb", "confidence", "label"],
    "formats": ["<f4", "<f4", "<f4", "<u4", "<f4", "<u2"],
    "offsets": [0, 4, 8, 12, 16, 20],
    "itemsize": POINT_STEP,
})
#: OccupancyGrid cell values
UNKNOWN: Final = -1
FREE: Final = 0
OCCUPIED: Final = 100
#: largest grid published (cells); a bigger extent is an error, not an allocation
MAX_GRID_CELLS: Final = 16_000_000
#: classes that are obstacles by default: everything standing on the floor that a base cannot
#: drive through; ``person`` and ``robot`` are moving things the local costmap sees anyway
DEFAULT_OBSTACLE_CLASSES: Final = "wall,door,table,chair,shelf,cabinet,box,obstacle,distractor"
DEFAULT_FREE_CLASSES: Final = "floor"


class MapOutputError(ValueError):
    """A map message that cannot be published (the reason names the field)."""


@dataclasses.dataclass(frozen=True)
class MapOutputConfig:
    """The robot bridge's map output (site file section ``map_output``).

    ``rate_hz``: at most this many maps a second go to the robot (0 turns the output off;
    at most 1). ``map_id``: the mapper instance whose voxels are published (``*``: any).
    ``cloud`` / ``grid``: publish the ``PointCloud2`` (topic ``ros.map_cloud_topic``) and / or
    the ``OccupancyGrid`` (``ros.obstacles_topic``). ``resolution_m``: grid cell size.
    ``floor_z_m``: height of the floor in the world frame; ``band_min_m`` / ``band_max_m``:
    the height band above it whose obstacle voxels mark a cell (a base's height clearance).
    ``obstacle_classes`` / ``free_classes``: comma-separated class names
    (``protocol.semantic_classes``) that make a cell occupied / free (``floor_z_m`` is >= 0 in
    the site file: put the world frame's origin on or below the floor). ``min_confidence``:
    voxels less certain of their class are left out of the grid (the cloud keeps them, with
    their confidence).
    """

    rate_hz: float = 1.0
    map_id: str = "*"
    cloud: bool = True
    grid: bool = True
    resolution_m: float = 0.05
    floor_z_m: float = 0.0
    band_min_m: float = 0.05
    band_max_m: float = 1.8
    obstacle_classes: str = DEFAULT_OBSTACLE_CLASSES
    free_classes: str = DEFAULT_FREE_CLASSES
    min_confidence: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_hz) and 0.0 <= self.rate_hz <= 1.0):
            raise ValueError(f"rate_hz {self.rate_hz}: expected 0 (off) to 1")
        if not (math.isfinite(self.resolution_m) and 0.005 <= self.resolution_m <= 10.0):
            raise ValueError(f"resolution_m {self.resolution_m}: expected 0.005 to 10")
        for name in ("floor_z_m", "band_min_m", "band_max_m"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} is not finite")
        if not self.band_min_m < self.band_max_m:
            raise ValueError(
                f"band_min_m {self.band_min_m} must be below band_max_m {self.band_max_m}")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f"min_confidence {self.min_confidence}: expected 0 to 1")
        if not str(self.map_id).strip():
            raise ValueError("map_id is empty")
        for name in ("obstacle_classes", "free_classes"):
            unknown = [v for v in _names(getattr(self, name)) if v not in SEMANTIC_CLASS_ID]
            if unknown:
                raise ValueError(f"{name}: unknown class {unknown[0]!r}; expected names of "
                                 f"protocol.semantic_classes")
        both = set(_names(self.obstacle_classes)) & set(_names(self.free_classes))
        if both:
            raise ValueError(f"class {sorted(both)[0]!r} is both an obstacle and free")

    @classmethod
    def from_site(cls, site: Any) -> MapOutputConfig:
        """The ``map_output`` section of a :class:`core.site.Site` (errors name file and
        key)."""
        return site.section_reader().section("map_output", site.section("map_output"), cls)

    @property
    def enabled(self) -> bool:
        return self.rate_hz > 0.0 and (self.cloud or self.grid)

    @staticmethod
    def class_ids(names: str) -> np.ndarray:
        """The class ids of comma-separated class ``names``."""
        return np.array(sorted(SEMANTIC_CLASS_ID[n] for n in _names(names)), dtype=np.int64)


def _names(text: str) -> tuple[str, ...]:
    return tuple(n.strip() for n in str(text).split(",") if n.strip())


@dataclasses.dataclass(frozen=True, eq=False)
class OccupancyGrid2D:
    """A 2D grid in the world frame: ``cells`` (height, width) int8 (-1 unknown, 0 free, 100
    occupied), row ``j`` column ``i`` covering x in ``origin_x_m + i * resolution_m`` (one
    cell), y likewise; ``origin_z_m`` the floor height."""

    cells: np.ndarray
    resolution_m: float
    origin_x_m: float
    origin_y_m: float
    origin_z_m: float = 0.0

    @property
    def width(self) -> int:
        return int(self.cells.shape[1])

    @property
    def height(self) -> int:
        return int(self.cells.shape[0])

    def cell_of(self, x_m: float, y_m: float) -> tuple[int, int]:
        """(row, column) of the cell holding world point (x, y)."""
        return (math.floor((y_m - self.origin_y_m) / self.resolution_m),
                math.floor((x_m - self.origin_x_m) / self.resolution_m))


@dataclasses.dataclass(frozen=True, eq=False)
class MapSnapshot:
    """One map, ready for ROS: the cloud's arrays (``points_xyz`` (N, 3) float32 m,
    ``rgb`` (N,) uint32 ``0x00RRGGBB``, ``labels`` (N,) uint16, ``confidences`` (N,) float32)
    in ``frame_id`` at ``stamp_ns``, and the obstacle grid (``None`` when off)."""

    stamp_ns: int
    frame_id: str
    map_id: str
    points_xyz: np.ndarray
    rgb: np.ndarray
    labels: np.ndarray
    confidences: np.ndarray
    grid: OccupancyGrid2D | None = None
    cloud: bool = True

    def __len__(self) -> int:
        return int(self.points_xyz.shape[0])

    # the adapters' view (robot_bridge.adapters.base.MapMessages)

    def cloud_payload(self, *, ros1: bool = False, seq: int = 0) -> bytes | None:
        """The ``PointCloud2`` wire bytes, or ``None`` when the cloud output is off."""
        return serialize_point_cloud(self, ros1=ros1, seq=seq) if self.cloud else None

    def grid_payload(self, *, ros1: bool = False, seq: int = 0) -> bytes | None:
        """The ``OccupancyGrid`` wire bytes, or ``None`` when the grid output is off."""
        return (None if self.grid is None
                else serialize_occupancy_grid(self, ros1=ros1, seq=seq))


# --------------------------------------------------------------------------------------------
# pure conversions
# --------------------------------------------------------------------------------------------


def check_map_cloud(cloud: object, world_frame: str | None = None) -> SemanticCloud:
    """``cloud`` when it is a publishable map: a :class:`SemanticCloud` with finite points, in
    ``world_frame`` when given; :class:`MapOutputError` naming the field otherwise. (Shapes and
    dtypes were checked when the message was built or decoded.)"""
    if not isinstance(cloud, SemanticCloud):
        raise MapOutputError(f"map message is a {type(cloud).__name__}, not a SemanticCloud")
    pts = np.asarray(cloud.points_xyz)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise MapOutputError(f"points_xyz has shape {pts.shape}, expected (N, 3)")
    n = pts.shape[0]
    if np.shape(cloud.class_ids) != (n,) or np.shape(cloud.confidences) != (n,):
        raise MapOutputError(
            f"class_ids {np.shape(cloud.class_ids)} / confidences {np.shape(cloud.confidences)}"
            f" do not match {n} points")
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        raise MapOutputError(f"points_xyz: {int(bad.sum())} of {n} points are not finite")
    conf = np.asarray(cloud.confidences)
    if not np.isfinite(conf).all():
        raise MapOutputError("confidences: not finite")
    if world_frame is not None and cloud.frame_id != world_frame:
        raise MapOutputError(
            f"frame_id {cloud.frame_id!r}: the map must be in the world frame {world_frame!r}")
    return cloud


def pack_rgb(colors: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 RGB → (N,) uint32 ``0x00RRGGBB`` (PCL's / RViz's packed ``rgb``)."""
    c = np.asarray(colors, dtype=np.uint32)
    return (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]


def occupancy_grid(points_xyz: np.ndarray, labels: np.ndarray, confidences: np.ndarray,
                   config: MapOutputConfig) -> OccupancyGrid2D:
    """The obstacle grid of a map's voxels (module docstring); :class:`MapOutputError` when
    its extent needs more than :data:`MAX_GRID_CELLS` cells."""
    res = float(config.resolution_m)
    pts = np.asarray(points_xyz, dtype=np.float64)
    if pts.shape[0] == 0:
        return OccupancyGrid2D(np.full((1, 1), UNKNOWN, np.int8), res, 0.0, 0.0,
                               config.floor_z_m)
    ij = np.floor(pts[:, :2] / res).astype(np.int64)
    lo = ij.min(axis=0)
    hi = ij.max(axis=0)
    width, height = (int(v) for v in hi - lo + 1)
    if width * height > MAX_GRID_CELLS:
        raise MapOutputError(
            f"grid of {width} x {height} cells at {res} m exceeds {MAX_GRID_CELLS} cells")
    cells = np.full((height, width), UNKNOWN, np.int8)
    col = ij[:, 0] - lo[0]
    row = ij[:, 1] - lo[1]
    lab = np.asarray(labels).astype(np.int64)
    sure = np.asarray(confidences) >= config.min_confidence
    z = pts[:, 2] - config.floor_z_m
    free = np.isin(lab, config.class_ids(config.free_classes)) & sure
    cells[row[free], col[free]] = FREE
    occ = (np.isin(lab, config.class_ids(config.obstacle_classes)) & sure
           & (z >= config.band_min_m) & (z <= config.band_max_m))
    cells[row[occ], col[occ]] = OCCUPIED
    return OccupancyGrid2D(cells, res, float(lo[0] * res), float(lo[1] * res),
                           float(config.floor_z_m))


def map_snapshot(cloud: SemanticCloud, config: MapOutputConfig,
                 world_frame: str | None = None) -> MapSnapshot:
    """The ROS-ready form of a checked map message (:func:`check_map_cloud` first)."""
    cloud = check_map_cloud(cloud, world_frame)
    labels = np.asarray(cloud.class_ids).astype(np.uint16)
    n_classes = int(labels.max()) + 1 if labels.size else 1
    palette = class_colors(max(n_classes, 1))
    rgb = pack_rgb(palette[labels]) if labels.size else np.zeros(0, np.uint32)
    pts = np.asarray(cloud.points_xyz, dtype=np.float32)
    conf = np.asarray(cloud.confidences, dtype=np.float32)
    grid = occupancy_grid(pts, labels, conf, config) if config.grid else None
    return MapSnapshot(int(cloud.stamp_ns), cloud.frame_id, cloud.sensor_id, pts, rgb,
                       labels, conf, grid, cloud=config.cloud)


def cloud_bytes(snapshot: MapSnapshot) -> bytes:
    """The ``PointCloud2`` data block of ``snapshot``: :data:`POINT_STEP` bytes a point, little
    endian, fields at the offsets of :data:`CLOUD_FIELDS`."""
    block = np.zeros(len(snapshot), dtype=_POINT_DTYPE)
    block["x"] = snapshot.points_xyz[:, 0]
    block["y"] = snapshot.points_xyz[:, 1]
    block["z"] = snapshot.points_xyz[:, 2]
    block["rgb"] = snapshot.rgb
    block["confidence"] = snapshot.confidences
    block["label"] = snapshot.labels
    return block.tobytes()


def decode_cloud_data(data: bytes | np.ndarray, fields: Any, point_step: int) -> dict[str, Any]:
    """The named columns of a ``PointCloud2`` data block (the inverse of :func:`cloud_bytes`,
    reading the offsets and datatypes from ``fields``); ``rgb`` as uint32."""
    kinds = {POINT_FIELD_FLOAT32: "<f4", POINT_FIELD_UINT16: "<u2"}
    names, formats, offsets = [], [], []
    for f in fields:
        names.append(f.name)
        formats.append("<u4" if f.name == "rgb" else kinds[int(f.datatype)])
        offsets.append(int(f.offset))
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                      "itemsize": int(point_step)})
    arr = np.frombuffer(bytes(np.asarray(data, dtype=np.uint8)), dtype=dtype)
    return {name: arr[name] for name in names}


def _header(t: Any, stamp_ns: int, frame_id: str, ros1: bool, seq: int) -> Any:
    from robot_bridge.adapters.ros2 import stamp_ns_to_ros

    sec, nanosec = stamp_ns_to_ros(stamp_ns)
    stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    if ros1:
        return t["std_msgs/msg/Header"](seq=int(seq) % 2**32, stamp=stamp, frame_id=frame_id)
    return t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def point_cloud_to_ros(snapshot: MapSnapshot, *, ros1: bool = False, seq: int = 0) -> Any:
    """``snapshot``'s cloud as a ``sensor_msgs/msg/PointCloud2`` (rosbags object): one row of
    N points (unorganised), dense, little endian, fields :data:`CLOUD_FIELDS`."""
    from robot_bridge.adapters.ros2 import typestore

    t = typestore(ros1).types
    fields = [t["sensor_msgs/msg/PointField"](name=name, offset=offset, datatype=kind, count=1)
              for name, offset, kind in CLOUD_FIELDS]
    n = len(snapshot)
    return t[POINT_CLOUD2_TYPE](
        header=_header(t, snapshot.stamp_ns, snapshot.frame_id, ros1, seq),
        height=1, width=n, fields=fields, is_bigendian=False, point_step=POINT_STEP,
        row_step=POINT_STEP * n, data=np.frombuffer(cloud_bytes(snapshot), dtype=np.uint8),
        is_dense=True)


def occupancy_grid_to_ros(snapshot: MapSnapshot, *, ros1: bool = False, seq: int = 0) -> Any:
    """``snapshot``'s grid as a ``nav_msgs/msg/OccupancyGrid`` (rosbags object): origin the
    world pose of cell (0, 0)'s corner (no rotation), data row-major from it."""
    from robot_bridge.adapters.ros2 import stamp_ns_to_ros, typestore

    grid = snapshot.grid
    if grid is None:
        raise MapOutputError("the snapshot has no grid")
    t = typestore(ros1).types
    sec, nanosec = stamp_ns_to_ros(snapshot.stamp_ns)
    origin = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](
            x=grid.origin_x_m, y=grid.origin_y_m, z=grid.origin_z_m),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
        resolution=float(grid.resolution_m), width=grid.width, height=grid.height,
        origin=origin)
    return t[OCCUPANCY_GRID_TYPE](
        header=_header(t, snapshot.stamp_ns, snapshot.frame_id, ros1, seq), info=info,
        data=np.ascontiguousarray(grid.cells, dtype=np.int8).reshape(-1))


def _serialize(msg: Any, ros_type: str, ros1: bool) -> bytes:
    from robot_bridge.adapters.ros2 import typestore

    ts = typestore(ros1)
    return bytes(ts.serialize_ros1(msg, ros_type) if ros1 else ts.serialize_cdr(msg, ros_type))


def serialize_point_cloud(snapshot: MapSnapshot, *, ros1: bool = False, seq: int = 0) -> bytes:
    """Wire bytes of :func:`point_cloud_to_ros` (CDR with its header; ROS 1 when ``ros1``)."""
    return _serialize(point_cloud_to_ros(snapshot, ros1=ros1, seq=seq), POINT_CLOUD2_TYPE, ros1)


def serialize_occupancy_grid(snapshot: MapSnapshot, *, ros1: bool = False,
                             seq: int = 0) -> bytes:
    """Wire bytes of :func:`occupancy_grid_to_ros`."""
    return _serialize(occupancy_grid_to_ros(snapshot, ros1=ros1, seq=seq),
                      OCCUPANCY_GRID_TYPE, ros1)


# --------------------------------------------------------------------------------------------
# rate limit, latest only
# --------------------------------------------------------------------------------------------


class MapOutput:
    """Which map goes out when: :meth:`on_map` keeps the newest checked map (a bad one is
    counted ``invalid``, one replacing a map not yet published ``replaced``); :meth:`due`
    converts and returns it once ``1 / rate_hz`` has passed since the last one published.
    :attr:`counters` also has ``received``, ``converted``, ``conversion_failed``. Not
    thread-safe."""

    def __init__(self, config: MapOutputConfig, world_frame: str | None = None) -> None:
        self.config = config
        self.world_frame = world_frame
        self._period_ns = round(NS_PER_S / config.rate_hz) if config.rate_hz > 0 else 0
        self._next_ns = 0
        self._pending: SemanticCloud | None = None
        self.counters: dict[str, int] = {}
        self.last_conversion_s = 0.0

    def _count(self, what: str) -> None:
        self.counters[what] = self.counters.get(what, 0) + 1

    def on_map(self, cloud: object) -> bool:
        """A map message from the mapper; ``False`` (and counted) when it cannot be used."""
        self._count("received")
        try:
            checked = check_map_cloud(cloud, self.world_frame)
        except MapOutputError as exc:
            self._count("invalid")
            log.warning("map message dropped: %s", exc)
            return False
        if self._pending is not None:
            self._count("replaced")
        self._pending = checked
        return True

    def due(self, now_ns: int) -> MapSnapshot | None:
        """The map to publish at ``now_ns`` (ns), or ``None``."""
        if not self.config.enabled or self._pending is None or now_ns < self._next_ns:
            return None
        cloud, self._pending = self._pending, None
        self._next_ns = int(now_ns) + self._period_ns
        import time

        t0 = time.perf_counter()
        try:
            snapshot = map_snapshot(cloud, self.config, self.world_frame)
        except MapOutputError as exc:
            self._count("conversion_failed")
            log.warning("map not published: %s", exc)
            return None
        self.last_conversion_s = time.perf_counter() - t0
        self._count("converted")
        return snapshot
