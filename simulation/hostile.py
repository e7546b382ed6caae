"""Hostile input a simulated attacker sends: oversized detection payloads.

Built from one genuine :class:`~protocol.messages.RobotDetections` so that everything but the
size is plausible. The fault harness (``smartedge bench reliability``, probes
``oversized_nested_detections`` and ``oversized_padded_detections``) and the oversized-message
tests (tests/system/test_oversized.py) send the same bytes.
"""

from __future__ import annotations

import math

import msgpack  # type: ignore[import-untyped]

from protocol import encode
from protocol.limits import PAYLOAD_CAPS
from protocol.messages import RobotDetections


def hostile_payloads(real: RobotDetections) -> dict[str, list[bytes]]:
    """Oversized detection payloads built from one genuine detections message: ``nested``
    (100 messages of 1.5 MB, thousands of nested detections each), ``counted`` (100 messages
    of 0.9 x the type's byte cap, nested detections) and ``padded`` (20 valid messages padded
    to 50 MB in an unknown key)."""
    wire = msgpack.unpackb(encode(real), raw=False)
    one = wire["detections"][:1]
    per_detection = len(msgpack.packb(one[0]))
    nested = {**wire, "detections": one * math.ceil(1_500_000 / per_detection)}
    counted = {**wire, "detections": one * int(0.9 * PAYLOAD_CAPS["RobotDetections"]
                                                 / per_detection)}
    padded = {**wire, "padding": b"\0" * (50_000_000 - len(encode(real)))}
    out = {"nested": [msgpack.packb(nested)] * 100, "counted": [msgpack.packb(counted)] * 100,
           "padded": [msgpack.packb(padded)] * 20}
    assert len(out["nested"][0]) >= 1_500_000 and len(out["padded"][0]) >= 50_000_000
    assert len(out["counted"][0]) <= PAYLOAD_CAPS["RobotDetections"]
    return out


__all__ = ["hostile_payloads"]
