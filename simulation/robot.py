"""The simulated robot: differential-drive motion between waypoints (ground truth), wheel
odometry with drift, and an internal localization that accepts corrections only when static.

Frames: ground truth and localization are planar poses (x, y in metres, theta in radians) of
the base in the world (map) frame; odometry is in the robot's ``odom`` frame, which starts at
the origin. Time: seconds since the start of the run (``t_s``) inside the simulation,
nanoseconds on the common clock (``stamp_ns``) in messages.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from core.geometry import angle_diff, se2_between, se2_compose, wrap_angle, wrap_angle_array
from protocol.messages import Odometry
from simulation.scenario import MotionConfig, Scenario, Waypoint

STOP, TURN, DRIVE = 0, 1, 2


def _profile(distance: float, v_max: float, accel: float) -> float:
    """Duration (s) of a trapezoidal (or triangular) rest-to-rest profile over ``distance``."""
    d = abs(distance)
    if d < 1e-12:
        return 0.0
    if d >= v_max * v_max / accel:
        return d / v_max + v_max / accel
    return 2.0 * math.sqrt(d / accel)


def _progress(tau: np.ndarray, duration: float, distance: float, v_max: float,
              accel: float) -> tuple[np.ndarray, np.ndarray]:
    """(signed progress, signed speed) at times ``tau`` (s) into a rest-to-rest profile."""
    d = abs(distance)
    sign = 1.0 if distance >= 0 else -1.0
    tau = np.clip(tau, 0.0, duration)
    if d < 1e-12:
        return np.zeros_like(tau), np.zeros_like(tau)
    t_acc = min(v_max / accel, duration / 2.0)
    v_peak = accel * t_acc
    s_acc = 0.5 * accel * t_acc * t_acc
    t_dec = duration - t_acc
    s = np.where(
        tau < t_acc,
        0.5 * accel * tau * tau,
        np.where(tau < t_dec, s_acc + v_peak * (tau - t_acc),
                 d - 0.5 * accel * (duration - tau) ** 2),
    )
    v = np.where(tau < t_acc, accel * tau, np.where(tau < t_dec, v_peak, accel * (duration - tau)))
    return sign * np.minimum(s, d), sign * np.maximum(v, 0.0)


@dataclasses.dataclass(frozen=True)
class WaypointStop:
    """One static dwell of the robot: at ``waypoint`` from ``t0_s`` to ``t1_s``; ``pose`` is
    the true stop pose (x, y, theta), within the goal tolerance of the waypoint."""

    index: int
    waypoint: str
    t0_s: float
    t1_s: float
    pose: tuple[float, float, float]


class MotionPlan:
    """Ground-truth motion through a sequence of waypoints: at each waypoint turn in place to
    face the next one, drive straight, turn in place to the waypoint heading, dwell.

    ``pose_at(t_s)`` / ``velocity_at(t_s)`` accept arrays of times (s since the run start).
    """

    def __init__(self, waypoints: Sequence[Waypoint], motion: MotionConfig,
                 rng: np.random.Generator | None = None) -> None:
        if len(waypoints) < 2:
            raise ValueError("a motion plan needs at least two waypoints")
        self.motion = motion
        rng = rng or np.random.default_rng(0)
        sig_xy, sig_th = motion.goal_sigma_m, math.radians(motion.goal_sigma_deg)
        goals = []
        for i, wp in enumerate(waypoints):
            if i == 0:  # the run starts exactly where it was initialized
                goals.append((wp.x, wp.y, wp.theta))
            else:
                n = rng.normal(size=3)
                goals.append((wp.x + sig_xy * n[0], wp.y + sig_xy * n[1],
                              wrap_angle(wp.theta + sig_th * n[2])))
        # segments: kind, t0, duration, start pose, amount (m or rad)
        kinds: list[int] = []
        t0s: list[float] = []
        durs: list[float] = []
        starts: list[tuple[float, float, float]] = []
        amounts: list[float] = []
        self.stops: list[WaypointStop] = []
        t = 0.0
        pose = goals[0]

        def add(kind: int, dur: float, amount: float) -> None:
            nonlocal t, pose
            if dur <= 0.0:
                return
            kinds.append(kind)
            t0s.append(t)
            durs.append(dur)
            starts.append(pose)
            amounts.append(amount)
            t += dur
            x, y, th = pose
            if kind == TURN:
                pose = (x, y, wrap_angle(th + amount))
            elif kind == DRIVE:
                pose = (x + amount * math.cos(th), y + amount * math.sin(th), th)

        self.stops.append(WaypointStop(0, waypoints[0].name, 0.0, motion.start_s, pose))
        add(STOP, motion.start_s, 0.0)
        for i in range(1, len(goals)):
            gx, gy, gth = goals[i]
            x, y, th = pose
            heading = math.atan2(gy - y, gx - x)
            add(TURN, _profile(angle_diff(heading, th), motion.max_yaw_rate_radps,
                               motion.yaw_accel_radps2), angle_diff(heading, th))
            dist = math.hypot(gx - x, gy - y)
            add(DRIVE, _profile(dist, motion.max_speed_mps, motion.accel_mps2), dist)
            dth = angle_diff(gth, pose[2])
            add(TURN, _profile(dth, motion.max_yaw_rate_radps, motion.yaw_accel_radps2), dth)
            self.stops.append(WaypointStop(i, waypoints[i].name, t, t + motion.stop_s, pose))
            add(STOP, motion.stop_s, 0.0)
        self._kind = np.array(kinds)
        self._t0 = np.array(t0s)
        self._dur = np.array(durs)
        self._start = np.array(starts)
        self._amount = np.array(amounts)
        self._t0_list = list(t0s)
        self._kind_list = list(kinds)
        self._start_list = list(starts)
        self._dur_list = list(durs)
        self._amount_list = list(amounts)
        self.duration_s = t
        self.path_length_m = float(np.sum(np.abs(self._amount[self._kind == DRIVE])))

    def _eval(self, t_s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        idx = np.clip(np.searchsorted(self._t0, t, side="right") - 1, 0, len(self._t0) - 1)
        tau = np.clip(t - self._t0[idx], 0.0, self._dur[idx])
        pose = self._start[idx].copy()
        vel = np.zeros((len(t), 2))  # (forward speed m/s, yaw rate rad/s)
        m = self.motion
        for kind, v_max, acc in ((TURN, m.max_yaw_rate_radps, m.yaw_accel_radps2),
                                 (DRIVE, m.max_speed_mps, m.accel_mps2)):
            sel = self._kind[idx] == kind
            if not np.any(sel):
                continue
            for j in np.unique(idx[sel]):
                rows = np.nonzero(idx == j)[0]
                s, v = _progress(tau[rows], float(self._dur[j]), float(self._amount[j]), v_max,
                                 acc)
                if kind == TURN:
                    pose[rows, 2] = wrap_angle_array(self._start[j, 2] + s)
                    vel[rows, 1] = v
                else:
                    th = self._start[j, 2]
                    pose[rows, 0] += s * math.cos(th)
                    pose[rows, 1] += s * math.sin(th)
                    vel[rows, 0] = v
        return pose, vel

    def pose_at(self, t_s: np.ndarray | float) -> np.ndarray:
        """(N, 3) true poses (x, y, theta) at times ``t_s`` (s since the run start)."""
        return self._eval(t_s)[0]

    def state_at(self, t_s: float) -> tuple[np.ndarray, float, float]:
        """Scalar fast path: ((3,) true pose, forward speed m/s, yaw rate rad/s) at ``t_s``."""
        j = min(max(bisect.bisect_right(self._t0_list, t_s) - 1, 0), len(self._t0_list) - 1)
        kind = self._kind_list[j]
        x, y, th = self._start_list[j]
        if kind == STOP:
            return np.array([x, y, th]), 0.0, 0.0
        m = self.motion
        dur, amount = self._dur_list[j], self._amount_list[j]
        tau = min(max(t_s - self._t0_list[j], 0.0), dur)
        v_max, acc = ((m.max_yaw_rate_radps, m.yaw_accel_radps2) if kind == TURN
                      else (m.max_speed_mps, m.accel_mps2))
        d = abs(amount)
        sign = 1.0 if amount >= 0 else -1.0
        t_acc = min(v_max / acc, dur / 2.0)
        v_peak = acc * t_acc
        if tau < t_acc:
            s, v = 0.5 * acc * tau * tau, acc * tau
        elif tau < dur - t_acc:
            s, v = 0.5 * acc * t_acc * t_acc + v_peak * (tau - t_acc), v_peak
        else:
            s, v = d - 0.5 * acc * (dur - tau) ** 2, acc * (dur - tau)
        s, v = sign * min(s, d), sign * max(v, 0.0)
        if kind == TURN:
            return np.array([x, y, wrap_angle(th + s)]), 0.0, v
        return np.array([x + s * math.cos(th), y + s * math.sin(th), th]), v, 0.0

    def velocity_at(self, t_s: np.ndarray | float) -> np.ndarray:
        """(N, 2) true (forward speed m/s, yaw rate rad/s) at times ``t_s``."""
        return self._eval(t_s)[1]

    def is_static(self, t_s: float) -> bool:
        """Whether the robot stands still at time ``t_s``."""
        _, v, w = self.state_at(t_s)
        return abs(v) < 1e-9 and abs(w) < 1e-9

    def stop_at(self, t_s: float) -> WaypointStop | None:
        """The waypoint dwell containing ``t_s``, if any."""
        for st in self.stops:
            if st.t0_s <= t_s <= st.t1_s:
                return st
        return None


class SimulatedRobot:
    """Steps the robot's sensors along a :class:`MotionPlan`.

    Call :meth:`step_to` with non-decreasing times; it advances the odometry and localization
    state in ticks of the odometry rate and returns the :class:`protocol.Odometry` messages of
    the ticks passed. :meth:`localization_pose` is the robot's own map pose (what the HSR
    navigation stack believes), :meth:`apply_correction` sets it (only while static).
    """

    def __init__(self, scenario: Scenario, plan: MotionPlan, rng: np.random.Generator,
                 robot_id: str | None = None) -> None:
        self.scenario = scenario
        self.plan = plan
        self.robot_id = robot_id or scenario.robot_id
        self._rng = rng
        oc, lc = scenario.odometry, scenario.localization
        self._dt_s = 1.0 / oc.rate_hz
        self._scale = 1.0 + rng.normal(0.0, oc.scale_sigma)
        self._yaw_scale = 1.0 + rng.normal(0.0, oc.yaw_scale_sigma)
        self._t_s = 0.0
        self._tick = 0
        self._gt = plan.state_at(0.0)[0]
        self._odom = np.zeros(3)
        self._odom_var = np.zeros(3)
        self._seq = 0
        # Localization error in the world frame (dx, dy, dtheta), OU over travelled distance.
        self._err = np.array([*rng.normal(0.0, lc.init_sigma_m, 2),
                              rng.normal(0.0, math.radians(lc.init_sigma_deg))])
        self._init_var = np.array([lc.init_sigma_m ** 2] * 2
                                  + [math.radians(lc.init_sigma_deg) ** 2])
        # the variance of that error, as a well-tuned particle filter would report it
        self._err_var = self._init_var.copy()
        self.travelled_m = 0.0
        self.corrections_applied = 0
        self.corrections_refused = 0

    @property
    def t_s(self) -> float:
        return self._t_s

    def stamp_ns(self, t_s: float) -> int:
        return self.scenario.start_stamp_ns + round(t_s * 1e9)

    def t_of(self, stamp_ns: int) -> float:
        return (stamp_ns - self.scenario.start_stamp_ns) * 1e-9

    def ground_truth(self) -> np.ndarray:
        """(3,) true pose at the current time."""
        return self._gt.copy()

    def localization_pose(self) -> np.ndarray:
        """(3,) the robot's internal localization (map frame) at the current time."""
        return np.array([self._gt[0] + self._err[0], self._gt[1] + self._err[1],
                         wrap_angle(self._gt[2] + self._err[2])])

    def localization_covariance(self) -> np.ndarray:
        """(3, 3) the variance of the localization error (x, y, theta), as the robot's own
        localization reports it: the error process's variance given the travelled distance
        since the start or the last correction."""
        return np.diag(self._err_var)

    def odometry_pose(self) -> np.ndarray:
        """(3,) integrated wheel odometry (odom frame) at the current time."""
        return self._odom.copy()

    def step_to(self, t_s: float) -> list[Odometry]:
        """Advance to ``t_s`` (s since the run start); returns the odometry messages due."""
        out: list[Odometry] = []
        while (self._tick + 1) * self._dt_s <= t_s + 1e-6:
            self._tick += 1
            out.append(self._advance(self._tick * self._dt_s))
        return out

    def _advance(self, t_s: float) -> Odometry:
        oc, lc = self.scenario.odometry, self.scenario.localization
        rng = self._rng
        gt_new, v_now, w_now = self.plan.state_at(t_s)
        d = se2_between(self._gt, gt_new)
        ds, dth = float(math.hypot(d[0], d[1])), float(d[2])
        if ds > 0.0 or dth != 0.0:
            # wheel odometry: systematic scale errors plus random walk per metre / radian
            meas = d.copy()
            meas[:2] *= self._scale
            meas[:2] += rng.normal(0.0, oc.sigma_m_per_sqrt_m * math.sqrt(ds), 2)
            meas[2] = (dth * self._yaw_scale
                       + rng.normal(0.0, oc.sigma_rad_per_sqrt_m * math.sqrt(ds))
                       + rng.normal(0.0, oc.sigma_rad_per_sqrt_rad * math.sqrt(abs(dth))))
            self._odom = se2_compose(self._odom, meas)
            self._odom_var += np.array([oc.sigma_m_per_sqrt_m ** 2 * ds] * 2
                                       + [oc.sigma_rad_per_sqrt_m ** 2 * ds
                                          + oc.sigma_rad_per_sqrt_rad ** 2 * abs(dth)])
            # localization error: Ornstein-Uhlenbeck in (distance + turn-equivalent distance)
            u = ds + lc.turn_equivalent_m_per_rad * abs(dth)
            L = lc.correlation_length_m
            decay = math.exp(-u / L)
            diffuse = math.sqrt(1.0 - decay * decay)
            sig = np.array([lc.stationary_sigma_m, lc.stationary_sigma_m,
                            math.radians(lc.stationary_sigma_deg)])
            if self.scenario.clutter:
                # LiDAR localization degrades where clutter hides the mapped walls
                sig = sig * self.scenario.localization_sigma_factor_at(self._gt[:2])
            self._err = self._err * decay + sig * diffuse * rng.normal(size=3)
            self._err_var = self._err_var * decay ** 2 + (sig * diffuse) ** 2
            self.travelled_m += ds
        self._gt = gt_new
        self._t_s = t_s
        msg = Odometry(
            robot_id=self.robot_id,
            stamp_ns=self.stamp_ns(t_s),
            seq=self._seq,
            x=float(self._odom[0]),
            y=float(self._odom[1]),
            theta=wrap_angle(self._odom[2]),
            vx=float(v_now * self._scale),
            wz=float(w_now * self._yaw_scale),
            covariance=np.diag(self._odom_var + 1e-9),
        )
        self._seq += 1
        return msg

    def is_static(self, t_s: float | None = None) -> bool:
        return self.plan.is_static(self._t_s if t_s is None else t_s)

    def apply_correction(self, pose: np.ndarray | Sequence[float], stamp_ns: int) -> bool:
        """Set the internal localization to ``pose`` (x, y, theta; map frame) observed at
        ``stamp_ns``. Like the HSR, it is accepted only while the robot is static (now and at
        the stamp); returns whether it was applied."""
        t_stamp = self.t_of(stamp_ns)
        if not (self.is_static() and self.is_static(t_stamp)):
            self.corrections_refused += 1
            return False
        p = np.asarray(pose, dtype=np.float64).reshape(3)
        self._err = np.array([p[0] - self._gt[0], p[1] - self._gt[1],
                              angle_diff(p[2], self._gt[2])])
        self._err_var = self._init_var.copy()
        self.corrections_applied += 1
        return True
