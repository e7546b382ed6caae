"""Zenoh key expressions of the wire contract: the only place they are spelled.

::

    smartedge/<site>/edge/<camera_id>/detections     RobotDetections
    smartedge/<site>/edge/<camera_id>/cloud          SemanticCloud
    smartedge/<site>/edge/<camera_id>/image          CameraImage (preview for the viewer)
    smartedge/<site>/robot/<robot_id>/odom           Odometry
    smartedge/<site>/robot/<robot_id>/cloud          SemanticCloud
    smartedge/<site>/robot/<robot_id>/pose           PoseEstimate (fused)
    smartedge/<site>/robot/<robot_id>/camera_pose    PoseEstimate (camera-only)
    smartedge/<site>/robot/<robot_id>/localization   PoseEstimate (the robot's own, "robot")
    smartedge/<site>/robot/<robot_id>/ground_truth   PoseEstimate (simulation only)
    smartedge/<site>/robot/<robot_id>/correction     PoseCorrection
    smartedge/<site>/map/<map_id>/voxels             SemanticCloud (the semantic map's voxels)
    smartedge/<site>/status/<service>/<id>           ServiceStatus
    smartedge/<site>/alive/<service>/<id>            liveliness token (no payload)
    smartedge/<site>/owner/<robot_id>/<id>           liveliness token: backend <id> publishes
                                                     the robot's estimates
    smartedge/<site>/area/<area>/<id>                liveliness token: backend <id> serves the
                                                     area's cameras (``--area``)
"""

from __future__ import annotations

import dataclasses
from typing import Final

from protocol.errors import ValidationError
from protocol.messages import (
    CameraImage,
    Message,
    Odometry,
    PoseCorrection,
    PoseEstimate,
    RobotDetections,
    SemanticCloud,
    ServiceStatus,
)
from protocol.validation import check_id

ROOT: Final = "smartedge"

#: (scope, topic) → the message type carried on that key.
TOPIC_TYPES: Final[dict[tuple[str, str], type[Message]]] = {
    ("edge", "detections"): RobotDetections,
    ("edge", "cloud"): SemanticCloud,
    ("edge", "image"): CameraImage,
    ("robot", "odom"): Odometry,
    ("robot", "cloud"): SemanticCloud,
    ("robot", "pose"): PoseEstimate,
    ("robot", "camera_pose"): PoseEstimate,
    ("robot", "localization"): PoseEstimate,
    ("robot", "ground_truth"): PoseEstimate,
    ("robot", "correction"): PoseCorrection,
    ("map", "voxels"): SemanticCloud,
}
SERVICES: Final = ("edge-agent", "backend", "mapper", "robot-bridge")


def _chunk(field: str, value: str, wildcard: bool) -> str:
    if wildcard and value == "*":
        return value
    return check_id(field, value)


def edge_key(site: str, camera_id: str, topic: str) -> str:
    """``smartedge/<site>/edge/<camera_id>/<topic>``; ``camera_id='*'`` gives a wildcard."""
    if ("edge", topic) not in TOPIC_TYPES:
        raise ValidationError("topic", f"unknown edge topic {topic!r}")
    return f"{ROOT}/{check_id('site', site)}/edge/{_chunk('camera_id', camera_id, True)}/{topic}"


def robot_key(site: str, robot_id: str, topic: str) -> str:
    """``smartedge/<site>/robot/<robot_id>/<topic>``; ``robot_id='*'`` gives a wildcard."""
    if ("robot", topic) not in TOPIC_TYPES:
        raise ValidationError("topic", f"unknown robot topic {topic!r}")
    return f"{ROOT}/{check_id('site', site)}/robot/{_chunk('robot_id', robot_id, True)}/{topic}"


def detections_key(site: str, camera_id: str) -> str:
    return edge_key(site, camera_id, "detections")


def edge_cloud_key(site: str, camera_id: str) -> str:
    return edge_key(site, camera_id, "cloud")


def image_key(site: str, camera_id: str) -> str:
    return edge_key(site, camera_id, "image")


def odom_key(site: str, robot_id: str) -> str:
    return robot_key(site, robot_id, "odom")


def robot_cloud_key(site: str, robot_id: str) -> str:
    return robot_key(site, robot_id, "cloud")


def pose_key(site: str, robot_id: str) -> str:
    return robot_key(site, robot_id, "pose")


def camera_pose_key(site: str, robot_id: str) -> str:
    return robot_key(site, robot_id, "camera_pose")


def localization_key(site: str, robot_id: str) -> str:
    return robot_key(site, robot_id, "localization")


def ground_truth_key(site: str, robot_id: str) -> str:
    return robot_key(site, robot_id, "ground_truth")


def correction_key(site: str, robot_id: str) -> str:
    return robot_key(site, robot_id, "correction")


def map_voxels_key(site: str, map_id: str) -> str:
    """``smartedge/<site>/map/<map_id>/voxels``: the mapper's semantic voxels (``'*'`` allowed
    for the id)."""
    return f"{ROOT}/{check_id('site', site)}/map/{_chunk('map_id', map_id, True)}/voxels"


def status_key(site: str, service: str, instance_id: str) -> str:
    """``smartedge/<site>/status/<service>/<id>``; ``'*'`` is allowed for both ids."""
    return (
        f"{ROOT}/{check_id('site', site)}/status/{_chunk('service', service, True)}/"
        f"{_chunk('instance_id', instance_id, True)}"
    )


def alive_key(site: str, service: str, instance_id: str) -> str:
    """Liveliness token key ``smartedge/<site>/alive/<service>/<id>``; ``'*'`` allowed."""
    return (
        f"{ROOT}/{check_id('site', site)}/alive/{_chunk('service', service, True)}/"
        f"{_chunk('instance_id', instance_id, True)}"
    )


def owner_key(site: str, robot_id: str, instance_id: str) -> str:
    """Liveliness token key ``smartedge/<site>/owner/<robot_id>/<id>``: backend ``<id>`` holds
    the robot (backend_service/ownership.py); ``'*'`` allowed for both ids."""
    return (
        f"{ROOT}/{check_id('site', site)}/owner/{_chunk('robot_id', robot_id, True)}/"
        f"{_chunk('instance_id', instance_id, True)}"
    )


def area_key(site: str, area: str, instance_id: str) -> str:
    """Liveliness token key ``smartedge/<site>/area/<area>/<id>``: backend ``<id>`` serves the
    cameras of site area ``<area>`` (backend_service/areas.py); ``'*'`` allowed for both."""
    return (
        f"{ROOT}/{check_id('site', site)}/area/{_chunk('area', area, True)}/"
        f"{_chunk('instance_id', instance_id, True)}"
    )


@dataclasses.dataclass(frozen=True)
class ParsedKey:
    """A key split into its parts. ``scope`` is ``edge``, ``robot``, ``map``, ``status``,
    ``alive``, ``owner`` or ``area``; ``source_id`` the camera/robot/map/instance id (for
    owner: the robot; for area: the area); ``topic`` the last chunk (for status/alive: the
    service name; for owner and area: the backend instance); ``message_type`` the type
    carried (``None`` for liveliness)."""

    site: str
    scope: str
    source_id: str
    topic: str
    message_type: type[Message] | None


def parse_key(key: str) -> ParsedKey:
    """Split a concrete key; :class:`ValidationError` if it is not one of ours."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[0] != ROOT:
        raise ValidationError("key", f"not a smartedge key: {str(key)[:200]!r}")
    _, site, scope, a, b = parts
    check_id("key.site", site)
    if scope in ("edge", "robot", "map"):
        msg_type = TOPIC_TYPES.get((scope, b))
        if msg_type is None:
            raise ValidationError("key", f"unknown {scope} topic {b!r} in {key!r}")
        return ParsedKey(site, scope, check_id("key.id", a), b, msg_type)
    if scope == "status":
        return ParsedKey(
            site, scope, check_id("key.id", b), check_id("key.service", a), ServiceStatus
        )
    if scope == "alive":
        return ParsedKey(site, scope, check_id("key.id", b), check_id("key.service", a), None)
    if scope == "owner":
        return ParsedKey(site, scope, check_id("key.robot_id", a), check_id("key.id", b), None)
    if scope == "area":
        return ParsedKey(site, scope, check_id("key.area", a), check_id("key.id", b), None)
    raise ValidationError("key", f"unknown scope {scope!r} in {key!r}")
