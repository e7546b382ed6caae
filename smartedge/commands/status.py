"""``smartedge status`` and ``smartedge echo``: what is live on the Zenoh network, from any
machine that reaches the router (or, with the embedded default, on this machine).

``status`` listens to every service's ``ServiceStatus`` (once a second) and liveliness token and
shows one row per service: state, age of its last status, uptime, message rates, median
latencies and its non-zero problem counters; a refreshing table on a terminal, plain lines
otherwise (``--once``: one table after ``--wait`` seconds, exit 1 if nobody answered).
``echo KEY`` decodes every message on a key expression (``smartedge/lab/robot/hsr/pose``,
``smartedge/lab/**``) and prints one readable line each; undecodable payloads are reported,
never fatal.

Zenoh callbacks only queue samples; the main thread decodes and prints (the threading rule).
"""

from __future__ import annotations

import argparse
import collections
import math
import sys
import time
from collections.abc import Sequence
from typing import Any, TextIO

from core.session import add_session_arguments, make_config, options_from_args
from protocol import keys
from protocol.codec import decode
from protocol.errors import DecodeError
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

#: counters shown in the status table: those that mean trouble (others are in `echo`)
PROBLEM_WORDS = ("drop", "invalid", "error", "late", "future", "unknown", "bad", "overflow",
                 "skipped", "image_size", "failed", "rejected", "rate_limited", "stale",
                 "mismatch", "lost", "unconfirmed", "reset", "outside_floor", "jump",
                 "window_exceeded")


def summarize(msg: Message) -> str:
    """One readable line of a decoded message (without its key)."""
    if isinstance(msg, RobotDetections):
        parts = [f"{len(msg.detections)} robot(s)"]
        for d in msg.detections:
            seen = int((d.keypoint_scores > 0).sum())
            sig = "" if d.keypoint_sigmas_px is None else \
                f", sigma median {float(_median(d.keypoint_sigmas_px)):.2f} px"
            parts.append(f"[{d.robot_id or '?'} score {d.score:.2f}, {seen}/"
                         f"{len(d.keypoint_scores)} keypoints{sig}]")
        return (f"RobotDetections {msg.camera_id} stamp {_stamp(msg.stamp_ns)} seq {msg.seq} "
                f"{msg.image_width}x{msg.image_height} {msg.model_id}: " + " ".join(parts))
    if isinstance(msg, PoseEstimate):
        std = [math.sqrt(max(float(msg.covariance[i, i]), 0.0)) for i in range(3)]
        return (f"PoseEstimate {msg.robot_id} ({msg.source}) stamp {_stamp(msg.stamp_ns)} "
                f"x {msg.x:.3f} y {msg.y:.3f} theta {math.degrees(msg.theta):.1f} deg "
                f"(std {100 * std[0]:.1f}/{100 * std[1]:.1f} cm, "
                f"{math.degrees(std[2]):.2f} deg) cams {','.join(msg.camera_ids) or '-'} "
                f"flags {','.join(msg.flags) or '-'}")
    if isinstance(msg, Odometry):
        return (f"Odometry {msg.robot_id} stamp {_stamp(msg.stamp_ns)} x {msg.x:.3f} "
                f"y {msg.y:.3f} theta {math.degrees(msg.theta):.1f} deg")
    if isinstance(msg, PoseCorrection):
        return (f"PoseCorrection {msg.robot_id} ({msg.kind}) stamp {_stamp(msg.stamp_ns)} "
                f"x {msg.x:.3f} y {msg.y:.3f} theta {math.degrees(msg.theta):.1f} deg")
    if isinstance(msg, ServiceStatus):
        return (f"ServiceStatus {msg.service}/{msg.instance_id} {msg.state} "
                f"up {msg.uptime_s:.0f} s {msg.detail}".rstrip())
    if isinstance(msg, CameraImage):
        return (f"CameraImage {msg.camera_id} stamp {_stamp(msg.stamp_ns)} "
                f"{msg.image_width}x{msg.image_height} {msg.encoding} {msg.data.size} bytes")
    if isinstance(msg, SemanticCloud):
        return (f"SemanticCloud {msg.sensor_id} stamp {_stamp(msg.stamp_ns)} "
                f"{len(msg.points_xyz)} points in {msg.frame_id}")
    return type(msg).__name__


def _median(a: Any) -> float:
    import numpy as np

    return float(np.median(a)) if len(a) else float("nan")


def _stamp(stamp_ns: int) -> str:
    return f"{stamp_ns / 1e9:.3f}"


def _open_session(args: argparse.Namespace) -> Any:
    import zenoh

    return zenoh.open(make_config(options_from_args(args)))


# --------------------------------------------------------------------------------------------
# echo
# --------------------------------------------------------------------------------------------


def echo_main(argv: Sequence[str], out: TextIO = sys.stdout) -> int:
    parser = argparse.ArgumentParser(prog="smartedge echo", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("key", help="key expression, e.g. smartedge/lab/robot/hsr/pose or "
                        "smartedge/lab/**")
    parser.add_argument("--count", type=int, default=0, help="stop after N messages")
    parser.add_argument("--duration", type=float, default=0.0, help="stop after S seconds")
    add_session_arguments(parser)
    args = parser.parse_args(list(argv))
    if not args.key.startswith(keys.ROOT + "/"):
        print(f"smartedge echo: {args.key!r} is not a smartedge key expression "
              f"(they start with {keys.ROOT}/)", file=sys.stderr)
        return 2
    queue: collections.deque[tuple[str, bytes]] = collections.deque(maxlen=10_000)
    session = _open_session(args)
    sub = session.declare_subscriber(
        args.key, lambda s: queue.append((str(s.key_expr), s.payload.to_bytes())))
    shown = 0
    deadline = time.monotonic() + args.duration if args.duration > 0 else math.inf
    try:
        while time.monotonic() < deadline and (args.count <= 0 or shown < args.count):
            if not queue:
                time.sleep(0.02)
                continue
            key, payload = queue.popleft()
            try:
                line = summarize(decode(payload))
            except DecodeError as exc:
                line = f"undecodable ({len(payload)} bytes): {exc}"
            print(f"{key}: {line}", file=out, flush=True)
            shown += 1
    except KeyboardInterrupt:
        pass
    finally:
        sub.undeclare()
        session.close()
    return 0


# --------------------------------------------------------------------------------------------
# status
# --------------------------------------------------------------------------------------------


def status_rows(statuses: dict[str, tuple[ServiceStatus, float]], alive: set[str],
                now_s: float) -> list[list[str]]:
    """Table rows (header first) from the latest status per ``service/id`` (with its receive
    time) and the ``service/id`` names whose liveliness token is present."""
    rows = [["service", "alive", "state", "seen", "up", "rates (Hz)", "p50 latency (ms)",
             "problems", "detail"]]
    for name in sorted(set(statuses) | alive):
        st, recv_s = statuses.get(name, (None, math.nan))
        if st is None:
            rows.append([name, "yes", "?", "never", "", "", "", "", "(no status yet)"])
            continue
        rates = " ".join(f"{k} {v:.1f}" for k, v in sorted(st.rates_hz.items()) if v > 0)
        lat = " ".join(f"{k} {v:.1f}" for k, v in sorted(st.latency_p50_ms.items())[:4])
        problems = " ".join(f"{k}={v}" for k, v in sorted(st.counters.items())
                            if v and any(w in k for w in PROBLEM_WORDS))
        rows.append([name, "yes" if name in alive else "NO", st.state,
                     f"{now_s - recv_s:.0f} s ago", f"{st.uptime_s:.0f} s", rates, lat,
                     problems or "-", st.detail[:60]])
    return rows


def format_table(rows: list[list[str]]) -> str:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
                     for r in rows)


def status_main(argv: Sequence[str], out: TextIO = sys.stdout) -> int:
    parser = argparse.ArgumentParser(prog="smartedge status", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--site", help="site file (its site id); default: every site heard")
    parser.add_argument("--once", action="store_true",
                        help="print one table after --wait seconds and exit (1: nobody answered)")
    parser.add_argument("--wait", type=float, default=2.5,
                        help="seconds to listen before the first table (default 2.5)")
    parser.add_argument("--interval", type=float, default=1.0, help="refresh period (s)")
    add_session_arguments(parser)
    args = parser.parse_args(list(argv))
    site = "*"
    if args.site:
        from core.site import load_site

        site = load_site(args.site).name
    import zenoh

    samples: collections.deque[tuple[str, bytes, float]] = collections.deque(maxlen=10_000)
    tokens: collections.deque[tuple[str, bool]] = collections.deque(maxlen=10_000)
    session = _open_session(args)
    status_sub = session.declare_subscriber(
        keys.status_key(site, "*", "*") if site != "*" else f"{keys.ROOT}/*/status/*/*",
        lambda s: samples.append((str(s.key_expr), s.payload.to_bytes(), time.monotonic())))
    alive_key = keys.alive_key(site, "*", "*") if site != "*" else f"{keys.ROOT}/*/alive/*/*"
    alive_sub = session.liveliness().declare_subscriber(
        alive_key, lambda s: tokens.append((str(s.key_expr),
                                            s.kind == zenoh.SampleKind.PUT)), history=True)
    statuses: dict[str, tuple[ServiceStatus, float]] = {}
    alive: set[str] = set()
    tty = out.isatty() and not args.once
    start = time.monotonic()
    next_print = start + args.wait
    try:
        while True:
            while samples:
                key, payload, recv = samples.popleft()
                try:
                    msg = decode(payload, expected=ServiceStatus)
                except DecodeError as exc:
                    print(f"{key}: undecodable status: {exc}", file=sys.stderr)
                    continue
                statuses[f"{msg.service}/{msg.instance_id}"] = (msg, recv)
            while tokens:
                key, present = tokens.popleft()
                parts = key.split("/")
                name = "/".join(parts[-2:])
                (alive.add if present else alive.discard)(name)
            now = time.monotonic()
            if now >= next_print:
                next_print = now + args.interval
                table = format_table(status_rows(statuses, alive, now))
                if tty:
                    out.write("\x1b[H\x1b[2J")
                print(f"smartedge status ({time.strftime('%H:%M:%S')}, site {site}):\n{table}",
                      file=out, flush=True)
                if args.once:
                    return 0 if (statuses or alive) else 1
            time.sleep(0.05)
    except KeyboardInterrupt:
        return 0
    finally:
        status_sub.undeclare()
        alive_sub.undeclare()
        session.close()
