"""A synthetic robot run for the pose-graph fusion: a loop of static waypoints driven with
drifting wheel odometry, and camera pose estimates delivered late.

The robot drives the paper's protocol (camera estimates at the stops, optionally also while
driving) with drifting odometry (scale error, heading bias, noise); camera estimates arrive
after a uniform edge latency. :func:`make_synthetic_run` builds the run (numpy only,
deterministic for a given seed) and :func:`replay` feeds it, in arrival order, to anything with
the fusion's two inputs (:class:`PoseFusion`, e.g. ``backend_service.fusion.PoseGraphFusion``).
Used by ``smartedge bench fusion`` and the fusion tests.

Frames: ``T_world_robot`` (x, y metres, theta radians) for the truth and the camera
estimates, ``T_odom_robot`` for the odometry; stamps in nanoseconds.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Final, Protocol

import numpy as np

from core.geometry import (
    angle_diff,
    rotation_z,
    se2_compose,
    se2_inverse,
    wrap_angle,
    wrap_angle_array,
)
from protocol.messages import NS_PER_S, Odometry, PoseEstimate


class PoseFusion(Protocol):
    """What :func:`replay` drives: odometry and camera estimates in, a fused
    ``T_world_robot`` out (or ``None``)."""

    def add_odometry(self, msg: Odometry) -> PoseEstimate | None: ...

    def add_camera_estimate(self, est: PoseEstimate) -> PoseEstimate | None: ...


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


@dataclasses.dataclass(frozen=True)
class SyntheticRoute:
    """How the robot drives the waypoint loop: odometry rate, speeds, dwell at each waypoint
    (x, y, theta in the world frame, m and rad)."""

    odom_hz: float = 30.0
    speed_m_s: float = 0.3
    turn_rate_rad_s: float = 0.6
    dwell_s: float = 4.0
    waypoints: Sequence[tuple[float, float, float]] = DEFAULT_WAYPOINTS
    #: waypoints where the cameras see the robot poorly (``CameraNoise``'s poor sigmas)
    poor_waypoints: Sequence[int] = DEFAULT_POOR_WAYPOINTS


@dataclasses.dataclass(frozen=True)
class OdometryDrift:
    """Wheel odometry's errors while moving (none at rest): a scale error of the speed, a
    heading bias (rad/s) and white noise on both."""

    scale_error: float = 0.02
    heading_bias_rad_s: float = 0.005
    noise_m_s: float = 0.01
    noise_rad_s: float = 0.01


@dataclasses.dataclass(frozen=True)
class CameraNoise:
    """The camera estimates: ``shots_per_stop`` per dwell (``sigma_good_*``, or ``sigma_poor_*``
    at the route's poor waypoints), ``moving_camera_hz`` while driving (good), each delivered
    ``latency_s`` (uniform) after its stamp."""

    sigma_good_m: float = 0.03
    sigma_good_rad: float = math.radians(1.0)
    sigma_poor_m: float = 0.15
    sigma_poor_rad: float = math.radians(5.0)
    shots_per_stop: int = 1
    moving_camera_hz: float = 0.0
    latency_s: tuple[float, float] = (0.05, 0.3)


def make_synthetic_run(
    duration_s: float,
    *,
    seed: int = 0,
    robot_id: str = "hsr1",
    route: SyntheticRoute = SyntheticRoute(),
    drift: OdometryDrift = OdometryDrift(),
    cameras: CameraNoise = CameraNoise(),
    start_stamp_ns: int = 1_700_000_000 * NS_PER_S,
) -> SyntheticRun:
    """Drive ``route``'s waypoint loop for ``duration_s`` (turn in place, drive straight, turn
    to the waypoint heading, dwell), starting static at waypoint 0.

    Odometry integrates ``v (1 + drift.scale_error) + noise`` and
    ``w + drift.heading_bias_rad_s + noise`` while moving (wheel odometry does not drift at
    rest). Camera shots as ``cameras`` says.
    """
    odom_hz, speed_m_s, turn_rate_rad_s = route.odom_hz, route.speed_m_s, route.turn_rate_rad_s
    dwell_s, waypoints, poor_waypoints = route.dwell_s, route.waypoints, route.poor_waypoints
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
    v_odom = v_cmd * (1.0 + drift.scale_error) + moving * rng.normal(0, drift.noise_m_s, n_total)
    w_odom = w_cmd + moving * (drift.heading_bias_rad_s
                              + rng.normal(0, drift.noise_rad_s, n_total))
    odom = integrate(v_odom, w_odom, np.zeros(3))
    stamps = start_stamp_ns + np.round(np.arange(n_total) * dt * NS_PER_S).astype(np.int64)

    shots: list[CameraShot] = []

    def shot(k: int, stamp_ns: int, poor: bool, at_stop: bool) -> None:
        sig_m = cameras.sigma_poor_m if poor else cameras.sigma_good_m
        sig_r = cameras.sigma_poor_rad if poor else cameras.sigma_good_rad
        noise = rng.normal(0.0, 1.0, 3) * np.array([sig_m, sig_m, sig_r])
        latency = int(rng.uniform(*cameras.latency_s) * NS_PER_S)
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
            for m in range(cameras.shots_per_stop):
                j = k + (m + 1) * (end - k) // (cameras.shots_per_stop + 1)
                # stamps between odometry samples (cameras are not synchronized to odometry)
                shot(j, int(stamps[j]) + int(0.4 * dt * NS_PER_S), stop_of[k] in poor_waypoints,
                     True)
        k = end
    if cameras.moving_camera_hz > 0:
        step = max(1, round(odom_hz / cameras.moving_camera_hz))
        for j in range(0, n_total - 1, step):
            if moving[j] and moving[j + 1]:
                shot(j, int(stamps[j]) + int(0.5 * dt * NS_PER_S), False, False)
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
    fusion: PoseFusion,
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


__all__ = [
    "DEFAULT_POOR_WAYPOINTS",
    "DEFAULT_WAYPOINTS",
    "CameraNoise",
    "CameraShot",
    "OdometryDrift",
    "PoseFusion",
    "SyntheticRoute",
    "SyntheticRun",
    "make_synthetic_run",
    "replay",
]
