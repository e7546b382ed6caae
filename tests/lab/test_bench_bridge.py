"""`smartedge bench bridge` runs and measures something real (tiny sizes)."""

from __future__ import annotations

import math

import pytest

pytest.importorskip("rosbags")
pytest.importorskip("zenoh")


def test_bench_bridge_measures_encoding_and_loopback_latency() -> None:
    from lab.bench import bridge

    enc = bridge.encoding(20)
    assert set(enc) >= {"msgpack PoseEstimate (peer)", "rmw_zenoh CDR + attachment"}
    assert all(0 < us < 10_000 for us in enc.values())
    for name in ("ros2", "rmw_zenoh"):
        median_ms, p95_ms, received = bridge.latency(name, 10, 0.0)
        assert received == 10 and math.isfinite(median_ms) and 0 < median_ms <= p95_ms
