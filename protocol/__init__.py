"""smartedge wire contract: messages, codec, key expressions, Zenoh config and site file.

Only numpy, msgpack, PyYAML (and zenoh in :mod:`protocol.session`) are imported here, so an
edge board with the ``edge`` extra can use all of it.
"""

from __future__ import annotations

import logging

from protocol.codec import MAX_PAYLOAD_BYTES, decode, encode
from protocol.errors import DecodeError, ProtocolError, SiteConfigError, ValidationError
from protocol.messages import (
    MESSAGE_TYPES,
    Detection,
    Message,
    Odometry,
    PoseCorrection,
    PoseEstimate,
    RobotDetections,
    SemanticCloud,
    ServiceStatus,
)

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "MAX_PAYLOAD_BYTES",
    "MESSAGE_TYPES",
    "DecodeError",
    "Detection",
    "Message",
    "Odometry",
    "PoseCorrection",
    "PoseEstimate",
    "ProtocolError",
    "RobotDetections",
    "SemanticCloud",
    "ServiceStatus",
    "SiteConfigError",
    "ValidationError",
    "decode",
    "encode",
]
