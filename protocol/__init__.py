"""The smartedge wire contract: what another implementation of a service must match, and only
that.

- ``messages``: the messages every service speaks, frozen dataclasses validated on
  construction; ``validation``: the field checks they share;
- ``codec``: the msgpack codec (:func:`decode` never raises anything but
  :class:`DecodeError`, whatever the bytes);
- ``limits``: what one message may cost a receiver: payload caps per type, the unknown-key
  rule, queue budgets;
- ``keys``: the Zenoh key expressions, the only place they are spelled;
- ``errors``: the project's exceptions: ``SmartedgeError``, the error root every package
  shares (the root of every user-facing error raised on purpose), and ``ProtocolError``
  under it for what this package raises;
- ``semantic_classes``: the indoor semantic class legend (names, ids, display colours).

Imports nothing of the project, and of third parties only numpy and msgpack, so an edge board
with the ``edge`` extra can use all of it. The shared code of the ground floor that is not part
of the contract (runtime, site file, camera, geometry...) is :mod:`core`.
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
