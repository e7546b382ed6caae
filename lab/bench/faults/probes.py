"""The probe catalogue of ``smartedge bench reliability``: one :class:`Probe` per fault, by
name (:data:`PROBES`), each with its injector (what the attacker session sends, or what is done
to a process) and its judge (the figures and whether what must hold held).

Probes that forge estimates (``forged_pose_*``) measure the robot bridge's own defences: the
loopback peers have no TLS, so the router's access control is not in the loop.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Any, Final

import numpy as np

from lab.bench.faults.harness import FAKE_SEQ0, Probe, Run, Verdict
from protocol import decode, encode, keys
from protocol.errors import DecodeError
from protocol.messages import NS_PER_S, Odometry, PoseEstimate, RobotDetections
from simulation.hostile import hostile_payloads

#: the status is published every second; a longer gap means a pinned worker
MAX_STATUS_GAP_S: Final = 3.0
#: how far above its level before a burst the backend's RSS may stay after it
RSS_TOLERANCE_MIB: Final = 100.0


def _put_loop(run: Run, key: str, rate_hz: float, make: Callable[[int], bytes | None],
              end_s: float | None = None) -> int:
    """Put ``make(i)`` on ``key`` from the attacker at ``rate_hz`` until ``end_s`` (default:
    the fault's end); a ``None`` payload is skipped. Returns the number put."""
    import zenoh

    pub = run.attacker.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
    end_s = run.fault[1] if end_s is None else end_s
    period = 1.0 / rate_hz
    sent = 0
    next_t = time.monotonic()
    try:
        while not run.stop.is_set() and run.sim_t() < end_s:
            payload = make(sent)
            if payload is not None:
                pub.put(payload)
                sent += 1
            next_t += period
            lag = next_t - time.monotonic()
            if lag > 0:
                time.sleep(lag)
            elif lag < -1.0:  # fell behind (a busy machine): do not burst to catch up
                next_t = time.monotonic()
    finally:
        pub.undeclare()
    return sent


def _fake_estimates(offset_m: tuple[float, float], *, covariance: np.ndarray,
                    ahead_s: float = 0.0, rate_hz: float = 50.0,
                    end_s: float | None = None) -> Callable[[Run], None]:
    """An injector: fused estimates of the robot from a non-backend peer at ``rate_hz``,
    ``offset_m`` (map frame) from the robot's own localization (from the ground truth while
    it has none), stamped ``ahead_s`` in the future, with ``covariance``."""

    def inject(run: Run) -> None:
        if not run.sleep_until(run.fault[0]):
            return

        def make(i: int) -> bytes | None:
            now = time.time_ns()
            base = run.latest_localization()
            if base is None:
                base = run.live.ground_truth(now)
            est = PoseEstimate(run.robot_id, now + round(ahead_s * NS_PER_S), FAKE_SEQ0 + i,
                               float(base[0] + offset_m[0]), float(base[1] + offset_m[1]),
                               float(base[2]), covariance, "fused")
            return encode(est)

        run.notes["fakes_sent"] = _put_loop(run, keys.pose_key(run.site, run.robot_id),
                                            rate_hz, make, end_s)

    return inject


def _common(run: Run, ref: Run | None, window: tuple[float, float] | None = None
            ) -> tuple[list[str], tuple[float, float]]:
    """Figures every row has: crashes, camera poses in the fault window (or ``window``; with
    the baseline's same window, or the run's own pre-fault window), and the backend's RSS."""
    t0, t1 = window or run.fault
    cam = run.camera(t0, t1)
    if ref is not None:
        without, label = ref.camera(t0, t1), "baseline run"
    else:
        pre0 = max(0.0, t0 - (t1 - t0))
        without, label = run.camera(pre0, t0), "pre-fault"
    crashed = f" ({', '.join(run.crashes)})" if run.crashes else ""
    figures = [f"crashes: {len(run.crashes)}{crashed}",
               f"camera poses with the fault {cam.text()} (without, {label}: {without.text()})",
               f"backend RSS {run.rss_fault_start_mib:.0f} → {run.rss_end_mib:.0f} MiB "
               f"(peak {run.rss_peak_mib:.0f})"]
    if run.injector_error:
        figures.append(f"injection failed: {run.injector_error}")
    return figures, (cam.rate_hz, without.rate_hz)


def _bridge_figures(run: Run, counters: Sequence[str]) -> list[str]:
    t0, _ = run.fault
    got = {c: run.delta("robot-bridge/hsr", f"bridge.{c}", t0) for c in counters}
    return [", ".join(f"`{c}` {v}" for c, v in got.items())]


def _localization_figures(run: Run) -> tuple[list[str], float, float]:
    """Robot's localization error before the fault → max during/after → at the end, and the
    corrections pushed; returns (figures, max error m, end error m)."""
    t0, _ = run.fault
    before = run.localization_error_at(t0)
    after = run.localization_error(t0, run.run_s)
    worst = float(after.max()) if after.size else math.nan
    end = run.localization_error_at(run.run_s)
    corr = run.corrections(t0, run.run_s)
    corr_text = ", ".join(f"{k} at t={t:.0f} s {100 * d:.0f} cm from the truth"
                          for t, k, d in corr) or "none"
    return ([f"robot's localization error {100 * before:.0f} cm → max {100 * worst:.0f} cm, "
             f"{100 * end:.0f} cm at the end", f"corrections pushed: {len(corr)} ({corr_text})"],
            worst, end)


# -- baseline: no fault --------------------------------------------------------------------


def _no_fault(run: Run) -> None:
    return


def _judge_baseline(run: Run, _ref: Run | None) -> Verdict:
    cam = run.camera(5.0, run.run_s)
    n, fused_rms, fused_max = run.fused(5.0, run.run_s)
    loc, _, end = _localization_figures(run)
    states = collections.Counter(s.state for s in run.statuses("backend/main", 5.0, run.run_s))
    figures = [f"crashes: {len(run.crashes)}",
               f"camera poses {cam.text()}",
               f"fused {n / (run.run_s - 5.0):.1f} Hz, {fused_rms:.1f} cm RMS "
               f"(max {fused_max:.0f})",
               *loc,
               f"backend status {dict(states)}; RSS {run.rss_fault_start_mib:.0f} → "
               f"{run.rss_end_mib:.0f} MiB"]
    ok = (not run.crashes and cam.n > 0 and fused_rms < 10.0 and end < 0.2
          and states.get("ok", 0) >= 0.9 * sum(states.values()))
    return Verdict(figures, ok)


# -- forged_pose_*: fused estimates of the robot from a peer that is not the backend -------


def _judge_fake(expect_refused: str, *, bound_m: float = 0.3) -> Callable[[Run, Run | None],
                                                                          Verdict]:
    def judge(run: Run, ref: Run | None) -> Verdict:
        figures, _ = _common(run, ref)
        loc, worst, _ = _localization_figures(run)
        counters = [expect_refused, "received_estimate_fused", "late_estimate",
                    "skip_jump_too_large", "skip_correction_window_exceeded", "corrections_sent"]
        bridge = _bridge_figures(run, counters)
        sent = int(run.notes.get("fakes_sent", 0))
        figures = [f"{sent} fakes sent", *loc, *bridge, *figures]
        refused = run.delta("robot-bridge/hsr", f"bridge.{expect_refused}", run.fault[0])
        if expect_refused == "future_stamp_estimate":
            ok = refused >= 0.95 * sent and worst < bound_m and not run.crashes
        else:
            ok = worst < bound_m and refused >= 1 and not run.crashes
        return Verdict(figures, ok)

    return judge


# -- forged_pose_while_kidnapped: the first estimates a fake 30 m away ---------------------


def _judge_kidnapped(run: Run, ref: Run | None) -> Verdict:
    figures, _ = _common(run, ref, (0.0, run.run_s))  # no camera frames before t = 0
    inits = [c for c in run.corrections(-math.inf, math.inf) if c[1] == "initialization"]
    bridge = _bridge_figures(run, ["skip_outside_floor_area", "skip_awaiting_agreement",
                                   "initializations_sent"])
    first = (f"first initialization at t={inits[0][0]:.1f} s, {100 * inits[0][2]:.0f} cm from "
             "the truth") if inits else "no initialization"
    end = run.localization_error_at(run.run_s)
    figures = [f"{run.notes.get('fakes_sent', 0)} fakes sent (30 m away)", first,
               f"robot's localization error at the end {100 * end:.0f} cm", *bridge, *figures]
    ok = (bool(inits) and inits[0][2] < 0.3 and end < 0.3 and not run.crashes
          and run.delta("robot-bridge/hsr", "bridge.skip_outside_floor_area", -math.inf) >= 1)
    return Verdict(figures, ok)


# -- poisoned_odometry: one odometry stamped 2**63-1, then odometry with a wrong pose ------


def _inject_odometry(run: Run, wrong: int = 200, rate_hz: float = 30.0,
                     offset_m: float = 1.0) -> None:
    import zenoh

    latest: list[Odometry] = []
    key = keys.odom_key(run.site, run.robot_id)

    def on_odom(sample: Any) -> None:
        try:
            msg: Any = decode(sample.payload.to_bytes())
        except DecodeError:
            return
        if isinstance(msg, Odometry) and msg.seq < FAKE_SEQ0:
            latest[:] = [msg]

    sub = run.attacker.declare_subscriber(key, on_odom)
    pub = run.attacker.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                         reliability=zenoh.Reliability.RELIABLE)
    try:
        if not run.sleep_until(run.fault[0]):
            return
        base = latest[0] if latest else Odometry(run.robot_id, 0, 0, 0.0, 0.0, 0.0)
        pub.put(encode(dataclasses.replace(base, stamp_ns=2**63 - 1, seq=FAKE_SEQ0)))
        run.notes["far_future_at"] = run.sim_t()
        sent = 0
        next_t = time.monotonic()
        while sent < wrong and not run.stop.is_set() and run.sim_t() < run.fault[1]:
            g = latest[0] if latest else base
            pub.put(encode(dataclasses.replace(g, stamp_ns=time.time_ns(), seq=FAKE_SEQ0 + 1 + sent,
                                               x=g.x + offset_m, y=g.y + 0.5 * offset_m)))
            sent += 1
            next_t += 1.0 / rate_hz
            time.sleep(max(0.0, next_t - time.monotonic()))
        run.notes["wrong_sent"] = sent
        run.notes["wrong_end"] = run.sim_t()
    finally:
        pub.undeclare()
        sub.undeclare()


def _judge_odometry(run: Run, ref: Run | None) -> Verdict:
    figures, _ = _common(run, ref)
    t0, t1 = run.fault
    end_wrong = float(run.notes.get("wrong_end", t1))
    b = "backend/main"
    fusion = [f"fusion.{run.robot_id}.{k}" for k in ("odometry_stamp_reset",
                                                     "odometry_out_of_order", "restarts")]
    counted = {c: run.delta(b, c, t0) for c in ["odometry_future", *fusion]}
    n_during, rms_during, max_during = run.fused(t0, end_wrong)
    after0 = min(end_wrong + 5.0, run.run_s - 1.0)
    n_after, rms_after, _ = run.fused(after0, run.run_s)
    if ref is not None:
        n_ref, rms_ref, _ = ref.fused(after0, run.run_s)
        ref_text = f" (baseline {n_ref / (run.run_s - after0):.1f} Hz, {rms_ref:.1f} cm)"
    else:
        n_ref, ref_text = 0, ""
    cam_all = run.camera(t0, run.run_s)
    reasons = run.degraded(b, t0, run.run_s)
    fused_rate_after = n_after / max(run.run_s - after0, 1e-9)
    figures = [f"1 odometry stamped 2^63-1, then {run.notes.get('wrong_sent', 0)} valid "
               f"odometry {math.hypot(1.0, 0.5):.2f} m off",
               ", ".join(f"`{c}` {v}" for c, v in counted.items() if v or c == "odometry_future"),
               f"fused while the wrong odometry came: {n_during} poses, {rms_during:.0f} cm RMS, "
               f"max {max_during:.0f} cm; from {after0:.0f} s: "
               f"{fused_rate_after:.1f} Hz, {rms_after:.1f} cm RMS{ref_text}",
               f"camera poses > 1 m off: {cam_all.over_1m_pct:.0f} %",
               f"backend status degraded: {'; '.join(reasons) or 'never'}",
               *figures]
    ok = (counted["odometry_future"] >= 1 and n_after > 0 and rms_after < 10.0
          and cam_all.over_1m_pct == 0 and (n_ref == 0 or n_after >= 0.8 * n_ref)
          and any("odometry" in r for r in reasons) and not run.crashes)
    return Verdict(figures, ok)


# -- camera_clock_ahead: one camera 0.5 s ahead -------------------------------------------


AHEAD_CAMERA: Final = "cam1"
AHEAD_S: Final = 0.5


def _inject_camera_ahead(run: Run) -> None:
    """Publish :data:`AHEAD_CAMERA`'s simulated detections as its edge agent would (that agent
    is not started), stamped :data:`AHEAD_S` ahead while the fault is on."""
    import zenoh

    from simulation.live import CameraFeed

    feed = CameraFeed(run.live, AHEAD_CAMERA)
    pub = run.attacker.declare_publisher(keys.detections_key(run.site, AHEAD_CAMERA),
                                         congestion_control=zenoh.CongestionControl.BLOCK)
    shifted = 0
    try:
        while not run.stop.is_set():
            for msg in feed.poll(time.time_ns()):
                if run.in_fault:
                    ahead_ns = round(AHEAD_S * NS_PER_S)
                    msg = dataclasses.replace(msg, stamp_ns=msg.stamp_ns + ahead_ns)
                    shifted += 1
                pub.put(encode(msg))
            time.sleep(0.005)
    finally:
        run.notes["shifted"] = shifted
        pub.undeclare()


def _judge_camera_ahead(run: Run, ref: Run | None) -> Verdict:
    figures, (rate, rate_without) = _common(run, ref)
    t0, t1 = run.fault
    b = "backend/main"
    cam = run.camera(t0, t1)
    future = run.delta(b, f"sync.camera.{AHEAD_CAMERA}.future", t0)
    others = [c for c in run.cameras if c != AHEAD_CAMERA]
    late = {c: run.delta(b, f"sync.camera.{c}.late", t0) for c in others}
    received = {c: run.delta(b, f"sync.camera.{c}.received", t0) for c in others}
    reasons = run.degraded(b, t0, t1 + 2.0)
    corr = run.corrections(t0, t1)
    figures = [f"{run.notes.get('shifted', 0)} {AHEAD_CAMERA} frames stamped +0.5 s",
               f"`sync.camera.{AHEAD_CAMERA}.future` {future}, other cameras' `late` "
               f"{sum(late.values())} of {sum(received.values())} frames",
               f"backend status degraded: {'; '.join(reasons) or 'never'}",
               f"corrections in the window: {len(corr)}"
               + (f" (max {100 * max(d for _, _, d in corr):.0f} cm from the truth)"
                  if corr else ""),
               *figures]
    ok = (future >= 1 and sum(late.values()) <= 0.02 * max(1, sum(received.values()))
          and cam.n > 0 and rate >= 0.8 * rate_without and cam.max_gap_s < 3.0
          and any(AHEAD_CAMERA in r for r in reasons) and not run.crashes)
    return Verdict(figures, ok)


# -- rogue_detection_source: a 1000 Hz source on one camera's key -------------------------


ROGUE_CAMERA: Final = "cam2"


def _inject_rogue(run: Run, rate_hz: float = 1000.0) -> None:
    """Detections of :data:`ROGUE_CAMERA` at ``rate_hz`` (a plausible frame of the robot where
    it truly is, refreshed every 20 ms, stamped now), on top of that camera's agent."""
    rng = np.random.default_rng(7)
    detector = run.live.run.detector
    frame: list[RobotDetections] = []
    refreshed = [0]
    if not run.sleep_until(run.fault[0]):
        return
    t_start = time.monotonic()

    def make(i: int) -> bytes:
        now = time.time_ns()
        if not frame or now - refreshed[0] > 20_000_000:
            frame[:] = [detector.detect(ROGUE_CAMERA, now, run.live.ground_truth(now), 0, rng)]
            refreshed[0] = now
        return encode(dataclasses.replace(frame[0], stamp_ns=now, seq=FAKE_SEQ0 + i))

    import zenoh

    pub = run.attacker.declare_publisher(keys.detections_key(run.site, ROGUE_CAMERA),
                                         congestion_control=zenoh.CongestionControl.DROP)
    sent = 0
    next_t = time.monotonic()
    try:
        while not run.stop.is_set() and run.sim_t() < run.fault[1]:
            # bursts of 10 every 10 ms: a Python sleep is too coarse for 1 ms periods
            for _ in range(10):
                pub.put(make(sent))
                sent += 1
            next_t += 10.0 / rate_hz
            time.sleep(max(0.0, next_t - time.monotonic()))
            if next_t < time.monotonic() - 1.0:
                next_t = time.monotonic()
    finally:
        pub.undeclare()
    run.notes["rogue_sent"] = sent
    run.notes["rogue_rate_hz"] = sent / max(time.monotonic() - t_start, 1e-9)


def _judge_rogue(run: Run, ref: Run | None) -> Verdict:
    figures, (rate, rate_without) = _common(run, ref)
    t0, t1 = run.fault
    b = "backend/main"
    limited = run.delta(b, f"sync.camera.{ROGUE_CAMERA}.rate_limited", t0)
    received = run.delta(b, f"sync.camera.{ROGUE_CAMERA}.received", t0)
    reasons = run.degraded(b, t0, t1 + 2.0)
    gap = run.status_gap_s(b, t0, t1)
    cam = run.camera(t0, t1)
    without = ref.camera(t0, t1) if ref is not None else None
    figures = [f"{run.notes.get('rogue_sent', 0)} rogue frames at "
               f"{run.notes.get('rogue_rate_hz', 0):.0f} Hz",
               f"`sync.camera.{ROGUE_CAMERA}.rate_limited` {limited} of {received} received",
               f"backend status degraded: {'; '.join(reasons) or 'never'}; longest status gap "
               f"{gap:.1f} s", *figures]
    err_ok = without is None or not without.n or cam.rms_cm <= without.rms_cm + 2.0
    ok = (limited >= 0.5 * received and any(ROGUE_CAMERA in r and "rogue" in r for r in reasons)
          and rate >= 0.8 * rate_without and err_ok and gap < MAX_STATUS_GAP_S
          and not run.crashes)
    return Verdict(figures, ok)


# -- oversized_*_detections: bursts of oversized detection messages -----------------------


def _oversized(which: str) -> Callable[[Run], None]:
    def inject(run: Run) -> None:
        import zenoh

        rng = np.random.default_rng(0)
        cam = run.cameras[0]
        now = time.time_ns()
        real = run.live.run.detector.detect(cam, now, run.live.ground_truth(now), 0, rng)
        payloads = hostile_payloads(real)[which]
        pub = run.attacker.declare_publisher(keys.detections_key(run.site, cam),
                                             congestion_control=zenoh.CongestionControl.BLOCK,
                                             reliability=zenoh.Reliability.RELIABLE)
        try:
            if not run.sleep_until(run.fault[0]):
                return
            t0 = time.monotonic()
            for p in payloads:
                if run.stop.is_set():
                    return
                pub.put(p)
            run.notes["send_s"] = time.monotonic() - t0
            run.notes["messages"] = len(payloads)
            run.notes["mb_each"] = len(payloads[0]) / 1e6
        finally:
            pub.undeclare()

    return inject


def _judge_oversized(run: Run, ref: Run | None) -> Verdict:
    figures, _ = _common(run, ref)
    t0, _ = run.fault
    b = "backend/main"
    n = int(run.notes.get("messages", 0))
    refused = run.delta(b, "invalid", t0)
    dropped = run.delta(b, "dropped", t0)
    reasons = {k: run.delta(b, k, t0) for k in run.counters(b) if k.startswith("invalid.")}
    reasons = {k: v for k, v in reasons.items() if v}
    window = (t0, min(t0 + 10.0, run.run_s))
    gap = run.status_gap_s(b, *window)
    cam = run.camera(*window)
    settled_ok = run.rss_end_mib < run.rss_fault_start_mib + RSS_TOLERANCE_MIB
    figures = [f"{n} x {run.notes.get('mb_each', 0):.1f} MB sent in "
               f"{run.notes.get('send_s', math.nan):.1f} s: refused {refused} "
               f"({', '.join(f'`{k}` {v}' for k, v in reasons.items())}), dropped {dropped}",
               f"within 10 s of the burst: longest status gap {gap:.1f} s, longest camera pose "
               f"gap {cam.max_gap_s:.1f} s, {cam.rms_cm:.1f} cm RMS", *figures]
    ok = (n > 0 and refused + dropped >= n and gap < MAX_STATUS_GAP_S and cam.max_gap_s < 3.0
          and settled_ok and not run.crashes)
    return Verdict(figures, ok)


# -- backend_restart: the backend SIGKILLed and started again -----------------------------


def _inject_restart(run: Run) -> None:
    if not run.sleep_until(run.fault[0]):
        return
    run.stack.kill("backend")
    run.notes["killed_ns"] = time.time_ns()
    if not run.sleep_until(run.fault[1]):
        return
    run.stack.start("backend")
    run.notes["restarted_ns"] = time.time_ns()


def _judge_restart(run: Run, ref: Run | None) -> Verdict:
    assert run.monitor is not None
    t0, t1 = run.fault
    restarted = int(run.notes.get("restarted_ns", 0))

    def first_after(arrivals: list[int]) -> float:
        later = [a for a in arrivals if a > restarted]
        return (later[0] - restarted) / NS_PER_S if restarted and later else math.nan

    cam_s = first_after(run.monitor.camera_arrivals)
    fused_s = first_after(run.monitor.fused_arrivals)
    bridge = "robot-bridge/hsr"
    replayed = run.delta(bridge, "bridge.odometry_replayed", t0)
    lost = run.delta(bridge, "bridge.odometry_lost", t0)
    states = [s.state for s in run.statuses(bridge, t0 + 3.0, t1)]
    last = run.statuses(bridge, t1, run.run_s)
    end_state = last[-1].state if last else "-"
    after0 = min(t1 + 10.0, run.run_s - 1.0)
    _, rms, mx = run.fused(after0, run.run_s)
    loc, _, _ = _localization_figures(run)
    figures = [f"backend SIGKILLed at t={t0:.0f} s, restarted at t={t1:.0f} s",
               f"`bridge.odometry_replayed` {replayed}, `bridge.odometry_lost` {lost}",
               f"first camera pose {cam_s:.1f} s and first fused pose {fused_s:.1f} s after "
               "the restart",
               f"bridge status while away: {', '.join(sorted(set(states))) or '-'}, at the end "
               f"{end_state}",
               f"fused from t={after0:.0f} s: {rms:.1f} cm RMS (max {mx:.0f})", *loc,
               f"crashes: {len(run.crashes)}; restarted backend RSS {run.rss_end_mib:.0f} MiB"]
    ok = (replayed > 0 and lost == 0 and cam_s < 15.0 and fused_s < 15.0
          and "degraded" in states and end_state == "ok" and rms < 10.0 and not run.crashes)
    return Verdict(figures, ok)


# -- the catalogue ---------------------------------------------------------------------------

FAKE_COV: Final = 1e-4 * np.eye(3)

PROBES: Final[dict[str, Probe]] = {p.name: p for p in [
    Probe(name="baseline", sends="no fault (the reference of the other probes)",
          holds="fused < 10 cm RMS, localization < 20 cm at the end, backend 'ok' in >= 90 % "
          "of its statuses",
          before="-", run_s=76.0, fault=(5.0, 76.0), inject=_no_fault, judge=_judge_baseline),
    Probe(name="forged_pose_future_stamp",
          sends="fake fused pose (covariance 1e-4·I, stamp now+0.3 s, 0.95 m off) at 50 Hz "
          "from a non-backend peer",
          holds="every fake refused and counted, the robot's localization never > 30 cm off",
          before="a 0.95 m correction at each of 6 stops: localization error ~5 cm → 3.94 m; "
          "all 2,849 genuine estimates discarded as late",
          run_s=45.0, fault=(2.0, 40.0),
          inject=_fake_estimates((0.95, 0.0), covariance=FAKE_COV, ahead_s=0.3),
          judge=_judge_fake("future_stamp_estimate")),
    Probe(name="forged_pose_stamped_now",
          sends="forged_pose_future_stamp stamped now instead of now+0.3 s (what is left to "
          "the bridge without the router's ACL)",
          holds="refusal counted (`skip_jump_too_large`), the robot's localization never "
          "> 120 cm off",
          before="(not probed)", run_s=45.0, fault=(2.0, 40.0),
          inject=_fake_estimates((0.95, 0.0), covariance=FAKE_COV),
          judge=_judge_fake("skip_jump_too_large", bound_m=1.2)),
    Probe(name="forged_pose_zero_covariance",
          sends="zero-covariance fused estimate 1.5 m off, stamp now, 50 Hz",
          holds="refusal counted (`skip_jump_too_large`), the robot's localization never "
          "> 30 cm off",
          before="gated on the sender's own covariance (the uncertainty gate of "
          "`CorrectionPolicy.decide`)",
          run_s=40.0, fault=(2.0, 35.0),
          inject=_fake_estimates((1.5, 0.0), covariance=np.zeros((3, 3))),
          judge=_judge_fake("skip_jump_too_large")),
    Probe(name="forged_pose_sub_limit_jumps",
          sends="repeated sub-limit jumps: fused estimate 0.6 m off the current "
          "localization, stamp now, 50 Hz through 3 stops",
          holds="refusal counted (`skip_jump_too_large`), the robot's localization never "
          "> 75 cm off",
          before="jump limit relative to a localization the attacker already moved: no bound "
          "on accumulation",
          run_s=76.0, fault=(2.0, 58.0),
          inject=_fake_estimates((0.6, 0.0), covariance=FAKE_COV),
          judge=_judge_fake("skip_jump_too_large", bound_m=0.75)),
    Probe(name="forged_pose_while_kidnapped",
          sends="--kidnapped, the first poses a fake 30 m away (outside the room)",
          holds="the fake refused (`skip_outside_floor_area`), the robot initialized from the "
          "genuine estimates within 30 cm",
          before="the fake accepted as the initialization; the 1 m jump limit then rejected "
          "the genuine estimates",
          run_s=25.0, fault=(-3.0, 3.0),
          inject=_fake_estimates((30.0, 0.0), covariance=FAKE_COV), judge=_judge_kidnapped,
          kidnapped=True),
    Probe(name="poisoned_odometry",
          sends="one odometry stamped 2^63-1 on .../odom, then 200 valid odometry 1.1 m off",
          holds="far-future stamp counted and named in the status; fused poses keep coming "
          "(>= 80 % of the baseline rate) and < 10 cm RMS 5 s after the wrong odometry stops; "
          "no camera pose > 1 m off",
          before="fusion stopped for good, status 'ok'; 16 % of camera poses > 1 m off (up to "
          "1.77 km); ~219 wrong odometry → 295 graph restarts, fused error up to 1.3 m",
          run_s=40.0, fault=(10.0, 20.0), inject=_inject_odometry, judge=_judge_odometry),
    Probe(name="camera_clock_ahead", sends=f"one camera ({AHEAD_CAMERA}) 0.5 s ahead",
          holds=f"{AHEAD_CAMERA}'s frames counted as future, <= 2 % of the others' frames "
          "late, camera pose rate >= 80 % of without, no gap >= 3 s, status degraded naming "
          "the camera",
          before="pose rate 15.4 → 6.9 Hz; 1,008 other cameras' frames late in 23 s; 12.4 s "
          "without a camera pose; camera error 3.9 → 19.2 cm; a correction with 15 cm error",
          run_s=40.0, fault=(15.0, 40.0), inject=_inject_camera_ahead,
          judge=_judge_camera_ahead, skip_agents=(AHEAD_CAMERA,)),
    Probe(name="rogue_detection_source",
          sends=f"rogue 1000 Hz detection source for {ROGUE_CAMERA}",
          holds="rogue frames cut and counted, status names the camera as rogue, camera pose "
          "rate >= 80 % and RMS within 2 cm of without, status every "
          f"< {MAX_STATUS_GAP_S:.0f} s",
          before="not flagged", run_s=35.0, fault=(10.0, 30.0), inject=_inject_rogue,
          judge=_judge_rogue),
    Probe(name="oversized_nested_detections",
          sends="100 detection messages of 1.5 MB (nested detections)",
          holds="every message refused or dropped and counted, status and camera poses "
          f"without a gap >= {MAX_STATUS_GAP_S:.0f} s, RSS back within "
          f"{RSS_TOLERANCE_MIB:.0f} MiB",
          before="worker pinned ~30 s, poses up to 28.9 s stale, a correction missed, RSS "
          "146 → 322 MiB, not released",
          run_s=25.0, fault=(10.0, 25.0), inject=_oversized("nested"), judge=_judge_oversized),
    Probe(name="oversized_padded_detections",
          sends="20 valid detection messages padded to 50 MB (unknown key)",
          holds="every message refused or dropped and counted, status and camera poses "
          f"without a gap >= {MAX_STATUS_GAP_S:.0f} s, RSS back within "
          f"{RSS_TOLERANCE_MIB:.0f} MiB",
          before="accepted; backend at 1.53 GiB", run_s=30.0, fault=(10.0, 30.0),
          inject=_oversized("padded"), judge=_judge_oversized),
    Probe(name="backend_restart", sends="backend SIGKILLed and restarted 10 s later",
          holds="odometry of the outage replayed, none lost; poses within 15 s of the "
          "restart; bridge degraded while away, ok after; fused < 10 cm",
          before="~148 odometry messages lost during the restart", run_s=50.0,
          fault=(15.0, 25.0), inject=_inject_restart, judge=_judge_restart),
]}


__all__ = ["FAKE_COV", "MAX_STATUS_GAP_S", "PROBES", "RSS_TOLERANCE_MIB"]
