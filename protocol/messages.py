"""The messages every smartedge service speaks.

Each message is a frozen dataclass validated on construction, so an instance that exists is a
valid message: ids are key-expression safe, stamps are non-negative nanoseconds, floats are finite
where the field requires it, arrays have the documented dtype and shape.

Frames and units (REP-103): positions in metres, angles in radians, x forward / y left / z up for
the robot base, pixel coordinates with the origin at the top-left image corner, x right, y down.
``stamp_ns`` is the sensor clock in nanoseconds since the Unix epoch (the time the observation was
made, not the send time). ``seq`` counts messages per source from 0.

See ``docs/protocol.md`` for the wire layout.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, ClassVar, Final

import numpy as np

from protocol.validation import (
    check_array,
    check_choice,
    check_covariance,
    check_float,
    check_id,
    check_int,
    check_number_map,
    check_str_tuple,
    check_text,
)

#: nanoseconds per second: every ``stamp_ns`` of the contract is an integer count of these
NS_PER_S: Final = 1_000_000_000

MAX_DETECTIONS: Final = 64
MAX_KEYPOINTS: Final = 256
MAX_CLOUD_POINTS: Final = 2_000_000
MAX_IMAGE_SIDE_PX: Final = 65_535
MAX_KEYPOINT_SIGMA_PX: Final = 1.0e4
MAX_IMAGE_BYTES: Final = 8 * 1024 * 1024
IMAGE_ENCODINGS: Final = ("jpeg",)
MAX_CAMERA_IDS: Final = 256
MAX_FLAGS: Final = 32
MAX_PEERS: Final = 4096
MAX_NUMBER_MAP_ENTRIES: Final = 256

POSE_SOURCES: Final = ("cameras", "fused", "robot", "ground_truth")
CORRECTION_KINDS: Final = ("initialization", "correction")
SERVICE_STATES: Final = ("starting", "ok", "degraded", "error", "stopping")


def _freeze(obj: Any, name: str, value: Any) -> None:
    object.__setattr__(obj, name, value)


def _readonly_f64(arr: np.ndarray) -> np.ndarray:
    """``arr`` as read-only float64 (a frozen message never hands out writeable arrays)."""
    out = arr if arr.dtype == np.float64 else arr.astype(np.float64)
    if out.flags.writeable:
        out = out.copy() if out is arr else out
        out.flags.writeable = False
    return out


def _check_image_header(msg: Any) -> None:
    """The fields every per-image message shares: camera id, stamp, seq, image size."""
    _freeze(msg, "camera_id", check_id("camera_id", msg.camera_id))
    _freeze(msg, "stamp_ns", check_int("stamp_ns", msg.stamp_ns))
    _freeze(msg, "seq", check_int("seq", msg.seq))
    _freeze(msg, "image_width",
            check_int("image_width", msg.image_width, lo=1, hi=MAX_IMAGE_SIDE_PX))
    _freeze(msg, "image_height",
            check_int("image_height", msg.image_height, lo=1, hi=MAX_IMAGE_SIDE_PX))


def _check_planar_pose(msg: Any) -> None:
    """The fields every planar pose message shares: robot id, stamp, seq, pose, covariance."""
    _freeze(msg, "robot_id", check_id("robot_id", msg.robot_id))
    _freeze(msg, "stamp_ns", check_int("stamp_ns", msg.stamp_ns))
    _freeze(msg, "seq", check_int("seq", msg.seq))
    _freeze(msg, "x", check_float("x", msg.x))
    _freeze(msg, "y", check_float("y", msg.y))
    _freeze(msg, "theta", check_float("theta", msg.theta, lo=-2 * math.pi, hi=2 * math.pi))
    _freeze(msg, "covariance", check_covariance("covariance", msg.covariance))


def _values_equal(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and bool(np.array_equal(a, b, equal_nan=a.dtype.kind == "f"))
        )
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_values_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(_values_equal(a[k], b[k]) for k in a)
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


class _Record:
    """Structural equality for dataclasses holding numpy arrays."""

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(
            _values_equal(getattr(self, f.name), getattr(other, f.name))
            for f in dataclasses.fields(self)  # type: ignore[arg-type]
        )

    __hash__ = None  # type: ignore[assignment]


class Message(_Record):
    """Base of top-level messages: each has a schema name and version on the wire."""

    SCHEMA: ClassVar[str]
    VERSION: ClassVar[int]


# --------------------------------------------------------------------------------------------
# Edge camera → backend
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Detection(_Record):
    """One detected robot in one image.

    ``keypoints_px``: (M, 2) float32/float64 pixel coordinates (u, v) of the robot model's M
    keypoints, in the order of the site file's robot model. A keypoint that was not found has
    score 0 (its coordinates are then ignored but must still be finite).
    ``keypoint_scores``: (M,) confidences in [0, 1].
    ``bbox_xyxy``: (4,) float64, [u_min, v_min, u_max, v_max] in pixels.
    ``robot_id``: which robot this is, or ``""`` when the detector cannot tell robots apart.
    ``keypoint_sigmas_px``: optional (M,) float64, the detector's own 1-sigma pixel uncertainty of
    each keypoint (> 0; the shipped keypoint network derives it from its confidence, calibrated on
    held-out renders). The backend then weights keypoints by 1/sigma^2 instead of by score.
    Optional on the wire (added without a version change: older senders omit it, older
    receivers ignore it).
    ``robot_model``: the robot model (type) the detector saw, a name of the site file's
    ``robot_models`` (same characters and length as an id), or ``""`` when unknown (one-type
    detectors, older senders). On a site with several robot types the backend assigns the
    detection only to robots of that model. Optional on the wire like ``keypoint_sigmas_px``.
    """

    bbox_xyxy: np.ndarray
    score: float
    keypoints_px: np.ndarray
    keypoint_scores: np.ndarray
    robot_id: str = ""
    keypoint_sigmas_px: np.ndarray | None = None
    robot_model: str = ""

    def __post_init__(self) -> None:
        bbox = check_array("bbox_xyxy", self.bbox_xyxy, dtypes=("float64", "float32"), shape=(4,))
        if bbox[2] < bbox[0] or bbox[3] < bbox[1]:
            raise_field("bbox_xyxy", "max corner is smaller than min corner")
        _freeze(self, "bbox_xyxy", _readonly_f64(bbox))
        _freeze(self, "score", check_float("score", self.score, lo=0.0, hi=1.0))
        kps = check_array(
            "keypoints_px", self.keypoints_px, dtypes=("float32", "float64"), shape=(None, 2)
        )
        if kps.shape[0] > MAX_KEYPOINTS:
            raise_field("keypoints_px", f"more than {MAX_KEYPOINTS} keypoints")
        scores = check_array(
            "keypoint_scores",
            self.keypoint_scores,
            dtypes=("float32", "float64"),
            shape=(kps.shape[0],),
        )
        if scores.size and (scores.min() < 0.0 or scores.max() > 1.0):
            raise_field("keypoint_scores", "scores must lie in [0, 1]")
        _freeze(self, "keypoints_px", kps)
        _freeze(self, "keypoint_scores", scores)
        _freeze(self, "robot_id", check_id("robot_id", self.robot_id, allow_empty=True))
        if self.keypoint_sigmas_px is not None:
            sig = check_array("keypoint_sigmas_px", self.keypoint_sigmas_px,
                              dtypes=("float32", "float64"), shape=(kps.shape[0],))
            if sig.size and not (np.all(np.isfinite(sig)) and sig.min() > 0.0
                                 and sig.max() <= MAX_KEYPOINT_SIGMA_PX):
                raise_field("keypoint_sigmas_px",
                            f"sigmas must be finite, > 0 and <= {MAX_KEYPOINT_SIGMA_PX:g} px")
            _freeze(self, "keypoint_sigmas_px", _readonly_f64(sig))
        _freeze(self, "robot_model", check_id("robot_model", self.robot_model, allow_empty=True))


@dataclasses.dataclass(frozen=True, eq=False)
class RobotDetections(Message):
    """Robot detections of one camera image (possibly none: an empty list says "no robot seen").

    ``image_width``/``image_height``: size in pixels of the image the keypoints refer to.
    ``model_id``: which detector/keypoint model produced them (for provenance).
    """

    SCHEMA: ClassVar[str] = "RobotDetections"
    VERSION: ClassVar[int] = 1

    camera_id: str
    stamp_ns: int
    seq: int
    image_width: int
    image_height: int
    model_id: str
    detections: tuple[Detection, ...] = ()

    def __post_init__(self) -> None:
        _check_image_header(self)
        _freeze(self, "model_id", check_text("model_id", self.model_id, max_len=128))
        dets = self.detections
        if isinstance(dets, Detection) or not isinstance(dets, (list, tuple)):
            raise_field("detections", "expected a list of Detection")
        if len(dets) > MAX_DETECTIONS:
            raise_field("detections", f"more than {MAX_DETECTIONS} detections")
        for i, det in enumerate(dets):
            if not isinstance(det, Detection):
                raise_field(f"detections[{i}]", f"expected Detection, got {type(det).__name__}")
        _freeze(self, "detections", tuple(dets))


@dataclasses.dataclass(frozen=True, eq=False)
class SemanticCloud(Message):
    """A semantic point cloud from a static edge sensor or a robot.

    ``points_xyz``: (N, 3) float32, metres, expressed in ``frame_id``.
    ``class_ids``: (N,) uint8 or uint16 semantic class per point.
    ``confidences``: (N,) float32 in [0, 1].
    ``T_frame_sensor``: optional (4, 4) float64 pose of the sensor in ``frame_id`` (maps sensor
    coordinates to ``frame_id`` coordinates); ``None`` when unknown.
    """

    SCHEMA: ClassVar[str] = "SemanticCloud"
    VERSION: ClassVar[int] = 1

    sensor_id: str
    stamp_ns: int
    seq: int
    frame_id: str
    points_xyz: np.ndarray
    class_ids: np.ndarray
    confidences: np.ndarray
    T_frame_sensor: np.ndarray | None = None

    def __post_init__(self) -> None:
        _freeze(self, "sensor_id", check_id("sensor_id", self.sensor_id))
        _freeze(self, "stamp_ns", check_int("stamp_ns", self.stamp_ns))
        _freeze(self, "seq", check_int("seq", self.seq))
        _freeze(self, "frame_id", check_id("frame_id", self.frame_id))
        pts = check_array(
            "points_xyz",
            self.points_xyz,
            dtypes=("float32",),
            shape=(None, 3),
            max_elems=3 * MAX_CLOUD_POINTS,
        )
        n = pts.shape[0]
        cls = check_array("class_ids", self.class_ids, dtypes=("uint8", "uint16"), shape=(n,))
        conf = check_array("confidences", self.confidences, dtypes=("float32",), shape=(n,))
        if np.any(conf < 0.0) or np.any(conf > 1.0):
            raise_field("confidences", "confidences must lie in [0, 1]")
        _freeze(self, "points_xyz", pts)
        _freeze(self, "class_ids", cls)
        _freeze(self, "confidences", conf)
        if self.T_frame_sensor is not None:
            T = check_array(
                "T_frame_sensor", self.T_frame_sensor, dtypes=("float64", "float32"), shape=(4, 4)
            ).astype(np.float64)
            T.setflags(write=False)
            _freeze(self, "T_frame_sensor", T)


# --------------------------------------------------------------------------------------------
# Robot ↔ backend
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Odometry(Message):
    """The robot's own planar pose in its odometry frame, with body velocities.

    ``x``, ``y`` in metres and ``theta`` in radians (normalised to [-pi, pi)) of the base in the
    odom frame; ``vx``, ``vy`` (m/s) and ``wz`` (rad/s) in the base frame.
    ``covariance``: (3, 3) of (x, y, theta), SI units.
    """

    SCHEMA: ClassVar[str] = "Odometry"
    VERSION: ClassVar[int] = 1

    robot_id: str
    stamp_ns: int
    seq: int
    x: float
    y: float
    theta: float
    vx: float = 0.0
    vy: float = 0.0
    wz: float = 0.0
    covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((3, 3)))
    frame_id: str = "odom"

    def __post_init__(self) -> None:
        _check_planar_pose(self)
        for name in ("vx", "vy", "wz"):
            _freeze(self, name, check_float(name, getattr(self, name)))
        _freeze(self, "frame_id", check_id("frame_id", self.frame_id))


@dataclasses.dataclass(frozen=True, eq=False)
class PoseEstimate(Message):
    """An allocentric planar pose of a robot in the world (map) frame.

    ``source``: ``"cameras"`` (multi-view keypoint solve of one frame-set or an average of a few),
    ``"fused"`` (pose graph of camera estimates and odometry), ``"robot"`` (the robot's own
    localization, as reported by the robot bridge) or ``"ground_truth"`` (simulation only).
    ``camera_ids``: the cameras whose detections went into the estimate.
    ``reprojection_rmse_px``: weighted RMS reprojection error of the solve; NaN for fused poses.
    ``flags``: short identifiers qualifying the estimate, e.g. ``single_camera``,
    ``lateral_only`` (single-camera heuristic limited the update), ``pnp_init``, ``prior_init``,
    ``multi_frame``, ``robust_loss``, ``6dof``.
    """

    SCHEMA: ClassVar[str] = "PoseEstimate"
    VERSION: ClassVar[int] = 1

    robot_id: str
    stamp_ns: int
    seq: int
    x: float
    y: float
    theta: float
    covariance: np.ndarray
    source: str
    camera_ids: tuple[str, ...] = ()
    reprojection_rmse_px: float = math.nan
    flags: tuple[str, ...] = ()
    frame_id: str = "map"

    def __post_init__(self) -> None:
        _check_planar_pose(self)
        _freeze(self, "source", check_choice("source", self.source, POSE_SOURCES))
        _freeze(self, "camera_ids",
                check_str_tuple("camera_ids", self.camera_ids, max_items=MAX_CAMERA_IDS))
        _freeze(
            self,
            "reprojection_rmse_px",
            check_float("reprojection_rmse_px", self.reprojection_rmse_px, lo=0.0, finite=False),
        )
        _freeze(self, "flags", check_str_tuple("flags", self.flags, max_items=MAX_FLAGS))
        _freeze(self, "frame_id", check_id("frame_id", self.frame_id))

    def numbered(self, seq: int, frame_id: str) -> PoseEstimate:
        """This estimate as its publisher numbers it: ``seq`` and ``frame_id`` replaced. Only
        those two are checked; every other field was checked when this instance was built and
        is shared (read-only), where ``dataclasses.replace`` would validate it all again."""
        out = object.__new__(PoseEstimate)
        out.__dict__.update(self.__dict__)
        _freeze(out, "seq", check_int("seq", seq))
        _freeze(out, "frame_id", check_id("frame_id", frame_id))
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class PoseCorrection(Message):
    """A pose to set the robot's own localization to (sent only while the robot is static).

    ``stamp_ns`` is the time the pose refers to (the camera estimate's time), not the send time,
    so a localizer that compensates motion between stamp and now (AMCL) does the right thing.
    ``kind``: ``"initialization"`` (kidnapped robot / first pose) or ``"correction"``.
    ``offset_m`` / ``offset_rad``: how far the robot's own localization was from this pose.
    """

    SCHEMA: ClassVar[str] = "PoseCorrection"
    VERSION: ClassVar[int] = 1

    robot_id: str
    stamp_ns: int
    seq: int
    x: float
    y: float
    theta: float
    covariance: np.ndarray
    kind: str
    offset_m: float = 0.0
    offset_rad: float = 0.0
    frame_id: str = "map"

    def __post_init__(self) -> None:
        _check_planar_pose(self)
        _freeze(self, "kind", check_choice("kind", self.kind, CORRECTION_KINDS))
        _freeze(self, "offset_m", check_float("offset_m", self.offset_m, lo=0.0))
        _freeze(self, "offset_rad", check_float("offset_rad", self.offset_rad, lo=0.0))
        _freeze(self, "frame_id", check_id("frame_id", self.frame_id))


# --------------------------------------------------------------------------------------------
# Every service → monitoring
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class ServiceStatus(Message):
    """Health of one service instance, published once per second.

    ``service``: ``edge-agent``, ``backend`` or ``robot-bridge``; ``instance_id`` its id
    (camera id, robot id, host name...). ``rates_hz``: message rates by stream name.
    ``latency_p50_ms``/``latency_p99_ms``: latencies by stage name. ``counters``: monotonically
    increasing event counts (``received``, ``invalid``, ``dropped``, ``unknown_camera``...).
    ``peers_alive``: ids of the peers the service currently sees (cameras, robots, backend).
    """

    SCHEMA: ClassVar[str] = "ServiceStatus"
    VERSION: ClassVar[int] = 1

    service: str
    instance_id: str
    stamp_ns: int
    seq: int
    state: str = "ok"
    uptime_s: float = 0.0
    rates_hz: Mapping[str, float] = dataclasses.field(default_factory=dict)
    latency_p50_ms: Mapping[str, float] = dataclasses.field(default_factory=dict)
    latency_p99_ms: Mapping[str, float] = dataclasses.field(default_factory=dict)
    counters: Mapping[str, int] = dataclasses.field(default_factory=dict)
    peers_alive: tuple[str, ...] = ()
    detail: str = ""

    def __post_init__(self) -> None:
        _freeze(self, "service", check_id("service", self.service))
        _freeze(self, "instance_id", check_id("instance_id", self.instance_id))
        _freeze(self, "stamp_ns", check_int("stamp_ns", self.stamp_ns))
        _freeze(self, "seq", check_int("seq", self.seq))
        _freeze(self, "state", check_choice("state", self.state, SERVICE_STATES))
        _freeze(self, "uptime_s", check_float("uptime_s", self.uptime_s, lo=0.0))
        for name in ("rates_hz", "latency_p50_ms", "latency_p99_ms"):
            _freeze(self, name, MappingProxyType(dict(check_number_map(
                name, getattr(self, name), max_items=MAX_NUMBER_MAP_ENTRIES))))
        _freeze(
            self,
            "counters",
            MappingProxyType(dict(check_number_map("counters", self.counters, integer=True,
                                                   max_items=MAX_NUMBER_MAP_ENTRIES))),
        )
        _freeze(self, "peers_alive",
                check_str_tuple("peers_alive", self.peers_alive, max_items=MAX_PEERS))
        _freeze(self, "detail", check_text("detail", self.detail))


@dataclasses.dataclass(frozen=True, eq=False)
class CameraImage(Message):
    """A preview of one camera frame for people (the viewer), not for the pipeline: the frame a
    :class:`RobotDetections` with the same ``camera_id`` and ``stamp_ns`` came from.

    ``encoding``: ``"jpeg"``; ``data``: (N,) uint8, the encoded image (at most
    :data:`MAX_IMAGE_BYTES`); ``image_width`` / ``image_height``: its size in pixels (the
    detections' pixel coordinates refer to it).
    """

    SCHEMA: ClassVar[str] = "CameraImage"
    VERSION: ClassVar[int] = 1

    camera_id: str
    stamp_ns: int
    seq: int
    image_width: int
    image_height: int
    encoding: str
    data: np.ndarray

    def __post_init__(self) -> None:
        _check_image_header(self)
        _freeze(self, "encoding", check_choice("encoding", self.encoding, IMAGE_ENCODINGS))
        data = check_array("data", self.data, dtypes=("uint8",), shape=(None,),
                           max_elems=MAX_IMAGE_BYTES)
        if data.size == 0:
            raise_field("data", "empty image")
        _freeze(self, "data", data)


#: most entries of each list or map field, by (schema or nested record name, field): the codec
#: reads them from the msgpack headers and refuses a payload before building its entries
MAX_ENTRIES: Final[Mapping[tuple[str, str], int]] = MappingProxyType({
    ("RobotDetections", "detections"): MAX_DETECTIONS,
    ("PoseEstimate", "camera_ids"): MAX_CAMERA_IDS,
    ("PoseEstimate", "flags"): MAX_FLAGS,
    ("ServiceStatus", "rates_hz"): MAX_NUMBER_MAP_ENTRIES,
    ("ServiceStatus", "latency_p50_ms"): MAX_NUMBER_MAP_ENTRIES,
    ("ServiceStatus", "latency_p99_ms"): MAX_NUMBER_MAP_ENTRIES,
    ("ServiceStatus", "counters"): MAX_NUMBER_MAP_ENTRIES,
    ("ServiceStatus", "peers_alive"): MAX_PEERS,
})

MESSAGE_TYPES: Final[tuple[type[Message], ...]] = (
    RobotDetections,
    CameraImage,
    SemanticCloud,
    Odometry,
    PoseEstimate,
    PoseCorrection,
    ServiceStatus,
)


def raise_field(field: str, reason: str) -> None:
    from protocol.errors import ValidationError

    raise ValidationError(field, reason)
