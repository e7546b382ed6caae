"""ROS 2 schemas and CDR payloads for ``smartedge record``: what Foxglove and ``ros2 bag`` read.

Every recorded key gets up to two MCAP channels (message encoding ``cdr``, schema encoding
``ros2msg``):

* ``/_smartedge_wire/<key>`` — ``smartedge_msgs/msg/Wire``: the msgpack payload exactly as it
  was published. ``smartedge replay`` and :func:`smartedge.commands.record.read_recording` read only
  these, so a replay publishes byte for byte what was live (a ROS message cannot carry every
  field of ours: source, flags, camera ids, NaNs...). A leading ``_`` makes them hidden topics
  in ROS 2 tools.
* ``/<key>`` — the message as a ROS 2 type, for the tools: standard types where they exist
  (:data:`ROS_TYPES`), ``smartedge_msgs`` for detections. Payloads that do not decode as a
  smartedge message get the wire channel only.

The ``smartedge_msgs`` definitions are the ``.msg`` files under ``smartedge/ros_msgs``.
"""

from __future__ import annotations

import functools
import re
import struct
from pathlib import Path
from typing import Any, Final

import numpy as np

from core.geometry import yaw_to_quaternion
from protocol.messages import (
    NS_PER_S,
    CameraImage,
    Message,
    Odometry,
    PoseCorrection,
    PoseEstimate,
    RobotDetections,
    SemanticCloud,
    ServiceStatus,
)

MSG_DIR: Final = Path(__file__).resolve().parent / "ros_msgs"
WIRE_TYPE: Final = "smartedge_msgs/msg/Wire"
WIRE_PREFIX: Final = "/_smartedge_wire"
#: channel metadata entry holding the Zenoh key a channel was recorded from
KEY_METADATA: Final = "smartedge_key"
#: the ROS 2 type each smartedge message becomes
ROS_TYPES: Final[dict[type[Message], str]] = {
    PoseEstimate: "geometry_msgs/msg/PoseWithCovarianceStamped",
    PoseCorrection: "geometry_msgs/msg/PoseWithCovarianceStamped",
    Odometry: "nav_msgs/msg/Odometry",
    ServiceStatus: "diagnostic_msgs/msg/DiagnosticArray",
    CameraImage: "sensor_msgs/msg/CompressedImage",
    SemanticCloud: "sensor_msgs/msg/PointCloud2",
    RobotDetections: "smartedge_msgs/msg/RobotDetections",
}
#: the pose types :func:`pose_from_ros` reads (a foreign recording's motion capture, say)
POSE_TYPES: Final = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
    "nav_msgs/msg/Odometry",
)
#: CDR encapsulation header, little endian (what rosbags and rclcpp write)
_CDR_LE: Final = b"\x00\x01\x00\x00"
_TOPIC_BAD_CHARS: Final = re.compile(r"[^A-Za-z0-9_/]")
_LEVELS: Final = {"starting": 0, "ok": 0, "degraded": 1, "error": 2, "stopping": 3}


class RosRecordError(ValueError):
    """A payload cannot be converted to / read from its ROS 2 form; the message says why."""


def ros_topic(key: str) -> str:
    """A smartedge key as a valid ROS 2 topic name: ``/`` first, ``-`` and ``.`` as ``_``, a
    ``_`` before a name part that starts with a digit."""
    parts = _TOPIC_BAD_CHARS.sub("_", key).split("/")
    return "/" + "/".join("_" + part if part[:1].isdigit() else part for part in parts)


def wire_topic(key: str) -> str:
    return WIRE_PREFIX + ros_topic(key)


@functools.cache
def typestore() -> Any:
    """rosbags' ROS 2 Humble typestore with the ``smartedge_msgs`` types registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types: dict[str, Any] = {}
    for path in sorted(MSG_DIR.glob("*/msg/*.msg")):
        name = f"{path.parents[1].name}/msg/{path.stem}"
        types.update(get_types_from_msg(path.read_text(encoding="utf-8"), name))
    store.register(types)
    return store


@functools.cache
def schema_text(ros_type: str) -> bytes:
    """The ``ros2msg`` schema of an MCAP channel: the definition and its dependencies."""
    text, _ = typestore().generate_msgdef(ros_type, ros_version=2)
    return text.encode()


def wire_cdr(payload: bytes) -> bytes:
    """``smartedge_msgs/msg/Wire`` CDR bytes holding ``payload``."""
    return _CDR_LE + struct.pack("<I", len(payload)) + bytes(payload)


def wire_payload(cdr: bytes | memoryview) -> bytes:
    """The msgpack payload inside ``smartedge_msgs/msg/Wire`` CDR bytes;
    :class:`RosRecordError` when they are not that."""
    data = bytes(cdr)
    if len(data) < 8 or data[:4] != _CDR_LE:
        raise RosRecordError(f"not a little-endian CDR message ({len(data)} bytes)")
    (n,) = struct.unpack_from("<I", data, 4)
    if 8 + n > len(data) or len(data) - (8 + n) > 3:  # CDR may pad the end to 4 bytes
        raise RosRecordError(f"Wire.data says {n} bytes, the message holds {len(data) - 8}")
    return data[8:8 + n]


def _time(ts: Any, stamp_ns: int) -> Any:
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    if not 0 <= sec < 2**31:
        raise RosRecordError(f"stamp {stamp_ns} ns does not fit a ROS 2 time")
    return ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _header(ts: Any, stamp_ns: int, frame_id: str) -> Any:
    return ts.types["std_msgs/msg/Header"](stamp=_time(ts, stamp_ns), frame_id=frame_id)


def _planar_pose(ts: Any, x: float, y: float, theta: float) -> Any:
    t = ts.types
    qx, qy, qz, qw = yaw_to_quaternion(theta)
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))


def _cov6(cov3: np.ndarray) -> np.ndarray:
    """(3, 3) of (x, y, yaw) → (36,) of (x, y, z, roll, pitch, yaw), REP 103 order."""
    idx = np.array([0, 1, 5])
    out = np.zeros((6, 6))
    out[np.ix_(idx, idx)] = np.asarray(cov3, dtype=np.float64).reshape(3, 3)
    return out.reshape(36)


def _f64(values: Any) -> np.ndarray:
    return np.ascontiguousarray(values, dtype=np.float64).reshape(-1)


def to_ros(msg: Message) -> tuple[str, Any]:
    """``(ros_type, rosbags message)`` of a smartedge message; :class:`RosRecordError` for a
    type without a ROS form or a value a ROS message cannot hold."""
    ts = typestore()
    t = ts.types
    if isinstance(msg, (PoseEstimate, PoseCorrection)):
        pose = t["geometry_msgs/msg/PoseWithCovariance"](
            pose=_planar_pose(ts, msg.x, msg.y, msg.theta), covariance=_cov6(msg.covariance))
        return ROS_TYPES[type(msg)], t["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=_header(ts, msg.stamp_ns, msg.frame_id), pose=pose)
    if isinstance(msg, Odometry):
        twist = t["geometry_msgs/msg/Twist"](
            linear=t["geometry_msgs/msg/Vector3"](x=float(msg.vx), y=float(msg.vy), z=0.0),
            angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=float(msg.wz)))
        return ROS_TYPES[Odometry], t["nav_msgs/msg/Odometry"](
            header=_header(ts, msg.stamp_ns, msg.frame_id), child_frame_id="base_link",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=_planar_pose(ts, msg.x, msg.y, msg.theta),
                covariance=_cov6(msg.covariance)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=twist, covariance=np.zeros(36)))
    if isinstance(msg, ServiceStatus):
        kv = t["diagnostic_msgs/msg/KeyValue"]
        values = [kv(key="state", value=msg.state), kv(key="uptime_s", value=f"{msg.uptime_s:g}")]
        for prefix, table in (("rate_hz", msg.rates_hz), ("latency_p50_ms", msg.latency_p50_ms),
                              ("latency_p99_ms", msg.latency_p99_ms), ("count", msg.counters)):
            values += [kv(key=f"{prefix}/{k}", value=f"{v:g}") for k, v in sorted(table.items())]
        values.append(kv(key="peers_alive", value=",".join(msg.peers_alive)))
        status = t["diagnostic_msgs/msg/DiagnosticStatus"](
            level=_LEVELS.get(msg.state, 2), name=f"{msg.service}/{msg.instance_id}",
            message=msg.detail or msg.state, hardware_id=msg.instance_id, values=values)
        return ROS_TYPES[ServiceStatus], t["diagnostic_msgs/msg/DiagnosticArray"](
            header=_header(ts, msg.stamp_ns, ""), status=[status])
    if isinstance(msg, CameraImage):
        return ROS_TYPES[CameraImage], t["sensor_msgs/msg/CompressedImage"](
            header=_header(ts, msg.stamp_ns, msg.camera_id), format=msg.encoding,
            data=np.ascontiguousarray(msg.data, dtype=np.uint8))
    if isinstance(msg, SemanticCloud):
        return ROS_TYPES[SemanticCloud], _cloud(ts, msg)
    if isinstance(msg, RobotDetections):
        det = t["smartedge_msgs/msg/Detection"]
        dets = [det(robot_id=d.robot_id, score=float(d.score), bbox_xyxy=_f64(d.bbox_xyxy),
                    keypoints_px=_f64(d.keypoints_px), keypoint_scores=_f64(d.keypoint_scores),
                    keypoint_sigmas_px=_f64(d.keypoint_sigmas_px
                                            if d.keypoint_sigmas_px is not None else ()),
                    robot_model=d.robot_model)
                for d in msg.detections]
        return ROS_TYPES[RobotDetections], t["smartedge_msgs/msg/RobotDetections"](
            header=_header(ts, msg.stamp_ns, msg.camera_id), seq=int(msg.seq) % 2**32,
            image_width=int(msg.image_width), image_height=int(msg.image_height),
            model_id=msg.model_id, detections=dets)
    raise RosRecordError(f"no ROS 2 form for {type(msg).__name__}")


#: PointCloud2 layout of a semantic cloud: x, y, z (float32), label (uint16), confidence
_CLOUD_DTYPE: Final = np.dtype({"names": ["x", "y", "z", "label", "confidence"],
                                "formats": ["<f4", "<f4", "<f4", "<u2", "<f4"],
                                "offsets": [0, 4, 8, 12, 16], "itemsize": 20})


def _cloud(ts: Any, msg: SemanticCloud) -> Any:
    t = ts.types
    field = t["sensor_msgs/msg/PointField"]
    n = len(msg.points_xyz)
    rows = np.zeros(n, dtype=_CLOUD_DTYPE)
    rows["x"], rows["y"], rows["z"] = msg.points_xyz.T
    rows["label"] = msg.class_ids
    rows["confidence"] = msg.confidences
    fields = [field(name=name, offset=off, datatype=dt, count=1) for name, off, dt in
              (("x", 0, field.FLOAT32), ("y", 4, field.FLOAT32), ("z", 8, field.FLOAT32),
               ("label", 12, field.UINT16), ("confidence", 16, field.FLOAT32))]
    return t["sensor_msgs/msg/PointCloud2"](
        header=_header(ts, msg.stamp_ns, msg.frame_id), height=1, width=n, fields=fields,
        is_bigendian=False, point_step=_CLOUD_DTYPE.itemsize,
        row_step=_CLOUD_DTYPE.itemsize * n, data=rows.view(np.uint8).reshape(-1).copy(),
        is_dense=True)


def to_cdr(msg: Message) -> tuple[str, bytes]:
    """``(ros_type, CDR bytes)`` of a smartedge message (see :func:`to_ros`)."""
    ros_type = ROS_TYPES.get(type(msg), type(msg).__name__)
    try:
        ros_type, obj = to_ros(msg)
        return ros_type, bytes(typestore().serialize_cdr(obj, ros_type))
    except RosRecordError:
        raise
    except Exception as exc:  # rosbags raises several types on values out of range
        raise RosRecordError(f"{ros_type}: {type(exc).__name__}: {exc}") from None


def pose_from_ros(ros_type: str, cdr: bytes) -> tuple[int, np.ndarray, np.ndarray]:
    """``(stamp_ns, position (3,) m, quaternion x y z w)`` of a CDR pose message of one of
    :data:`POSE_TYPES`; :class:`RosRecordError` for another type or bytes that do not decode."""
    if ros_type not in POSE_TYPES:
        raise RosRecordError(f"{ros_type} is not a pose type (one of {', '.join(POSE_TYPES)})")
    try:
        obj = typestore().deserialize_cdr(bytes(cdr), ros_type)
    except Exception as exc:  # rosbags raises several types on truncated/garbage bytes
        raise RosRecordError(f"{ros_type} does not decode: {type(exc).__name__}: {exc}") from None
    stamp = obj.header.stamp
    if ros_type.endswith("TransformStamped"):
        p, q = obj.transform.translation, obj.transform.rotation
    else:
        pose = obj.pose if ros_type.endswith("PoseStamped") else obj.pose.pose
        p, q = pose.position, pose.orientation
    return (int(stamp.sec) * NS_PER_S + int(stamp.nanosec), np.array([p.x, p.y, p.z]),
            np.array([q.x, q.y, q.z, q.w]))
