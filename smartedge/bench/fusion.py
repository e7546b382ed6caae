"""``smartedge bench fusion``: ISAM2 latency and memory of the pose-graph fusion over hours.

Simulates a robot driving a loop of static waypoints (the paper's protocol: camera estimates at
the stops, optionally also while driving) with drifting odometry (scale error, heading bias,
noise), delivers camera estimates late (uniform edge latency), and feeds everything to one
:class:`backend_service.fusion.PoseGraphFusion`. Reports the latency of each call that ran an
ISAM2 update (camera estimate, new odometry keyframe; p50/p99 over the last 5 simulated minutes
and over the whole run), the graph size, and the process RSS after 5 minutes and at the end.

The synthetic run generator (:func:`make_synthetic_run`, :func:`replay`) is also used by the
fusion tests; it is numpy-only and deterministic for a given seed.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from collections.abc import Sequence
from typing import Final

import numpy as np

from backend_service.fusion import FusionConfig, PoseGraphFusion
from protocol.geometry import (
    angle_diff,
    rotation_z,
    se2_compose,
    se2_inverse,
    wrap_angle,
    wrap_angle_array,
)
from protocol.messages import Odometry, PoseEstimate

_NS_PER_S: Final = 1_000_000_000

#: a loop of static waypoints (x, y metres, theta radians) in a ~7 x 6 m room; waypoints 0 and 3
#: stand for the paper's single-camera waypoints (poorly observed).
DEFAULT_WAYPOINTS: Final[tuple[tuple[float, float, float], ...]] = (
    (1.0, 1.0, 0.0),
    (5.0, 1.0, math.pi / 2),
    (6.5, 3.5, math.pi / 2),
    (5.0, 5.0, math.pi),
    (2.0, 5.0, -math.pi / 2),
    (0.8, 3.0, -math.pi / 2),
)
DEFAULT_POOR_WAYPOINTS: Final = (0, 3)


@dataclasses.dataclass(frozen=True)
class CameraShot:
    """One camera pose estimate of the synthetic run.

    ``pose``: (3,) measured ``T_world_robot`` (x, y, theta); ``truth``: (3,) true pose at
    ``stamp_ns``; ``latency_ns``: edge latency (delivery = stamp + latency).
    """

    stamp_ns: int
    latency_ns: int
    pose: np.ndarray
    truth: np.ndarray
    sigma_m: float
    sigma_rad: float
    poorly_observed: bool
    at_stop: bool

    def estimate(self, robot_id: str, seq: int, stamp_shift_ns: int = 0) -> PoseEstimate:
        """The :class:`PoseEstimate` message (``stamp_shift_ns`` mis-stamps it, for tests)."""
        return PoseEstimate(
            robot_id=robot_id,
            stamp_ns=self.stamp_ns + stamp_shift_ns,
            seq=seq,
            x=float(self.pose[0]),
            y=float(self.pose[1]),
            theta=wrap_angle(float(self.pose[2])),
            covariance=np.diag([self.sigma_m**2, self.sigma_m**2, self.sigma_rad**2]),
            source="cameras",
            camera_ids=("cam1",) if self.poorly_observed else ("cam1", "cam2", "cam3"),
            flags=("single_camera",) if self.poorly_observed else (),
        )


@dataclasses.dataclass(frozen=True)
class SyntheticRun:
    """A simulated run: odometry samples and camera estimates.

    ``stamps_ns``: (N,) int64 odometry stamps; ``truth``: (N, 3) true ``T_world_robot``;
    ``odom``: (N, 3) ``T_odom_robot`` as the robot reports it (drifting; starts at 0, 0, 0).
    """

    robot_id: str
    stamps_ns: np.ndarray
    truth: np.ndarray
    odom: np.ndarray
    shots: tuple[CameraShot, ...]

    def odometry(self, i: int) -> Odometry:
        return Odometry(
            robot_id=self.robot_id,
            stamp_ns=int(self.stamps_ns[i]),
            seq=i,
            x=float(self.odom[i, 0]),
            y=float(self.odom[i, 1]),
            theta=wrap_angle(float(self.odom[i, 2])),
        )

    def odometry_in_world(self) -> np.ndarray:
        """(N, 3) odometry aligned to the world by its first pose (the "odometry alone")."""
        T_world_odom = se2_compose(self.truth[0], se2_inverse(self.odom[0]))
        R = rotation_z(T_world_odom[2])[:2, :2]
        out = np.empty_like(self.odom)
        out[:, :2] = self.odom[:, :2] @ R.T + T_world_odom[:2]
        out[:, 2] = wrap_angle_array(self.odom[:, 2] + T_world_odom[2])
        return out


def make_synthetic_run(
    duration_s: float,
    *,
    seed: int = 0,
    robot_id: str = "hsr1",
    odom_hz: float = 30.0,
    speed_m_s: float = 0.3,
    turn_rate_rad_s: float = 0.6,
    dwell_s: float = 4.0,
    waypoints: Sequence[tuple[float, float, float]] = DEFAULT_WAYPOINTS,
    poor_waypoints: Sequence[int] = DEFAULT_POOR_WAYPOINTS,
    odom_scale_error: float = 0.02,
    odom_heading_bias_rad_s: float = 0.005,
    odom_noise_m_s: float = 0.01,
    odom_noise_rad_s: float = 0.01,
    sigma_good_m: float = 0.03,
    sigma_good_rad: float = math.radians(1.0),
    sigma_poor_m: float = 0.15,
    sigma_poor_rad: float = math.radians(5.0),
    shots_per_stop: int = 1,
    moving_camera_hz: float = 0.0,
    latency_s: tuple[float, float] = (0.05, 0.3),
    start_stamp_ns: int = 1_700_000_000 * _NS_PER_S,
) -> SyntheticRun:
    """Drive the waypoint loop for ``duration_s`` (turn in place, drive straight, turn to the
    waypoint heading, dwell ``dwell_s``), starting static at waypoint 0.

    Odometry integrates ``v (1 + odom_scale_error) + noise`` and
    ``w + odom_heading_bias_rad_s + noise`` while moving (wheel odometry does not drift at
    rest). Camera shots: ``shots_per_stop`` per dwell (noise ``sigma_good_*``, or
    ``sigma_poor_*`` at ``poor_waypoints``) plus ``moving_camera_hz`` while driving (good);
    latency uniform in ``latency_s``.
    """
    rng = np.random.default_rng(seed)
    dt = 1.0 / odom_hz
    n_total = int(duration_s * odom_hz) + 1
    # phases as (samples, v, w, waypoint index or -1 when moving)
    v_cmd = np.zeros(n_total)
    w_cmd = np.zeros(n_total)
    stop_of = np.full(n_total, -1)
    truth = np.zeros((n_total, 3))
    pose = np.array(waypoints[0], dtype=float)
    i = 0
    wp = 0

    def emit(n: int, v: float, w: float, stop: int) -> None:
        nonlocal i
        n = min(n, n_total - i)
        v_cmd[i : i + n], w_cmd[i : i + n], stop_of[i : i + n] = v, w, stop
        i += n

    while i < n_total:
        emit(max(1, round(dwell_s * odom_hz)), 0.0, 0.0, wp)
        nxt = (wp + 1) % len(waypoints)
        gx, gy, gth = waypoints[nxt]
        dx, dy = gx - pose[0], gy - pose[1]
        bearing = math.atan2(dy, dx)
        for target in (bearing, None, gth):
            if target is None:
                dist = math.hypot(dx, dy)
                n = max(1, math.ceil(dist / (speed_m_s * dt)))
                emit(n, dist / (n * dt), 0.0, -1)
                pose = np.array([gx, gy, bearing])
                continue
            d_th = angle_diff(target, pose[2])
            n = max(1, math.ceil(abs(d_th) / (turn_rate_rad_s * dt)))
            emit(n, 0.0, d_th / (n * dt), -1)
            pose[2] = target
        wp = nxt

    def integrate(v: np.ndarray, w: np.ndarray, start: np.ndarray) -> np.ndarray:
        out = np.zeros((n_total, 3))
        out[0] = start
        # midpoint heading: exact for straight lines and turns in place (the route's only moves)
        th = start[2] + np.concatenate(([0.0], np.cumsum(w[:-1] * dt)))
        mid = th[:-1] + 0.5 * w[:-1] * dt
        out[1:, 0] = start[0] + np.cumsum(v[:-1] * np.cos(mid) * dt)
        out[1:, 1] = start[1] + np.cumsum(v[:-1] * np.sin(mid) * dt)
        out[:, 2] = th
        return out

    truth = integrate(v_cmd, w_cmd, np.array(waypoints[0], dtype=float))
    moving = (v_cmd != 0.0) | (w_cmd != 0.0)
    v_odom = v_cmd * (1.0 + odom_scale_error) + moving * rng.normal(0, odom_noise_m_s, n_total)
    w_odom = w_cmd + moving * (odom_heading_bias_rad_s + rng.normal(0, odom_noise_rad_s, n_total))
    odom = integrate(v_odom, w_odom, np.zeros(3))
    stamps = start_stamp_ns + np.round(np.arange(n_total) * dt * _NS_PER_S).astype(np.int64)

    shots: list[CameraShot] = []

    def shot(k: int, stamp_ns: int, poor: bool, at_stop: bool) -> None:
        sig_m = sigma_poor_m if poor else sigma_good_m
        sig_r = sigma_poor_rad if poor else sigma_good_rad
        noise = rng.normal(0.0, 1.0, 3) * np.array([sig_m, sig_m, sig_r])
        latency = int(rng.uniform(*latency_s) * _NS_PER_S)
        shots.append(
            CameraShot(stamp_ns, latency, truth[k] + noise, truth[k].copy(), sig_m, sig_r, poor,
                       at_stop)
        )

    # dwell segments: contiguous runs of one waypoint index
    k = 0
    while k < n_total:
        if stop_of[k] < 0:
            k += 1
            continue
        end = k
        while end < n_total and stop_of[end] == stop_of[k]:
            end += 1
        if end < n_total or end - k > 2:
            for m in range(shots_per_stop):
                j = k + (m + 1) * (end - k) // (shots_per_stop + 1)
                # stamps between odometry samples (cameras are not synchronized to odometry)
                shot(j, int(stamps[j]) + int(0.4 * dt * _NS_PER_S), stop_of[k] in poor_waypoints,
                     True)
        k = end
    if moving_camera_hz > 0:
        step = max(1, round(odom_hz / moving_camera_hz))
        for j in range(0, n_total - 1, step):
            if moving[j] and moving[j + 1]:
                shot(j, int(stamps[j]) + int(0.5 * dt * _NS_PER_S), False, False)
    # the pose at a stamp between samples j and j+1 is within one odometry step of truth[j];
    # replace truth at the shot stamp by linear interpolation so errors are measured exactly
    fixed = []
    for s in shots:
        j = int(np.searchsorted(stamps, s.stamp_ns, side="right") - 1)
        a = (s.stamp_ns - stamps[j]) / (stamps[j + 1] - stamps[j]) if j + 1 < n_total else 0.0
        t = truth[j] + a * (truth[min(j + 1, n_total - 1)] - truth[j])
        fixed.append(dataclasses.replace(s, pose=s.pose - s.truth + t, truth=t))
    fixed.sort(key=lambda s: s.stamp_ns)
    return SyntheticRun(robot_id, stamps, truth, odom, tuple(fixed))


def replay(
    run: SyntheticRun,
    fusion: PoseGraphFusion,
    *,
    latency_ns: int | None = None,
    stamp_shift_ns: int = 0,
    n_samples: int | None = None,
) -> np.ndarray:
    """Feed ``run`` to ``fusion`` in arrival order; each camera estimate is delivered after the
    first odometry sample at or past ``stamp + latency`` (``latency_ns`` overrides the shot's).

    Returns (N, 3) online fused poses at the odometry stamps (NaN where none was available).
    """
    n = len(run.stamps_ns) if n_samples is None else min(n_samples, len(run.stamps_ns))
    fused = np.full((n, 3), np.nan)
    deliveries = sorted(
        (s.stamp_ns + (s.latency_ns if latency_ns is None else latency_ns), k)
        for k, s in enumerate(run.shots)
    )
    d = 0
    for i in range(n):
        out = fusion.add_odometry(run.odometry(i))
        stamp = int(run.stamps_ns[i])
        while d < len(deliveries) and deliveries[d][0] <= stamp:
            shot = run.shots[deliveries[d][1]]
            res = fusion.add_camera_estimate(shot.estimate(run.robot_id, d, stamp_shift_ns))
            out = res if res is not None else out
            d += 1
        if out is not None and out.stamp_ns == stamp:
            fused[i] = (out.x, out.y, out.theta)
    return fused


def _rss_mib() -> float:
    """Resident set size of this process in MiB (Linux /proc; peak RSS elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        import os

        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


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
        duration_s, seed=args.seed, odom_hz=args.odom_hz, moving_camera_hz=args.camera_hz,
        shots_per_stop=3,
    )
    odometry = [run.odometry(i) for i in range(len(run.stamps_ns))]
    deliveries = sorted((s.stamp_ns + s.latency_ns, k) for k, s in enumerate(run.shots))
    estimates = {k: run.shots[k].estimate(run.robot_id, k) for _, k in deliveries}
    print(f"simulated {args.minutes:g} min: {len(odometry)} odometry samples at "
          f"{args.odom_hz:g} Hz, {len(run.shots)} camera estimates "
          f"(latency 50-300 ms), generated in {time.perf_counter() - t0:.1f} s")

    config = FusionConfig()
    fusion = PoseGraphFusion(run.robot_id, config)
    five_min_ns = int(run.stamps_ns[0]) + 300 * _NS_PER_S
    tail_start_ns = int(run.stamps_ns[-1]) - 300 * _NS_PER_S
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
            rss_5min, graph_5min = _rss_mib(), fusion.graph_size()
    wall_s = time.perf_counter() - t_start
    rss_end, graph_end = _rss_mib(), fusion.graph_size()

    valid = ~np.isnan(fused[:, 0])
    fused_err = np.hypot(*(fused[valid, :2] - run.truth[valid, :2]).T)
    odom_err = np.hypot(*(run.odometry_in_world()[valid, :2] - run.truth[valid, :2]).T)
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
