"""ROS 2 (and ROS 1) robots over Zenoh: odometry in, pose corrections out, as ROS messages.

The robot runs ``zenoh-bridge-ros2dds``, which maps the ROS 2 topic ``/x`` to the Zenoh key
``x`` (prefixed with the bridge's ``namespace`` when one is configured) and carries the DDS
payload unchanged: CDR with its 4-byte encapsulation header. This module

* converts between ROS messages and the bridge's planar types with pure functions
  (``nav_msgs/msg/Odometry`` → :class:`OdometrySample`; ``PoseWithCovarianceStamped`` or
  ``PoseStamped`` → :class:`LocalizationPose`; :class:`PoseCorrection` →
  ``geometry_msgs/msg/PoseWithCovarianceStamped`` with frame ``map``, the header stamp being the
  estimate's time and the 6x6 covariance filled from the 3x3 (x, y, yaw));
* serializes them with ``rosbags`` (CDR for ROS 2, ROS 1 serialization with ``ros1=True`` for
  ``zenoh-plugin-ros1``, whose keys are ``<hex(type)>/<md5>/<topic>``);
* isolates the Zenoh part in :class:`RosZenohAdapter` (zenoh is imported there only).

Topics: HSR corrections ``laser_2d_correct_pose`` (odometry ``/hsrb/odom`` on ROS 1,
``/switched_odom`` on ROS 2, localization ``/global_pose``); Nav2/AMCL ``initialpose``
(odometry ``/odom``, localization ``/amcl_pose``). See ``docs/robot_bridge.md``.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import re
from collections.abc import Callable
from typing import Any, Final

import numpy as np

from core.geometry import quaternion_to_yaw, yaw_to_quaternion
from protocol.messages import NS_PER_S, PoseCorrection, PoseEstimate
from robot_bridge.adapters.base import (
    POSE_STREAMS,
    LocalizationPose,
    MapMessages,
    MapToOdom,
    OdometrySample,
    RobotAdapter,
)

log = logging.getLogger(__name__)

ODOMETRY_TYPE: Final = "nav_msgs/msg/Odometry"
POSE_WITH_COVARIANCE_STAMPED_TYPE: Final = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE_STAMPED_TYPE: Final = "geometry_msgs/msg/PoseStamped"
LOCALIZATION_TYPES: Final = (POSE_WITH_COVARIANCE_STAMPED_TYPE, POSE_STAMPED_TYPE)
TF_MESSAGE_TYPE: Final = "tf2_msgs/msg/TFMessage"
POINT_CLOUD2_TYPE: Final = "sensor_msgs/msg/PointCloud2"
OCCUPANCY_GRID_TYPE: Final = "nav_msgs/msg/OccupancyGrid"
#: variance written on the z, roll and pitch diagonal of the continuous pose output: the
#: cameras do not measure them (robot_localization in 2D mode ignores them anyway)
UNOBSERVED_VARIANCE: Final = 1.0e6

HSR_CORRECTION_TOPIC: Final = "laser_2d_correct_pose"
NAV2_INITIALPOSE_TOPIC: Final = "initialpose"
#: continuous pose output topics (fused, camera-only) and the transform topic
POSE_OUTPUT_TOPIC: Final = "smartedge/pose"
CAMERA_POSE_OUTPUT_TOPIC: Final = "smartedge/camera_pose"
TF_TOPIC: Final = "tf"
#: the semantic map (PointCloud2) and its obstacle grid (OccupancyGrid)
MAP_CLOUD_TOPIC: Final = "smartedge/semantic_map"
OBSTACLES_TOPIC: Final = "smartedge/obstacles"
#: the robot topic sets :class:`RosConfig` knows
ROBOT_PROFILES: Final = ("hsr", "nav2")

#: (x, y, yaw) → index in the row-major 6x6 (x, y, z, roll, pitch, yaw) ROS covariance.
_COV6_INDEX: Final = (0, 1, 5)
_FRAME_BAD_CHARS: Final = re.compile(r"[^A-Za-z0-9_.\-]")


class RosConversionError(ValueError):
    """A ROS payload could not be turned into a bridge reading (the reason says why)."""


# --------------------------------------------------------------------------------------------
# topic names and keys
# --------------------------------------------------------------------------------------------


def _clean_topic(topic: str) -> str:
    name = str(topic).strip().strip("/")
    if not name or any(c in name for c in "*?$#") or "//" in name:
        raise ValueError(f"invalid ROS topic name {topic!r}")
    return name


def ros2dds_key(topic: str, namespace: str = "") -> str:
    """Zenoh key of a ROS 2 topic as ``zenoh-bridge-ros2dds`` routes it: ``/x`` → ``x``, with
    the bridge's ``namespace`` (``/robot1`` or ``robot1``) prepended when it is not ``/``."""
    name = _clean_topic(topic)
    ns = str(namespace).strip().strip("/")
    return f"{_clean_topic(ns)}/{name}" if ns else name


def ros1_datatype(ros_type: str) -> str:
    """ROS 1 spelling of a message type: ``nav_msgs/msg/Odometry`` → ``nav_msgs/Odometry``."""
    parts = ros_type.split("/")
    return f"{parts[0]}/{parts[-1]}"


def ros1_key(topic: str, ros_type: str, namespace: str = "") -> str:
    """Zenoh key of a ROS 1 topic as ``zenoh-plugin-ros1`` routes it:
    ``<hex(datatype)>/<md5>/[<bridge_ns>/]<topic>``; ``md5`` is the ROS 1 message md5sum."""
    _, md5 = typestore(ros1=True).generate_msgdef(ros_type)
    datatype_hex = ros1_datatype(ros_type).encode().hex()
    name = _clean_topic(topic)
    ns = str(namespace).strip().strip("/")
    prefix = f"{datatype_hex}/{md5}"
    return f"{prefix}/{_clean_topic(ns)}/{name}" if ns else f"{prefix}/{name}"


def ros1_key_pattern(topic: str, namespace: str = "") -> str:
    """Subscription key matching a ROS 1 topic of any type through ``zenoh-plugin-ros1``."""
    name = _clean_topic(topic)
    ns = str(namespace).strip().strip("/")
    return f"*/*/{_clean_topic(ns)}/{name}" if ns else f"*/*/{name}"


def ros_frame_to_id(frame_id: str, default: str) -> str:
    """A ROS frame id (``/odom``, ``hsrb/odom``) as a protocol id (``odom``, ``hsrb_odom``)."""
    name = str(frame_id).strip().strip("/")
    return _FRAME_BAD_CHARS.sub("_", name)[:64] or default


# --------------------------------------------------------------------------------------------
# pure conversions
# --------------------------------------------------------------------------------------------


@functools.cache
def typestore(ros1: bool = False) -> Any:
    """The ``rosbags`` typestore: ROS 2 Humble message definitions (CDR), or ROS 1 Noetic."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if TF_MESSAGE_TYPE not in store.types:
        # Noetic's store lacks tf2_msgs; its TFMessage is one field, defined as in tf2_msgs
        store.register(get_types_from_msg(
            "geometry_msgs/TransformStamped[] transforms", TF_MESSAGE_TYPE))
    return store


def stamp_ns_to_ros(stamp_ns: int) -> tuple[int, int]:
    """ns since the epoch → ``(sec, nanosec)`` of ``builtin_interfaces/Time``;
    :class:`RosConversionError` past 2038 (``sec`` is an int32 in ROS 2, uint32 in ROS 1)."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    if not 0 <= sec < 2**31:
        raise RosConversionError(f"stamp {stamp_ns} ns does not fit a ROS time")
    return sec, nanosec


def ros_to_stamp_ns(sec: int, nanosec: int) -> int:
    """``builtin_interfaces/Time`` → ns since the epoch."""
    return int(sec) * NS_PER_S + int(nanosec)


def orientation_to_yaw(orientation: Any) -> float:
    """Yaw (rad, in [-pi, pi)) of a ``geometry_msgs/Quaternion``; it need not be normalised,
    must not be zero (:class:`RosConversionError`)."""
    q = orientation
    try:
        return quaternion_to_yaw(float(q.x), float(q.y), float(q.z), float(q.w))
    except ValueError as exc:
        raise RosConversionError(f"invalid orientation: {exc}") from None


def covariance_3x3_to_6x6(covariance: np.ndarray) -> np.ndarray:
    """(3, 3) covariance of (x, y, yaw) → the (36,) row-major ROS covariance of
    (x, y, z, roll, pitch, yaw). z, roll and pitch rows stay zero: a ground robot's pose has
    none of that freedom, and AMCL / the HSR localizer read only the x, y and yaw entries."""
    cov3 = np.asarray(covariance, dtype=np.float64).reshape(3, 3)
    cov6 = np.zeros((6, 6))
    for i, ri in enumerate(_COV6_INDEX):
        for j, rj in enumerate(_COV6_INDEX):
            cov6[ri, rj] = cov3[i, j]
    return cov6.reshape(36)


def covariance_6x6_to_3x3(covariance: Any) -> np.ndarray:
    """(36,) ROS covariance → (3, 3) of (x, y, yaw). A covariance that is not finite or has a
    negative variance (ROS's "unknown" convention puts -1 first) gives zeros: unknown."""
    cov6 = np.asarray(covariance, dtype=np.float64).reshape(6, 6)
    idx = np.array(_COV6_INDEX)
    cov3 = cov6[np.ix_(idx, idx)]
    cov3 = 0.5 * (cov3 + cov3.T)
    if not np.all(np.isfinite(cov3)) or np.any(np.diag(cov3) < 0.0):
        return np.zeros((3, 3))
    return cov3


def pose_with_covariance_to_ros(
    stamp_ns: int, x: float, y: float, theta: float, covariance: np.ndarray, *,
    frame_id: str = "map", ros1: bool = False, seq: int = 0,
    unobserved_variance: float = 0.0,
) -> Any:
    """A planar pose as a ``geometry_msgs/msg/PoseWithCovarianceStamped`` (rosbags object).

    Header stamp ``stamp_ns`` (the estimate's time: AMCL and robot_localization compensate
    motion since then), frame ``frame_id``; ROS 1 headers get ``seq``. The 6x6 covariance is
    REP-103 ordered (x, y, z, roll, pitch, yaw) with the (x, y, yaw) block from
    ``covariance``; z, roll and pitch get ``unobserved_variance`` on the diagonal (0 for AMCL's
    initial pose, a large value for a measurement robot_localization may fuse)."""
    ts = typestore(ros1)
    t = ts.types
    sec, nanosec = stamp_ns_to_ros(stamp_ns)
    stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    if ros1:
        header = t["std_msgs/msg/Header"](seq=int(seq) % 2**32, stamp=stamp, frame_id=frame_id)
    else:
        header = t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)
    qx, qy, qz, qw = yaw_to_quaternion(theta)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )
    cov6 = covariance_3x3_to_6x6(covariance)
    if unobserved_variance:
        for i in (2, 3, 4):
            cov6[i * 6 + i] = float(unobserved_variance)
    pwc = t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov6)
    return t[POSE_WITH_COVARIANCE_STAMPED_TYPE](header=header, pose=pwc)


def correction_to_ros(
    correction: PoseCorrection, *, frame_id: str = "map", ros1: bool = False
) -> Any:
    """A :class:`PoseCorrection` as a ``geometry_msgs/msg/PoseWithCovarianceStamped`` (rosbags
    message object). Header stamp = the estimate's time (AMCL compensates motion since then),
    frame ``frame_id``; ROS 1 headers get ``seq`` = the correction's seq."""
    return pose_with_covariance_to_ros(
        correction.stamp_ns, correction.x, correction.y, correction.theta,
        correction.covariance, frame_id=frame_id, ros1=ros1, seq=correction.seq)


def _serialize(msg: Any, ros_type: str, ros1: bool) -> bytes:
    ts = typestore(ros1)
    if ros1:
        return bytes(ts.serialize_ros1(msg, ros_type))
    return bytes(ts.serialize_cdr(msg, ros_type))


def serialize_correction(
    correction: PoseCorrection, *, frame_id: str = "map", ros1: bool = False
) -> bytes:
    """Wire bytes of :func:`correction_to_ros`: CDR (little endian, with the encapsulation
    header) for ROS 2, ROS 1 serialization when ``ros1``."""
    return _serialize(correction_to_ros(correction, frame_id=frame_id, ros1=ros1),
                      POSE_WITH_COVARIANCE_STAMPED_TYPE, ros1)


def serialize_pose_estimate(
    estimate: PoseEstimate, *, frame_id: str = "map", ros1: bool = False,
    unobserved_variance: float = UNOBSERVED_VARIANCE,
) -> bytes:
    """Wire bytes of a backend estimate as the continuous pose topic's
    ``PoseWithCovarianceStamped`` (see :func:`pose_with_covariance_to_ros`): stamped with the
    estimate's time, ``seq`` the estimate's, unobserved axes at ``unobserved_variance``."""
    msg = pose_with_covariance_to_ros(
        estimate.stamp_ns, estimate.x, estimate.y, estimate.theta, estimate.covariance,
        frame_id=frame_id, ros1=ros1, seq=estimate.seq,
        unobserved_variance=unobserved_variance)
    return _serialize(msg, POSE_WITH_COVARIANCE_STAMPED_TYPE, ros1)


def map_to_odom_to_ros(transform: MapToOdom, *, ros1: bool = False) -> Any:
    """A :class:`MapToOdom` as a ``tf2_msgs/msg/TFMessage`` holding one
    ``geometry_msgs/msg/TransformStamped`` (``parent_frame`` -> ``child_frame``)."""
    ts = typestore(ros1)
    t = ts.types
    sec, nanosec = stamp_ns_to_ros(transform.stamp_ns)
    stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    if ros1:
        header = t["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=transform.parent_frame)
    else:
        header = t["std_msgs/msg/Header"](stamp=stamp, frame_id=transform.parent_frame)
    qx, qy, qz, qw = yaw_to_quaternion(transform.theta)
    tf = t["geometry_msgs/msg/TransformStamped"](
        header=header,
        child_frame_id=transform.child_frame,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](
                x=float(transform.x), y=float(transform.y), z=0.0),
            rotation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )
    return t[TF_MESSAGE_TYPE](transforms=[tf])


def serialize_map_to_odom(transform: MapToOdom, *, ros1: bool = False) -> bytes:
    """Wire bytes of :func:`map_to_odom_to_ros` (``tf2_msgs/msg/TFMessage``)."""
    return _serialize(map_to_odom_to_ros(transform, ros1=ros1), TF_MESSAGE_TYPE, ros1)


def _deserialize(payload: Any, ros_type: str, ros1: bool) -> Any:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise RosConversionError(f"payload is {type(payload).__name__}, not bytes")
    ts = typestore(ros1)
    try:
        if ros1:
            return ts.deserialize_ros1(bytes(payload), ros_type)
        return ts.deserialize_cdr(bytes(payload), ros_type)
    except Exception as exc:  # rosbags raises several types on truncated/garbage bytes
        raise RosConversionError(f"not a {ros_type}: {type(exc).__name__}: {exc}") from None


def _finite(name: str, value: Any) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise RosConversionError(f"{name} is not finite")
    return value


def odometry_from_ros(msg: Any) -> OdometrySample:
    """``nav_msgs/msg/Odometry`` (rosbags object, ROS 1 or 2) → :class:`OdometrySample`: the
    planar pose (x, y, yaw) of ``child_frame_id`` in ``header.frame_id``, the body twist
    (vx, vy, wz) and the (x, y, yaw) covariance."""
    p = msg.pose.pose
    tw = msg.twist.twist
    stamp_ns = ros_to_stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)
    if stamp_ns < 0:
        raise RosConversionError("negative stamp")
    return OdometrySample(
        stamp_ns=stamp_ns,
        x=_finite("position.x", p.position.x),
        y=_finite("position.y", p.position.y),
        theta=orientation_to_yaw(p.orientation),
        vx=_finite("twist.linear.x", tw.linear.x),
        vy=_finite("twist.linear.y", tw.linear.y),
        wz=_finite("twist.angular.z", tw.angular.z),
        covariance=covariance_6x6_to_3x3(msg.pose.covariance),
        frame_id=ros_frame_to_id(msg.header.frame_id, "odom"),
    )


def deserialize_odometry(payload: Any, *, ros1: bool = False) -> OdometrySample:
    """Odometry wire bytes (CDR, or ROS 1 when ``ros1``) → :class:`OdometrySample`;
    :class:`RosConversionError` on anything else."""
    return odometry_from_ros(_deserialize(payload, ODOMETRY_TYPE, ros1))


def deserialize_tf_message(payload: Any, *, ros1: bool = False) -> Any:
    """``/tf`` or ``/tf_static`` wire bytes (CDR, or ROS 1 when ``ros1``) → the decoded
    ``tf2_msgs/msg/TFMessage`` (rosbags object), for
    :meth:`core.tf_buffer.TfBuffer.add_tf_message`; :class:`RosConversionError` on
    anything else."""
    return _deserialize(payload, TF_MESSAGE_TYPE, ros1)


def localization_from_ros(msg: Any, ros_type: str) -> LocalizationPose:
    """``PoseWithCovarianceStamped`` (AMCL ``amcl_pose``) or ``PoseStamped`` (HSR
    ``global_pose``) → :class:`LocalizationPose` in the message's frame."""
    if ros_type == POSE_WITH_COVARIANCE_STAMPED_TYPE:
        pose, cov = msg.pose.pose, covariance_6x6_to_3x3(msg.pose.covariance)
    elif ros_type == POSE_STAMPED_TYPE:
        pose, cov = msg.pose, None
    else:
        raise RosConversionError(f"unsupported localization type {ros_type}")
    return LocalizationPose(
        stamp_ns=ros_to_stamp_ns(msg.header.stamp.sec, msg.header.stamp.nanosec),
        x=_finite("position.x", pose.position.x),
        y=_finite("position.y", pose.position.y),
        theta=orientation_to_yaw(pose.orientation),
        covariance=cov,
        frame_id=ros_frame_to_id(msg.header.frame_id, "map"),
    )


def deserialize_localization(
    payload: Any, ros_type: str = POSE_WITH_COVARIANCE_STAMPED_TYPE, *, ros1: bool = False
) -> LocalizationPose:
    """Localization wire bytes → :class:`LocalizationPose`; :class:`RosConversionError` on
    anything else."""
    if ros_type not in LOCALIZATION_TYPES:
        raise RosConversionError(f"unsupported localization type {ros_type}")
    return localization_from_ros(_deserialize(payload, ros_type, ros1), ros_type)


# --------------------------------------------------------------------------------------------
# Zenoh transport
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class RosTopics:
    """Which ROS topics the adapter uses (names without leading slash are fine).

    ``correction_topic``: ``laser_2d_correct_pose`` (HSR) or ``initialpose`` (Nav2/AMCL).
    ``localization_topic``: the robot's own map pose (``amcl_pose``, HSR ``global_pose``) or
    ``None`` when the robot does not publish one (then every stop may send an initial pose).
    ``namespace``: the ``namespace`` of zenoh-bridge-ros2dds (or of zenoh-plugin-ros1).
    ``ros1``: ROS 1 serialization and zenoh-plugin-ros1 keys instead of CDR / ros2dds keys.
    ``map_frame``: frame id written into corrections and pose outputs (the bridge sets the
    site's ``world_frame``). ``pose_topic`` / ``camera_pose_topic``: the continuous pose
    output (fused / camera-only ``PoseWithCovarianceStamped``), ``tf_topic`` the map -> odom
    transform (``tf2_msgs/msg/TFMessage``); whether and how often they are published is the
    bridge's ``pose_output`` section. ``map_cloud_topic`` / ``obstacles_topic``: the semantic
    map (``sensor_msgs/msg/PointCloud2``) and its obstacle grid (``nav_msgs/msg/OccupancyGrid``),
    section ``map_output``.
    """

    odometry_topic: str = "odom"
    correction_topic: str = NAV2_INITIALPOSE_TOPIC
    localization_topic: str | None = "amcl_pose"
    localization_type: str = POSE_WITH_COVARIANCE_STAMPED_TYPE
    namespace: str = ""
    ros1: bool = False
    map_frame: str = "map"
    pose_topic: str = POSE_OUTPUT_TOPIC
    camera_pose_topic: str = CAMERA_POSE_OUTPUT_TOPIC
    tf_topic: str = TF_TOPIC
    map_cloud_topic: str = MAP_CLOUD_TOPIC
    obstacles_topic: str = OBSTACLES_TOPIC

    @classmethod
    def hsr(cls, *, ros1: bool = False, namespace: str = "") -> RosTopics:
        """Toyota HSR: odometry ``/hsrb/odom`` (ROS 1) or ``/switched_odom`` (ROS 2),
        corrections on ``laser_2d_correct_pose``, localization ``global_pose``."""
        return cls(
            odometry_topic="hsrb/odom" if ros1 else "switched_odom",
            correction_topic=HSR_CORRECTION_TOPIC,
            localization_topic="global_pose",
            localization_type=POSE_STAMPED_TYPE,
            namespace=namespace,
            ros1=ros1,
        )

    @classmethod
    def nav2(cls, *, namespace: str = "") -> RosTopics:
        """Nav2 with AMCL: ``odom``, ``initialpose``, ``amcl_pose``."""
        return cls(namespace=namespace)

    def odometry_key(self) -> str:
        if self.ros1:
            return ros1_key_pattern(self.odometry_topic, self.namespace)
        return ros2dds_key(self.odometry_topic, self.namespace)

    def correction_key(self) -> str:
        if self.ros1:
            return ros1_key(self.correction_topic, POSE_WITH_COVARIANCE_STAMPED_TYPE,
                            self.namespace)
        return ros2dds_key(self.correction_topic, self.namespace)

    def output_key(self, topic: str, ros_type: str) -> str:
        """Key of a topic the bridge publishes (``ros_type`` picks the ROS 1 md5 prefix)."""
        if self.ros1:
            return ros1_key(topic, ros_type, self.namespace)
        return ros2dds_key(topic, self.namespace)

    def pose_output_topic(self, stream: str) -> str:
        """The topic of pose-output ``stream`` (``fused`` or ``cameras``)."""
        if stream == "fused":
            return self.pose_topic
        if stream == "cameras":
            return self.camera_pose_topic
        raise ValueError(f"unknown pose stream {stream!r}: expected 'fused' or 'cameras'")

    def localization_key(self) -> str | None:
        if self.localization_topic is None:
            return None
        if self.ros1:
            return ros1_key_pattern(self.localization_topic, self.namespace)
        return ros2dds_key(self.localization_topic, self.namespace)


@dataclasses.dataclass(frozen=True)
class RosConfig:
    """The robot's ROS side (site file section ``ros``), for the ``ros2``, ``ros1`` and
    ``rmw_zenoh`` adapters; the bridge's command-line options override it.

    ``profile``: ``hsr`` (corrections on ``laser_2d_correct_pose``, odometry
    ``/switched_odom`` on ROS 2 or ``/hsrb/odom`` on ROS 1, localization ``global_pose``) or
    ``nav2`` (``initialpose``, ``odom``, ``amcl_pose``). ``odometry_topic``,
    ``correction_topic``, ``localization_topic``: override the profile's topics (empty: the
    profile's; ``localization_topic: none`` when the robot publishes no map pose).
    ``namespace``: zenoh-bridge-ros2dds's (or zenoh-plugin-ros1's) ``namespace``, or the
    rmw_zenoh node namespace. ``domain_id``: the ROS domain (rmw_zenoh keys start with it).
    ``pose_topic``, ``camera_pose_topic``, ``tf_topic``: where the continuous pose output
    (section ``pose_output``) goes; ``map_cloud_topic``, ``obstacles_topic``: where the
    semantic map's ``PointCloud2`` and obstacle ``OccupancyGrid`` go (section ``map_output``).
    Frames: corrections and pose outputs carry the site's
    ``world_frame``.
    """

    profile: str = "hsr"
    odometry_topic: str = ""
    correction_topic: str = ""
    localization_topic: str = ""
    namespace: str = ""
    domain_id: int = 0
    pose_topic: str = POSE_OUTPUT_TOPIC
    camera_pose_topic: str = CAMERA_POSE_OUTPUT_TOPIC
    tf_topic: str = TF_TOPIC
    map_cloud_topic: str = MAP_CLOUD_TOPIC
    obstacles_topic: str = OBSTACLES_TOPIC

    def __post_init__(self) -> None:
        if self.profile not in ROBOT_PROFILES:
            raise ValueError(f"profile {self.profile!r}: expected one of {ROBOT_PROFILES}")
        if not 0 <= self.domain_id <= 232:
            raise ValueError(f"domain_id {self.domain_id}: ROS domains are 0..232")
        for name in ("odometry_topic", "correction_topic", "pose_topic",
                     "camera_pose_topic", "tf_topic", "map_cloud_topic", "obstacles_topic"):
            value = getattr(self, name)
            if value:
                _clean_topic(value)  # ValueError naming the bad topic
        if self.localization_topic and self.localization_topic != "none":
            _clean_topic(self.localization_topic)

    @classmethod
    def from_site(cls, site: Any, robot_id: str | None = None) -> RosConfig:
        """The ``ros`` section of a :class:`core.site.Site` as it applies to ``robot_id``
        (the robot entry's own ``ros:`` keys on top; errors name file and key)."""
        reader = site.section_reader()
        if robot_id and robot_id in site.robot_ros:
            index = list(site.robots).index(robot_id)
            reader.section(f"robots[{index}].ros", site.robot_ros[robot_id], cls)
        return reader.section("ros", site.ros_section(robot_id or None), cls)

    def topics(self, *, ros1: bool = False, map_frame: str = "map") -> RosTopics:
        """The :class:`RosTopics` of this configuration."""
        if self.profile == "hsr":
            topics = RosTopics.hsr(ros1=ros1, namespace=self.namespace)
        else:
            topics = dataclasses.replace(RosTopics.nav2(namespace=self.namespace), ros1=ros1)
        changes: dict[str, Any] = {
            "map_frame": map_frame, "pose_topic": self.pose_topic,
            "camera_pose_topic": self.camera_pose_topic, "tf_topic": self.tf_topic,
            "map_cloud_topic": self.map_cloud_topic or MAP_CLOUD_TOPIC,
            "obstacles_topic": self.obstacles_topic or OBSTACLES_TOPIC,
        }
        if self.odometry_topic:
            changes["odometry_topic"] = self.odometry_topic
        if self.correction_topic:
            changes["correction_topic"] = self.correction_topic
        if self.localization_topic == "none":
            changes["localization_topic"] = None
        elif self.localization_topic:
            changes["localization_topic"] = self.localization_topic
        return dataclasses.replace(topics, **changes)


class RosAdapterBase(RobotAdapter):
    """What the ROS adapters share: reading odometry and the robot's localization from their
    subscriptions' ring channels, and writing corrections, pose outputs and the transform as
    ROS messages. A subclass sets ``topics``, ``_odom_sub``, ``_loc_sub`` (or ``None``),
    ``_closed`` and ``_latest_localization``, implements :meth:`_send` (which publisher takes a
    payload), and may override :meth:`_drain` (the rmw_zenoh adapter checks each sample's
    attachment there). Undecodable payloads are counted (``invalid_odometry``,
    ``invalid_localization``) and dropped; a message that cannot be encoded is counted
    ``<what>_invalid``, one that cannot be sent ``<what>_publish_failed``."""

    topics: RosTopics
    _odom_sub: Any
    _loc_sub: Any
    _closed: bool
    _latest_localization: LocalizationPose | None
    #: sequence number of the last map published (ROS 1 headers carry it)
    _map_seq: int = -1

    def _drain(self, subscriber: Any) -> list[bytes]:
        """The payloads received on ``subscriber`` since the last call."""
        out: list[bytes] = []
        while True:
            sample = subscriber.try_recv()
            if sample is None:
                return out
            out.append(sample.payload.to_bytes())

    def read_odometry(self) -> list[OdometrySample]:
        if self._closed:
            return []
        samples = []
        for payload in self._drain(self._odom_sub):
            try:
                samples.append(deserialize_odometry(payload, ros1=self.topics.ros1))
            except RosConversionError as exc:
                self._count("invalid_odometry")
                log.debug("dropped odometry: %s", exc)
        self._count("odometry", len(samples))
        return samples

    def read_localization(self) -> LocalizationPose | None:
        if self._loc_sub is not None and not self._closed:
            for payload in self._drain(self._loc_sub):
                try:
                    self._latest_localization = deserialize_localization(
                        payload, self.topics.localization_type, ros1=self.topics.ros1
                    )
                    self._count("localization")
                except RosConversionError as exc:
                    self._count("invalid_localization")
                    log.debug("dropped localization: %s", exc)
        return self._latest_localization

    def _send(self, target: str, payload: bytes) -> None:
        """Put ``payload`` on the publisher of ``target``: ``correction``, ``pose_fused``,
        ``pose_cameras``, ``tf``, ``map_cloud`` or ``map_grid``. Raises when the transport fails."""
        raise NotImplementedError

    def _write(self, target: str, encode: Callable[[], bytes], published: str) -> bool:
        if self._closed:
            return False
        try:
            payload = encode()
        except RosConversionError as exc:
            self._count(f"{target}_invalid")
            log.warning("%s not sent: %s", target, exc)
            return False
        try:
            self._send(target, payload)
        except Exception as exc:  # a dead session must not take the bridge down
            self._count(f"{target}_publish_failed")
            log.warning("could not publish %s: %s", target, exc)
            return False
        self._count(published)
        return True

    def apply_correction(self, correction: PoseCorrection) -> bool:
        return self._write("correction", lambda: serialize_correction(
            correction, frame_id=self.topics.map_frame, ros1=self.topics.ros1),
            "corrections_published")

    def publish_pose(self, estimate: PoseEstimate, stream: str = "fused") -> bool:
        if stream not in POSE_STREAMS:
            raise ValueError(f"unknown pose stream {stream!r}: expected one of {POSE_STREAMS}")
        return self._write(f"pose_{stream}", lambda: serialize_pose_estimate(
            estimate, frame_id=self.topics.map_frame, ros1=self.topics.ros1),
            f"pose_{stream}_published")

    def publish_transform(self, transform: MapToOdom) -> bool:
        return self._write("tf", lambda: serialize_map_to_odom(transform, ros1=self.topics.ros1),
                           "tf_published")

    def publish_map(self, messages: MapMessages) -> bool:
        """The semantic map's cloud (target ``map_cloud``) and obstacle grid (``map_grid``),
        each when on; ``False`` when one that is on could not be encoded or sent."""
        if self._closed:
            return False
        self._map_seq += 1
        ok = True
        for target, encode in (("map_cloud", messages.cloud_payload),
                               ("map_grid", messages.grid_payload)):
            try:
                payload = encode(ros1=self.topics.ros1, seq=self._map_seq)
            except ValueError as exc:  # RosConversionError, a map that cannot be encoded
                self._count(f"{target}_invalid")
                log.warning("%s not sent: %s", target, exc)
                ok = False
                continue
            if payload is not None:  # None: that output is off
                ok = self._write(target, lambda p=payload: p, f"{target}_published") and ok
        return ok


class RosZenohAdapter(RosAdapterBase):
    """A ROS robot reached over Zenoh through zenoh-bridge-ros2dds (or zenoh-plugin-ros1).

    Uses an open ``zenoh.Session`` (not owned: the caller closes it). Subscriptions hand
    samples to bounded ring channels (oldest dropped under overload, never blocking Zenoh's
    threads); :meth:`read_odometry` drains and decodes them. Undecodable payloads are counted
    in :attr:`counters` (``invalid_odometry``, ``invalid_localization``) and dropped.
    """

    name = "ros2"

    def __init__(self, session: Any, topics: RosTopics | None = None, *,
                 queue_size: int = 512) -> None:
        import zenoh

        super().__init__()
        self.topics = topics or RosTopics()
        if self.topics.localization_type not in LOCALIZATION_TYPES:
            raise ValueError(
                f"localization_type {self.topics.localization_type!r}: expected one of "
                f"{LOCALIZATION_TYPES}"
            )
        self.name = "ros1" if self.topics.ros1 else "ros2"
        self._session = session
        self._latest_localization: LocalizationPose | None = None
        self._closed = False
        self._odom_sub = session.declare_subscriber(
            self.topics.odometry_key(), zenoh.handlers.RingChannel(queue_size)
        )
        loc_key = self.topics.localization_key()
        self._loc_sub = (
            session.declare_subscriber(loc_key, zenoh.handlers.RingChannel(16))
            if loc_key is not None
            else None
        )
        # Corrections are rare and must not be dropped by congestion control.
        self._publisher = session.declare_publisher(
            self.topics.correction_key(),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        # Pose outputs are a stream: the newest matters, congestion may drop (declared on use).
        self._output_publishers: dict[str, Any] = {}

    def _output_publisher(self, topic: str, ros_type: str) -> Any:
        pub = self._output_publishers.get(topic)
        if pub is None:
            import zenoh

            pub = self._session.declare_publisher(
                self.topics.output_key(topic, ros_type),
                congestion_control=zenoh.CongestionControl.DROP,
            )
            self._output_publishers[topic] = pub
        return pub

    def _send(self, target: str, payload: bytes) -> None:
        if target == "correction":
            self._publisher.put(payload)
        elif target == "tf":
            self._output_publisher(self.topics.tf_topic, TF_MESSAGE_TYPE).put(payload)
        elif target == "map_cloud":
            self._output_publisher(self.topics.map_cloud_topic, POINT_CLOUD2_TYPE).put(payload)
        elif target == "map_grid":
            self._output_publisher(self.topics.obstacles_topic, OCCUPANCY_GRID_TYPE).put(payload)
        else:
            topic = self.topics.pose_output_topic(target.removeprefix("pose_"))
            self._output_publisher(topic, POSE_WITH_COVARIANCE_STAMPED_TYPE).put(payload)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        outputs = list(self._output_publishers.values())
        for entity in (self._odom_sub, self._loc_sub, self._publisher, *outputs):
            if entity is not None:
                try:
                    entity.undeclare()
                except Exception:  # session already closed
                    log.debug("undeclare failed", exc_info=True)
