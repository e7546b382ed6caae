"""``smartedge bench codec``: encode+decode round trips of the wire codec.

Measures a detections message (1 robot, 12 keypoints) and a 100k-point semantic cloud. Peers
in the same run: the careful decode path alone (``decode_checked``: the per-field
decode, every limit located in the raw bytes first), the unbounded decode (``msgpack.unpackb``
with no limits, then the same message construction and validation: what the limits cost), and
the same content as JSON with arrays as float lists (what a naive wire format would do).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Callable, Sequence

import msgpack
import numpy as np

from protocol.codec import decode, decode_checked, encode, message_from_wire
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


def _us(seconds: float) -> str:
    return f"{seconds * 1e6:.1f} us" if seconds < 1e-3 else f"{seconds * 1e3:.2f} ms"


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench codec", description=__doc__)
    parser.add_argument("--seconds", type=float, default=2.0, help="time per measurement")
    args = parser.parse_args(list(argv))
    print(
        f"machine: {platform.machine()} {platform.processor() or ''} python "
        f"{platform.python_version()} numpy {np.__version__}"
    )
    print(f"{'message':<22}{'bytes':>9}{'round trip':>12}{'careful':>10}{'unbounded':>11}"
          f"{'json':>11}   ratios: careful / this, this / unbounded, json / this")
    for name, msg in (("detections (12 kp)", _detections()), ("cloud (100k points)", _cloud())):
        payload = encode(msg)
        expected = type(msg)
        per, _ = _time_it(lambda m=msg, e=expected: decode(encode(m), e), args.seconds)
        per_careful, _ = _time_it(lambda m=msg, e=expected: decode_checked(encode(m), e),
                                  args.seconds)
        per_free, _ = _time_it(lambda m=msg: message_from_wire(msgpack.unpackb(encode(m))),
                               args.seconds)
        obj = _to_json_obj(msg)
        per_json, _ = _time_it(lambda o=obj: json.loads(json.dumps(o)), args.seconds)
        print(f"{name:<22}{len(payload):>9}{_us(per):>12}{_us(per_careful):>10}"
              f"{_us(per_free):>11}{_us(per_json):>11}   {per_careful / per:.2f}x, "
              f"{per / per_free:.2f}x, {per_json / per:.1f}x")
    print("round trip = encode + decode of the expected type with every limit checked; careful = "
          "the careful path alone (per-field checks, no fast paths); unbounded = msgpack "
          "without limits + the same validation; json = float lists")
    return 0
