"""``smartedge bench codec``: encode+decode throughput of the wire codec.

Measures a detections message (1 robot, 12 keypoints) and a 100k-point semantic cloud, and, as a
peer in the same run, the same content as JSON with arrays as float lists (what a naive wire
format would do), printed as a speed-up ratio.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Callable, Sequence

import numpy as np

from protocol.codec import decode, encode
from protocol.messages import Detection, Message, RobotDetections, SemanticCloud


def _detections() -> RobotDetections:
    rng = np.random.default_rng(0)
    det = Detection(
        np.array([100.0, 120, 260, 330]),
        0.97,
        rng.random((12, 2)) * 400,
        rng.random(12).astype(np.float32),
    )
    return RobotDetections("cam_sw", 1_700_000_000_000_000_000, 42, 848, 480, "hsr-kp-v1", (det,))


def _cloud(n: int = 100_000) -> SemanticCloud:
    rng = np.random.default_rng(1)
    return SemanticCloud(
        "hsr",
        1_700_000_000_000_000_000,
        7,
        "map",
        rng.normal(size=(n, 3)).astype(np.float32),
        rng.integers(0, 40, n).astype(np.uint8),
        rng.random(n).astype(np.float32),
        np.eye(4),
    )


def _to_json_obj(msg: Message) -> dict:
    import dataclasses

    def conv(v):
        if isinstance(v, np.ndarray):
            return v.tolist()
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        return v

    return conv(msg)


def _time_it(fn: Callable[[], object], min_time_s: float) -> tuple[float, int]:
    fn()
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        elapsed = time.perf_counter() - t0
        if elapsed >= min_time_s:
            return elapsed / n, n


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench codec", description=__doc__)
    parser.add_argument("--seconds", type=float, default=2.0, help="time per measurement")
    args = parser.parse_args(list(argv))
    print(
        f"machine: {platform.machine()} {platform.processor() or ''} python "
        f"{platform.python_version()} numpy {np.__version__}"
    )
    print(
        f"{'message':<28}{'bytes':>10}{'msg/s':>12}{'MB/s':>10}{'json msg/s':>12}{'speed-up':>10}"
    )
    for name, msg in (("detections (12 kp)", _detections()), ("cloud (100k points)", _cloud())):
        payload = encode(msg)
        per, _ = _time_it(lambda m=msg: decode(encode(m)), args.seconds)
        obj = _to_json_obj(msg)
        per_json, _ = _time_it(lambda o=obj: json.loads(json.dumps(o)), args.seconds)
        print(
            f"{name:<28}{len(payload):>10}{1 / per:>12.0f}{len(payload) / per / 1e6:>10.1f}"
            f"{1 / per_json:>12.0f}{per_json / per:>9.1f}x"
        )
    print(
        "msg/s = encode+decode round trips per second (with full validation); "
        "speed-up = msgpack codec vs json with float lists"
    )
    return 0
