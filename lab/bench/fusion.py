"""``smartedge bench fusion``: ISAM2 latency and memory of the pose-graph fusion over hours.

Simulates a robot driving a loop of static waypoints (the paper's protocol: camera estimates at
the stops, optionally also while driving) with drifting odometry (scale error, heading bias,
noise), delivers camera estimates late (uniform edge latency), and feeds everything to one
:class:`backend_service.fusion.PoseGraphFusion`. Reports the latency of each call that ran an
ISAM2 update (camera estimate, new odometry keyframe; p50/p99 over the last 5 simulated minutes
and over the whole run), the graph size, and the process RSS after 5 minutes and at the end.

The synthetic run comes from :mod:`simulation.synthetic_run` (the fusion tests use the same
generator).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from typing import Final

import numpy as np

from backend_service.fusion import FusionConfig, PoseGraphFusion
from lab.evaluation.metrics import translation_errors
from lab.launcher import rss_mib
from protocol.messages import NS_PER_S
from simulation.synthetic_run import CameraNoise, SyntheticRoute, make_synthetic_run


class _Latencies:
    """Preallocated latency records (seconds), so the bench's own bookkeeping does not grow
    during the run and distort the RSS figures. ``kind``: 0 odometry without keyframe,
    1 odometry keyframe, 2 camera estimate, 3 any call that marginalized (rebuilt ISAM2)."""

    KINDS: Final = ("odometry", "keyframe", "camera", "marginalization")

    def __init__(self, capacity: int) -> None:
        # np.full writes every page now (np.zeros pages would become resident during the run)
        self.seconds = np.full(capacity, np.nan)
        self.kind = np.full(capacity, -1, dtype=np.int8)
        self.stamp_ns = np.full(capacity, -1, dtype=np.int64)
        self.n = 0

    def add(self, seconds: float, kind: int, stamp_ns: int) -> None:
        self.seconds[self.n], self.kind[self.n], self.stamp_ns[self.n] = seconds, kind, stamp_ns
        self.n += 1

    def select(self, kind: int, since_ns: int = 0) -> np.ndarray:
        sel = (self.kind[: self.n] == kind) & (self.stamp_ns[: self.n] >= since_ns)
        return self.seconds[: self.n][sel]


def _fmt(values: np.ndarray) -> str:
    if values.size == 0:
        return "p50    n/a  p99    n/a"
    p50, p99 = np.percentile(values, [50, 99]) * 1e3
    return f"p50 {p50:6.2f}  p99 {p99:6.2f}"


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench fusion", description=__doc__)
    parser.add_argument("--minutes", type=float, default=60.0, help="simulated minutes (60)")
    parser.add_argument("--odom-hz", type=float, default=30.0, help="odometry rate (30)")
    parser.add_argument(
        "--camera-hz", type=float, default=2.0,
        help="camera estimates per second while driving, besides the static waypoints (2)",
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(list(argv))
    if args.minutes <= 0 or args.odom_hz <= 0 or args.camera_hz < 0:
        parser.error("--minutes and --odom-hz must be > 0, --camera-hz >= 0")

    duration_s = args.minutes * 60.0
    t0 = time.perf_counter()
    run = make_synthetic_run(
        duration_s, seed=args.seed, route=SyntheticRoute(odom_hz=args.odom_hz),
        cameras=CameraNoise(moving_camera_hz=args.camera_hz, shots_per_stop=3),
    )
    odometry = [run.odometry(i) for i in range(len(run.stamps_ns))]
    deliveries = sorted((s.stamp_ns + s.latency_ns, k) for k, s in enumerate(run.shots))
    estimates = {k: run.shots[k].estimate(run.robot_id, k) for _, k in deliveries}
    print(f"simulated {args.minutes:g} min: {len(odometry)} odometry samples at "
          f"{args.odom_hz:g} Hz, {len(run.shots)} camera estimates "
          f"(latency 50-300 ms), generated in {time.perf_counter() - t0:.1f} s")

    config = FusionConfig()
    fusion = PoseGraphFusion(run.robot_id, config)
    five_min_ns = int(run.stamps_ns[0]) + 300 * NS_PER_S
    tail_start_ns = int(run.stamps_ns[-1]) - 300 * NS_PER_S
    lat = _Latencies(len(odometry) + len(deliveries))
    fused = np.full((len(odometry), 3), np.nan)
    rss_5min = graph_5min = None
    counters = fusion.counters
    t_start = time.perf_counter()
    d = 0
    for i, msg in enumerate(odometry):
        stamp = msg.stamp_ns
        kfs, margs = counters["keyframes_created"], counters["marginalizations"]
        t = time.perf_counter()
        out = fusion.add_odometry(msg)
        elapsed = time.perf_counter() - t
        kind = 3 if counters["marginalizations"] != margs else int(
            counters["keyframes_created"] != kfs)
        lat.add(elapsed, kind, stamp)
        while d < len(deliveries) and deliveries[d][0] <= stamp:
            est = estimates[deliveries[d][1]]
            margs = counters["marginalizations"]
            t = time.perf_counter()
            res = fusion.add_camera_estimate(est)
            elapsed = time.perf_counter() - t
            lat.add(elapsed, 3 if counters["marginalizations"] != margs else 2, stamp)
            out = res if res is not None else out
            d += 1
        if out is not None and out.stamp_ns == stamp:
            fused[i] = (out.x, out.y, out.theta)
        if rss_5min is None and stamp >= five_min_ns:
            rss_5min, graph_5min = rss_mib(), fusion.graph_size()
    wall_s = time.perf_counter() - t_start
    rss_end, graph_end = rss_mib(), fusion.graph_size()

    valid = ~np.isnan(fused[:, 0])
    fused_err = translation_errors(run.truth[valid, :2], fused[valid, :2])
    odom_err = translation_errors(run.truth[valid, :2], run.odometry_in_world()[valid, :2])
    print(f"replayed in {wall_s:.1f} s wall ({duration_s / wall_s:.0f}x real time); "
          f"FusionConfig defaults (window {config.window_s:g} s / {config.max_keyframes} "
          f"keyframes, marginalized in batches of {config.marginalize_batch})")
    print("latency per call (ms)               last 5 min        |  whole run")
    labels = ("odometry, no keyframe (compose+cov)", "odometry keyframe (ISAM2 update)",
              "camera estimate (ISAM2 update)", "call that marginalized (rebuild)")
    for kind, label in enumerate(labels):
        whole = lat.select(kind)
        tail = lat.select(kind, tail_start_ns)
        peak = f"{whole.max() * 1e3:6.2f}" if whole.size else "   n/a"
        print(f"  {label:35s} {_fmt(tail)} | {_fmt(whole)}  max {peak}  n={whole.size}")
    if rss_5min is not None:
        print(f"memory: RSS {rss_5min:.1f} MiB after 5 min, {rss_end:.1f} MiB at the end "
              f"({rss_end - rss_5min:+.1f} MiB); ISAM2 (variables, factors) "
              f"{graph_5min} after 5 min, {graph_end} at the end")
    else:
        print(f"memory: RSS {rss_end:.1f} MiB at the end (run shorter than 5 min); "
              f"ISAM2 (variables, factors) {graph_end}")
    print(f"buffers at the end: {fusion.buffer_sizes()}; marginalizations "
          f"{counters['marginalizations']}")
    print(f"translation RMS: fused {np.sqrt(np.mean(fused_err**2)) * 100:.1f} cm, odometry "
          f"alone {np.sqrt(np.mean(odom_err**2)) * 100:.1f} cm")
    rejected = {k: v for k, v in counters.items() if k.startswith("camera_") and
                k not in ("camera_received", "camera_fused", "camera_deferred")}
    if rejected:
        print(f"camera estimates not fused: {rejected}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
