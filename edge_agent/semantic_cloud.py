"""Semantic point clouds from an RGB-D frame and its segmentation (pure numpy, no transport).

A static edge camera and the robot's head camera both turn a frame into a
:class:`protocol.messages.SemanticCloud` the same way (paper Sec. III-C):

1. the segmentation network labels the colour image at its own output resolution (h, w);
   output pixel (i, j) covers image pixel centre ``((j + 0.5) W / w - 0.5, (i + 0.5) H / h -
   0.5)`` of the W x H image;
2. each output pixel takes the depth of the image pixel nearest that centre and is
   back-projected along that image pixel's ray (the lens distortion undone exactly, see
   :func:`core.geometry.undistort_normalized`), so depth and ray belong to the same pixel;
3. points are filtered (no depth, range, confidence, dynamic classes), transformed into
   ``frame_id`` with ``T_frame_sensor``, voxel-downsampled on a grid aligned with ``frame_id``
   (per voxel: the mean point, the majority class, the mean confidence of the points of that
   class) and capped in count.

Frame convention (the backend relies on it): a static camera publishes in the site's world frame
(``frame_id`` = the site's ``world_frame``, ``T_frame_sensor`` = the calibrated ``T_world_cam``);
a robot's head camera publishes in ``base_link`` (``T_frame_sensor`` = ``T_base_cam``), and the
backend places it with the fused pose at the cloud's stamp.

:class:`SemanticCloudMaker` wraps segmenter + builder + rate for one sensor; the edge agent and
the simulated robot camera use it.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Final

import numpy as np

from core.camera import CameraModel
from core.geometry import undistort_normalized
from protocol.messages import MAX_CLOUD_POINTS, SemanticCloud
from protocol.semantic_classes import SEMANTIC_CLASS_ID, SEMANTIC_CLASSES

if TYPE_CHECKING:
    from edge_agent.networks import Segmentation

log = logging.getLogger(__name__)

#: the robot's own frame, in which a robot's head camera publishes its clouds
ROBOT_BASE_FRAME: Final = "base_link"
#: largest ``max_points`` a config may ask for (well below the protocol's limit: a cloud a
#: second of this size is already ~1.5 MB on the wire)
MAX_POINTS_LIMIT: Final = MAX_CLOUD_POINTS // 10
#: frames a service cannot make a cloud of that are logged in full (then only counted)
BAD_FRAMES_LOGGED: Final = 5


@dataclasses.dataclass(frozen=True)
class SemanticCloudConfig:
    """How a frame becomes a cloud.

    ``voxel_m``: edge of the downsampling voxels in ``frame_id`` (0: no downsampling).
    ``min_confidence``: pixels whose class confidence is below are dropped. ``min_range_m`` /
    ``max_range_m``: Euclidean distance from the sensor kept (a depth camera's useful range; its
    noise grows with the square of the distance). ``max_points``: the cloud is capped at this
    many points (an even subsample of the voxels, in grid order). ``drop_classes``: class names
    (:data:`protocol.semantic_classes.SEMANTIC_CLASSES`) never sent: dynamic things and
    unlabeled pixels do not belong in the static map.
    """

    voxel_m: float = 0.05
    min_confidence: float = 0.4
    min_range_m: float = 0.3
    max_range_m: float = 6.0
    max_points: int = 50_000
    drop_classes: tuple[str, ...] = ("unlabeled", "person", "robot")

    def __post_init__(self) -> None:
        if not (math.isfinite(self.voxel_m) and 0.0 <= self.voxel_m <= 10.0):
            raise ValueError(f"voxel_m: {self.voxel_m} outside [0, 10] m")
        if not 0.0 <= self.min_confidence <= 1.0:
            raise ValueError(f"min_confidence: {self.min_confidence} outside [0, 1]")
        if not (math.isfinite(self.min_range_m) and self.min_range_m >= 0.0):
            raise ValueError(f"min_range_m: {self.min_range_m} must be >= 0")
        if not (math.isfinite(self.max_range_m) and self.max_range_m > self.min_range_m):
            raise ValueError(f"max_range_m: {self.max_range_m} must be finite and above "
                             f"min_range_m ({self.min_range_m})")
        if isinstance(self.max_points, bool) or not isinstance(self.max_points, int) or not (
                1 <= self.max_points <= MAX_POINTS_LIMIT):
            raise ValueError(f"max_points: {self.max_points!r} must be an int in "
                             f"[1, {MAX_POINTS_LIMIT}]")
        names = (self.drop_classes,) if isinstance(self.drop_classes, str) else self.drop_classes
        unknown = [n for n in names if n not in SEMANTIC_CLASS_ID]
        if unknown:
            raise ValueError(f"drop_classes: unknown class(es) {unknown}; known: "
                             f"{list(SEMANTIC_CLASSES)}")
        object.__setattr__(self, "drop_classes", tuple(names))

    @property
    def drop_class_ids(self) -> tuple[int, ...]:
        return tuple(SEMANTIC_CLASS_ID[n] for n in self.drop_classes)


# --------------------------------------------------------------------------------------------
# pixel grid
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class PixelRays:
    """Where the (h, w) output pixels of a segmentation sample a W x H image.

    ``pixel_index``: (h * w,) int64 flat index (``v * W + u``) of the image pixel nearest each
    output pixel's centre, row-major over the output. ``rays``: (h * w, 2) float64 undistorted
    normalized coordinates (x/z, y/z in the camera optical frame) of that image pixel; NaN where
    the lens model has no preimage.
    """

    pixel_index: np.ndarray
    rays: np.ndarray


def output_pixel_centres(out_w: int, out_h: int, image_w: int, image_h: int
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(out_w,) u and (out_h,) v: the image pixel coordinates of the output pixels' centres,
    ``(j + 0.5) * W / w - 0.5`` and ``(i + 0.5) * H / h - 0.5``."""
    u = (np.arange(out_w) + 0.5) * (image_w / out_w) - 0.5
    v = (np.arange(out_h) + 0.5) * (image_h / out_h) - 0.5
    return u, v


def pixel_rays(camera: CameraModel, out_w: int, out_h: int) -> PixelRays:
    """The :class:`PixelRays` of ``camera`` for an (out_h, out_w) output (cached per camera
    intrinsics and sizes: the exact undistortion of a VGA grid takes a fraction of a second)."""
    return _pixel_rays(camera.K.tobytes(), camera.dist.tobytes(), camera.width, camera.height,
                       int(out_w), int(out_h))


@functools.lru_cache(maxsize=16)
def _pixel_rays(K_bytes: bytes, dist_bytes: bytes, width: int, height: int, out_w: int,
                out_h: int) -> PixelRays:
    K = np.frombuffer(K_bytes, np.float64).reshape(3, 3)
    dist = np.frombuffer(dist_bytes, np.float64)
    u, v = output_pixel_centres(out_w, out_h, width, height)
    # nearest image pixel; floor(x + 0.5) rounds halves up on both axes alike
    ui = np.clip(np.floor(u + 0.5), 0, width - 1).astype(np.int64)
    vi = np.clip(np.floor(v + 0.5), 0, height - 1).astype(np.int64)
    uu, vv = np.meshgrid(ui, vi)
    index = (vv * width + uu).ravel()
    # K^-1 [u, v, 1] with skew, then the lens undone
    y_d = (vv.ravel() - K[1, 2]) / K[1, 1]
    x_d = (uu.ravel() - K[0, 2] - K[0, 1] * y_d) / K[0, 0]
    rays = undistort_normalized(np.stack([x_d, y_d], axis=-1), dist)
    for arr in (index, rays):
        arr.setflags(write=False)
    return PixelRays(index, rays)


# --------------------------------------------------------------------------------------------
# the cloud
# --------------------------------------------------------------------------------------------


def _check_inputs(segmentation: Segmentation, depth_m: np.ndarray, camera: CameraModel
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    class_ids = segmentation.class_ids
    confidence = segmentation.confidence
    if not isinstance(class_ids, np.ndarray) or class_ids.ndim != 2 or class_ids.dtype not in (
            np.uint8, np.uint16):
        raise ValueError(f"segmentation.class_ids: expected an (h, w) uint8 array, got "
                         f"{_describe(class_ids)}")
    if class_ids.size == 0:
        raise ValueError("segmentation.class_ids: empty")
    if not isinstance(confidence, np.ndarray) or confidence.shape != class_ids.shape or \
            confidence.dtype.kind != "f":
        raise ValueError(f"segmentation.confidence: expected a float32 array of shape "
                         f"{class_ids.shape} (as class_ids), got {_describe(confidence)}")
    size = (segmentation.image_width, segmentation.image_height)
    if size != (camera.width, camera.height):
        raise ValueError(f"segmentation.image_width/image_height: {size[0]}x{size[1]}, the "
                         f"camera {camera.camera_id} is {camera.width}x{camera.height}")
    if not isinstance(depth_m, np.ndarray) or depth_m.shape != (camera.height, camera.width) \
            or depth_m.dtype.kind != "f":
        raise ValueError(f"depth_m: expected a float32 array of shape "
                         f"{(camera.height, camera.width)} (the camera's image), got "
                         f"{_describe(depth_m)}")
    return class_ids, confidence, depth_m


def _describe(arr: Any) -> str:
    if isinstance(arr, np.ndarray):
        return f"{arr.dtype} {arr.shape}"
    return type(arr).__name__


def back_project(segmentation: Segmentation, depth_m: np.ndarray, camera: CameraModel
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every output pixel with usable depth as a 3D point, unfiltered otherwise.

    Returns ``points_cam`` (N, 3) float64 in the camera optical frame (metres), ``class_ids``
    (N,) and ``confidence`` (N,) float32. Depth 0, inf or NaN and pixels without a lens
    preimage are left out. Raises ``ValueError`` naming the field for wrong shapes or dtypes.
    """
    class_ids, confidence, depth = _check_inputs(segmentation, depth_m, camera)
    h, w = class_ids.shape
    grid = pixel_rays(camera, w, h)
    z = np.asarray(depth).reshape(-1)[grid.pixel_index].astype(np.float64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(z) & (z > 0.0) & np.isfinite(grid.rays[:, 0])
    rays = grid.rays[ok]
    z = z[ok]
    points = np.empty((z.size, 3))
    points[:, 0] = rays[:, 0] * z
    points[:, 1] = rays[:, 1] * z
    points[:, 2] = z
    return (points, class_ids.reshape(-1)[ok],
            np.asarray(confidence, np.float32).reshape(-1)[ok])


def voxel_downsample(points: np.ndarray, class_ids: np.ndarray, confidence: np.ndarray,
                     voxel_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One point per occupied voxel of edge ``voxel_m`` on the grid aligned with the points'
    frame (voxel ``floor(p / voxel_m)``).

    Per voxel: the mean of its points, the majority class (ties: the lower id) and the mean
    confidence of the points of that class. Returns (M, 3) float64 points, (M,) classes (the
    input's dtype), (M,) float32 confidences and (M,) int64 point counts, in voxel-grid order.
    """
    n = points.shape[0]
    if n == 0:
        return (np.zeros((0, 3)), class_ids[:0], np.zeros(0, np.float32),
                np.zeros(0, np.int64))
    cells = np.floor(points / voxel_m).astype(np.int64)
    cells -= cells.min(axis=0)
    dims = cells.max(axis=0) + 1
    cls = class_ids.astype(np.int64)
    num_cls = int(cls.max()) + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) * num_cls < 2.0**62:
        keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    else:  # a cloud kilometres across: number the occupied voxels first
        _, keys = np.unique(cells, axis=0, return_inverse=True)
        keys = keys.reshape(-1)
    # one sort for everything: (voxel, class) pairs in ascending order, so the pairs of one
    # voxel are adjacent and in ascending class order
    pair_keys, pair_inverse, pair_counts = np.unique(keys * num_cls + cls, return_inverse=True,
                                                     return_counts=True)
    pair_voxel_key = pair_keys // num_cls
    starts = np.flatnonzero(np.r_[True, pair_voxel_key[1:] != pair_voxel_key[:-1]])
    pair_voxel = np.cumsum(np.r_[True, pair_voxel_key[1:] != pair_voxel_key[:-1]]) - 1
    m = starts.size
    inverse = pair_voxel[pair_inverse.reshape(-1)]
    counts = np.bincount(pair_voxel, pair_counts, m).astype(np.int64)
    mean = np.stack([np.bincount(inverse, points[:, k], m) for k in range(3)], axis=1)
    mean /= counts[:, None]
    pair_conf = np.bincount(pair_inverse.reshape(-1), confidence.astype(np.float64),
                            pair_keys.size)
    # per voxel the first pair (lowest class id) with the most points
    best = np.maximum.reduceat(pair_counts, starts)
    is_best = np.flatnonzero(pair_counts == best[pair_voxel])
    first = is_best[np.r_[True, pair_voxel[is_best][1:] != pair_voxel[is_best][:-1]]]
    majority = (pair_keys[first] % num_cls).astype(class_ids.dtype)
    conf = (pair_conf[first] / pair_counts[first]).astype(np.float32)
    return mean, majority, conf, counts


def build_semantic_cloud(
    segmentation: Segmentation,
    depth_m: np.ndarray,
    camera: CameraModel,
    *,
    sensor_id: str,
    stamp_ns: int,
    seq: int,
    frame_id: str,
    T_frame_sensor: np.ndarray | None,
    config: SemanticCloudConfig | None = None,
) -> SemanticCloud:
    """A :class:`SemanticCloud` from one RGB-D frame's segmentation.

    ``segmentation``: an :class:`edge_agent.networks.Segmentation` of the W x H colour image
    (``class_ids`` (h, w) uint8, ``confidence`` (h, w) float32, any output scale).
    ``depth_m``: (H, W) float32 z in the camera optical frame, metres, aligned to the colour
    image; 0, inf or NaN = no depth. ``camera``: the colour camera's intrinsics and distortion
    (its extrinsics are not used). ``T_frame_sensor``: (4, 4) camera optical frame →
    ``frame_id``; the points are transformed with it and it is sent along (``None``: points
    stay in the optical frame, and ``frame_id`` must name it). Returns points in ``frame_id``
    (float32, metres), one per occupied voxel, at most ``config.max_points``.

    Raises ``ValueError`` naming the field for wrong shapes or dtypes.
    """
    config = config or SemanticCloudConfig()
    points, cls, conf = back_project(segmentation, depth_m, camera)
    r = np.linalg.norm(points, axis=1)
    keep = (r >= config.min_range_m) & (r <= config.max_range_m)
    with np.errstate(invalid="ignore"):
        keep &= conf >= config.min_confidence  # NaN confidence: dropped
    if config.drop_classes:
        keep &= ~np.isin(cls, config.drop_class_ids)
    points, cls, conf = points[keep], cls[keep], conf[keep]
    T = None
    if T_frame_sensor is not None:
        T = np.asarray(T_frame_sensor, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"T_frame_sensor: expected a finite (4, 4) transform, got "
                             f"{_describe(T)}")
        points = points @ T[:3, :3].T + T[:3, 3]
    if config.voxel_m > 0.0:
        points, cls, conf, _ = voxel_downsample(points, cls, conf, config.voxel_m)
    if points.shape[0] > config.max_points:
        pick = np.linspace(0, points.shape[0] - 1, config.max_points).round().astype(np.int64)
        points, cls, conf = points[pick], cls[pick], conf[pick]
    return SemanticCloud(
        sensor_id=sensor_id,
        stamp_ns=int(stamp_ns),
        seq=int(seq),
        frame_id=frame_id,
        points_xyz=np.ascontiguousarray(points, dtype=np.float32),
        class_ids=np.ascontiguousarray(cls),
        confidences=np.clip(np.ascontiguousarray(conf, dtype=np.float32), 0.0, 1.0),
        T_frame_sensor=T,
    )


# --------------------------------------------------------------------------------------------
# one sensor: segmenter + builder + rate
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class CloudTiming:
    """Milliseconds of one cloud: the segmentation network and the cloud building."""

    segmentation_ms: float
    cloud_ms: float


class SemanticCloudMaker:
    """The clouds of one RGB-D sensor at ``rate_hz``.

    ``segmenter``: image (H, W, 3) uint8 RGB → :class:`edge_agent.networks.Segmentation` (the
    :class:`edge_agent.networks.SemanticSegmenter`). ``camera``: the colour camera (intrinsics,
    distortion, size). ``frame_id`` / ``T_frame_sensor``: see :func:`build_semantic_cloud` (a
    static camera: the site's world frame and ``camera.T_world_cam``; a robot:
    :data:`ROBOT_BASE_FRAME` and ``T_base_cam``). Frames are due by their stamps: the first one,
    then each at least ``1 / rate_hz`` after the last one taken. ``seq`` counts the clouds made.
    """

    def __init__(self, segmenter: Callable[[np.ndarray], Segmentation], camera: CameraModel, *,
                 sensor_id: str, frame_id: str, T_frame_sensor: np.ndarray | None,
                 rate_hz: float = 1.0, config: SemanticCloudConfig | None = None) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"cloud rate {rate_hz} Hz: must be > 0")
        self.segmenter = segmenter
        self.camera = camera
        self.sensor_id = sensor_id
        self.frame_id = frame_id
        self.T_frame_sensor = None if T_frame_sensor is None else np.array(
            T_frame_sensor, dtype=np.float64)
        self.rate_hz = float(rate_hz)
        self.config = config or SemanticCloudConfig()
        self._period_ns = round(1e9 / self.rate_hz)
        self._last_stamp_ns: int | None = None
        self.seq = 0
        self._bad_frames = 0

    def due(self, stamp_ns: int) -> bool:
        """Whether a frame taken at ``stamp_ns`` should become a cloud."""
        last = self._last_stamp_ns
        return last is None or stamp_ns - last >= self._period_ns or stamp_ns < last

    def make(self, image_rgb: np.ndarray, depth_m: np.ndarray, stamp_ns: int
             ) -> tuple[SemanticCloud, CloudTiming]:
        """Segment ``image_rgb`` and build the cloud stamped ``stamp_ns`` (marks it taken,
        also when it raises ``ValueError`` on bad input)."""
        self._last_stamp_ns = stamp_ns
        t0 = time.perf_counter()
        segmentation = self.segmenter(image_rgb)
        t1 = time.perf_counter()
        cloud = build_semantic_cloud(
            segmentation, depth_m, self.camera, sensor_id=self.sensor_id, stamp_ns=stamp_ns,
            seq=self.seq, frame_id=self.frame_id, T_frame_sensor=self.T_frame_sensor,
            config=self.config)
        t2 = time.perf_counter()
        self.seq += 1
        return cloud, CloudTiming((t1 - t0) * 1e3, (t2 - t1) * 1e3)

    def make_for_service(self, image_rgb: np.ndarray, depth_m: np.ndarray, stamp_ns: int,
                         stats: Any) -> SemanticCloud | None:
        """:meth:`make` with a service's bookkeeping on ``stats`` (a
        :class:`core.runtime.Stats`): segmentation and cloud latencies, the counters
        ``clouds_published``, ``cloud_points``, ``clouds_skipped_empty`` and
        ``clouds_skipped_bad_input`` (the first :data:`BAD_FRAMES_LOGGED` such frames logged).
        Returns the cloud to publish, or ``None``."""
        try:
            cloud, timing = self.make(image_rgb, depth_m, stamp_ns)
        except ValueError as exc:  # a frame the network or the builder cannot take
            stats.count("clouds_skipped_bad_input")
            self._bad_frames += 1
            if self._bad_frames <= BAD_FRAMES_LOGGED:
                log.warning("%s: no cloud from the frame at %d ns: %s", self.sensor_id,
                            stamp_ns, exc)
            return None
        stats.latency("segmentation", timing.segmentation_ms * 1e-3)
        stats.latency("cloud", timing.cloud_ms * 1e-3)
        if len(cloud.points_xyz) == 0:
            stats.count("clouds_skipped_empty")
            return None
        stats.count("clouds_published")
        stats.count("cloud_points", len(cloud.points_xyz))
        stats.event("clouds")
        return cloud
