"""What one message may cost a receiver: payload caps per type, the unknown-key rule, queue budgets.

The counts in :mod:`protocol.messages` (64 detections, 256 keypoints, 2 000 000 cloud points...)
bound what a valid message holds; the figures here bound what *any* payload costs before it is
known to be valid, so a receiver never spends more than a few milliseconds and a bounded number
of bytes on one sample (docs/protocol.md, "Limits"):

- :data:`PAYLOAD_CAPS`: the largest payload of each message type, in bytes. Each cap admits every
  message the count limits allow (the largest valid ``RobotDetections`` — 64 detections of 256
  float64 keypoints with sigmas, 64-character ids and model names — packs to 536 KiB; the
  largest valid ``SemanticCloud`` — 2 000 000 points with ``uint16`` classes — to 34.3 MiB)
  and rejects anything bigger before it is parsed. Realistic messages are far smaller: two
  detections of 12 keypoints pack to about 1 KiB, an edge cloud of 50 000 points (5 cm voxels)
  to 0.9 MB, a map of 357 000 voxels to 6.4 MB.
- the unknown-key rule: a receiver ignores keys it does not know (a producer may add a field
  within a version), but each unknown value may pack to at most :data:`MAX_UNKNOWN_VALUE_BYTES`
  and a record may carry at most :data:`MAX_UNKNOWN_KEYS` of them, so padding is refused.
- :data:`QUEUE_BYTE_BUDGETS`: default bound, in bytes, of the channel between the Zenoh threads
  and a service's worker, per subscribed message type (the channel is also bounded in messages).

A payload over a limit raises :class:`LimitError` (a :class:`~protocol.errors.DecodeError`) whose
``limit`` names which one, so a service counts rejections per reason (``invalid.<limit>``).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Final

from protocol.errors import DecodeError

KiB: Final = 1024
MiB: Final = 1024 * KiB

#: hard cap of any payload, whatever its type (and of a payload whose type is not known yet)
MAX_PAYLOAD_BYTES: Final = 64 * MiB

#: largest payload of each message type, by schema name (bytes)
PAYLOAD_CAPS: Final[Mapping[str, int]] = MappingProxyType({
    "RobotDetections": 640 * KiB,
    "CameraImage": 8 * MiB + 64 * KiB,
    "SemanticCloud": 40 * MiB,
    "Odometry": 16 * KiB,
    "PoseEstimate": 64 * KiB,
    "PoseCorrection": 16 * KiB,
    "ServiceStatus": 512 * KiB,
})

#: default byte budget of a subscription's channel, by schema name (bytes); never below the cap
QUEUE_BYTE_BUDGETS: Final[Mapping[str, int]] = MappingProxyType({
    "RobotDetections": 16 * MiB,
    "CameraImage": 32 * MiB,
    "SemanticCloud": 96 * MiB,
    "Odometry": 4 * MiB,
    "PoseEstimate": 4 * MiB,
    "PoseCorrection": 4 * MiB,
    "ServiceStatus": 8 * MiB,
})
#: byte budget of a channel whose message type is not fixed (one payload of the hard cap fits)
DEFAULT_QUEUE_BYTE_BUDGET: Final = MAX_PAYLOAD_BYTES

#: largest packed size of one value under a key the receiver does not know (bytes): room for a
#: per-keypoint float64 array of 256 keypoints added within a version, none for padding
MAX_UNKNOWN_VALUE_BYTES: Final = 4 * KiB
#: most unknown keys in one record (top-level message or nested record)
MAX_UNKNOWN_KEYS: Final = 32
#: longest msgpack string (bytes): the longest text field is 4 096 characters of UTF-8
MAX_STR_BYTES: Final = 16 * KiB
#: most entries of any msgpack array (``peers_alive`` holds up to 4 096 ids; arrays of numbers
#: travel as binary)
MAX_ARRAY_ENTRIES: Final = 4_096
#: most entries of any msgpack map (records have a few dozen keys, number maps at most 256)
MAX_MAP_ENTRIES: Final = 4_096

#: the reasons a :class:`LimitError` names (counter suffixes: ``invalid.<limit>``)
LIMIT_REASONS: Final = (
    "payload_too_large",
    "unknown_key_too_large",
    "too_many_unknown_keys",
    "too_many_entries",
)


class LimitError(DecodeError):
    """A payload exceeds one of the receiver's limits; ``limit`` is one of :data:`LIMIT_REASONS`.

    Raised before the offending part is built into objects."""

    def __init__(self, limit: str, reason: str) -> None:
        super().__init__(reason)
        self.limit = limit


def payload_cap(schema: str | None) -> int:
    """Largest payload (bytes) of messages of ``schema`` (:data:`MAX_PAYLOAD_BYTES` when the
    schema is ``None`` or unknown)."""
    if schema is None:
        return MAX_PAYLOAD_BYTES
    return PAYLOAD_CAPS.get(schema, MAX_PAYLOAD_BYTES)


def queue_byte_budget(schema: str | None) -> int:
    """Default byte budget of a channel carrying ``schema`` (``None``: any type); at least the
    type's payload cap, so one message of the largest allowed size always fits."""
    if schema is None:
        return DEFAULT_QUEUE_BYTE_BUDGET
    return max(QUEUE_BYTE_BUDGETS.get(schema, DEFAULT_QUEUE_BYTE_BUDGET), payload_cap(schema))


def check_payload_size(size: int, schema: str | None) -> None:
    """Raise :class:`LimitError` when a payload of ``size`` bytes is over ``schema``'s cap."""
    cap = payload_cap(schema)
    if size > cap:
        what = schema or "any message"
        raise LimitError(
            "payload_too_large", f"payload of {size} bytes exceeds the {cap}-byte cap of {what}"
        )
