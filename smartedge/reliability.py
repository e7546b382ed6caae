"""``smartedge bench reliability``: hostile and faulty input against the running system.

Every probe starts the real services as OS processes on Zenoh loopback, the way ``smartedge
demo --processes`` does (backend, four simulated edge agents with the detection noise model,
the robot bridge on the simulated HSR; no viewer, no clouds), lets the simulated robot drive
the paper site's ``traj3``, injects one fault from a separate *attacker* Zenoh session (or
kills a process), and measures what the system did against the simulator's ground truth:
crashes, the services' counters and status, the backend's resident memory (``/proc``), camera
pose rate and error, fused error, the robot's own localization error, corrections pushed, and
recovery times. One Markdown table row per probe: probe, the figure issue 17 measured before
the fixes, the figures now, the verdict against the criterion the row states.

The ``baseline`` probe runs the same system without a fault; the other probes compare their
fault window with the same window of the baseline run (same trajectory, same seed), or with
their own pre-fault window when the baseline was not run.

The loopback peers have no TLS, so the router's access control (the identity mechanism,
docs/deployment.md) is not in the loop: a probe that poses as the backend measures the robot
bridge's own defences only.

Also the shared helpers of the oversized-message tests (:func:`rss_mib`, :class:`RssSampler`,
:func:`hostile_payloads`).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import math
import os
import platform
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Final

import msgpack  # type: ignore[import-untyped]
import numpy as np

from protocol import decode, encode, keys
from protocol.errors import DecodeError
from protocol.limits import PAYLOAD_CAPS
from protocol.messages import (
    Odometry,
    PoseCorrection,
    PoseEstimate,
    RobotDetections,
    ServiceStatus,
)
from protocol.session import loopback_config
from smartedge.demo import Monitor, Services, _free_port

MiB: Final = 1024 * 1024
NS: Final = 1_000_000_000
#: seconds between starting the services and the simulation's t = 0
STARTUP_S: Final = 10.0
#: sequence numbers of the attacker's own messages start here (so the monitor can tell them)
FAKE_SEQ0: Final = 1_000_000_000
#: the simulated robot's dwell at each waypoint and top speed (the demo's)
STOP_S: Final = 4.0
MAX_SPEED_MPS: Final = 0.4
TRAJECTORY: Final = "traj3"
#: the status is published every second; a longer gap means a pinned worker
MAX_STATUS_GAP_S: Final = 3.0
#: how far above its level before a burst the backend's RSS may stay after it
RSS_TOLERANCE_MIB: Final = 100.0


# ------------------------------------------------------------------------------------------
# Shared helpers (tests/system/test_oversized.py uses them too)
# ------------------------------------------------------------------------------------------


def rss_mib(pid: int) -> float:
    """Resident set size of process ``pid`` in MiB (Linux ``/proc``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for process {pid}")


class RssSampler:
    """Samples a process's RSS every 50 ms in a thread; ``peak_mib`` is the largest seen."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.peak_mib = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            try:
                self.peak_mib = max(self.peak_mib, rss_mib(self.pid))
            except (OSError, RuntimeError):
                return

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join(2)


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


# ------------------------------------------------------------------------------------------
# Observation
# ------------------------------------------------------------------------------------------


class TimedMonitor(Monitor):
    """The demo's :class:`~smartedge.demo.Monitor` that also keeps every status message with
    its arrival time (``statuses[name]``: (arrival ns, status)), the arrival time of every
    camera and fused pose, and sets the attacker's own fake estimates aside (``fakes``)."""

    def __init__(self, site: str, robot_id: str, endpoint: str) -> None:
        self._timed: collections.deque[tuple[str, bytes, int]] = collections.deque()
        self.statuses: dict[str, list[tuple[int, ServiceStatus]]] = collections.defaultdict(list)
        self.camera_arrivals: list[int] = []
        self.fused_arrivals: list[int] = []
        self.fakes = 0
        self.undecodable = 0
        super().__init__(site, robot_id, endpoint)

    def _on(self, sample: Any) -> None:  # Zenoh thread: hand over only
        self._timed.append((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    def drain(self) -> None:
        seen = self.seen
        while self._timed:
            key, payload, arrival_ns = self._timed.popleft()
            try:
                msg: Any = decode(payload)
            except DecodeError:
                self.undecodable += 1
                continue
            if isinstance(msg, ServiceStatus):
                name = f"{msg.service}/{msg.instance_id}"
                seen.status[name] = msg
                seen.status_count += 1
                self.statuses[name].append((arrival_ns, msg))
            elif isinstance(msg, PoseCorrection):
                seen.corrections.append(msg)
            elif not isinstance(msg, PoseEstimate):
                continue
            elif msg.seq >= FAKE_SEQ0:
                self.fakes += 1
            elif key.endswith("/camera_pose"):
                seen.camera.append(msg)
                self.camera_arrivals.append(arrival_ns)
            elif key.endswith("/pose"):
                seen.fused.append(msg)
                self.fused_arrivals.append(arrival_ns)
            elif key.endswith("/localization"):
                seen.localization.append(msg)


class Stack:
    """The services as OS processes (the demo's command lines), by name; a process may be
    killed and started again (``restart``), which :meth:`unexpected_exits` does not count."""

    def __init__(self, commands: dict[str, list[str]], log_dir: Path) -> None:
        self.commands = commands
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.killed: list[subprocess.Popen[bytes]] = []
        self._starts: collections.Counter[str] = collections.Counter()

    def start(self, name: str | None = None) -> None:
        for n in [name] if name else list(self.commands):
            suffix = f".{self._starts[n]}" if self._starts[n] else ""
            log = (self.log_dir / f"{n.replace('/', '_')}{suffix}.log").open("w")
            self._starts[n] += 1
            self.procs[n] = subprocess.Popen(
                [sys.executable, "-m", "smartedge", *self.commands[n]],
                stdout=log, stderr=subprocess.STDOUT,
                env={**os.environ, "PYTHONUNBUFFERED": "1"})
            log.close()

    def kill(self, name: str) -> None:
        proc = self.procs[name]
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        self.killed.append(proc)

    def pid(self, name: str) -> int:
        return int(self.procs[name].pid)

    def unexpected_exits(self) -> list[str]:
        killed = {id(p) for p in self.killed}
        return [n for n, p in self.procs.items() if p.poll() is not None and id(p) not in killed]

    def stop(self) -> dict[str, int]:
        """SIGTERM to every process still running (last started first); the exit codes."""
        for proc in reversed(list(self.procs.values())):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        codes: dict[str, int] = {}
        for name, proc in reversed(list(self.procs.items())):
            try:
                codes[name] = int(proc.wait(timeout=20))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
                codes[name] = -9
        return codes


# ------------------------------------------------------------------------------------------
# One probe run
# ------------------------------------------------------------------------------------------


@dataclasses.dataclass
class CameraFigures:
    """Camera-only (single-frame) poses whose stamps fall in a window."""

    n: int
    rate_hz: float
    rms_cm: float
    mean_cm: float
    over_1m_pct: float
    max_gap_s: float

    def text(self) -> str:
        if not self.n:
            return "no camera pose"
        return (f"{self.rate_hz:.1f} Hz, {self.rms_cm:.1f} cm RMS, "
                f"{self.over_1m_pct:.0f} % > 1 m, longest gap {self.max_gap_s:.1f} s")


class Run:
    """The services, the monitor and the attacker session of one probe, and what they saw."""

    def __init__(self, probe: Probe, run_s: float, out_dir: Path,
                 startup_s: float = STARTUP_S) -> None:
        from simulation.live import LiveSimSpec, LiveSimulation
        from simulation.scenario import load_scenario

        self.probe = probe
        self.run_s = run_s
        scale = run_s / probe.run_s
        self.fault = (probe.fault[0] * scale, probe.fault[1] * scale)
        scenario = load_scenario()
        self.spec = LiveSimSpec(trajectory=TRAJECTORY, seed=0,
                                epoch_ns=time.time_ns() + round(startup_s * NS),
                                stop_s=STOP_S, max_speed_mps=MAX_SPEED_MPS)
        self.live = LiveSimulation(self.spec, scenario)
        self.site = scenario.site.name
        self.robot_id = self.live.robot_id
        self.cameras = sorted(scenario.site.cameras)
        self.endpoint = f"tcp/127.0.0.1:{_free_port()}"
        args = argparse.Namespace(no_feedback=False, kidnapped=probe.kidnapped, processes=True,
                                  detections="noise", no_clouds=True)
        agents = [c for c in self.cameras if c not in probe.skip_agents]
        services = Services(args, self.spec, Path(scenario.site.source_path), self.endpoint,
                            "none", agents)
        self.log_dir = out_dir / probe.key
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.stack = Stack(dict(services.commands()), self.log_dir)
        self.monitor: TimedMonitor | None = None
        self.attacker: Any = None
        self.stop = threading.Event()
        #: what the injector measured or did (figures by name)
        self.notes: dict[str, Any] = {}
        self.rss_fault_start_mib = math.nan
        self.rss_end_mib = math.nan
        self.rss_peak_mib = math.nan
        self.exit_codes: dict[str, int] = {}
        self.died: list[str] = []
        self.injector_error = ""

    # -- clocks --------------------------------------------------------------------------

    def sim_t(self, wall_ns: int | None = None) -> float:
        """Simulated seconds at ``wall_ns`` (default: now)."""
        return ((time.time_ns() if wall_ns is None else wall_ns) - self.spec.epoch_ns) / NS

    def wall_ns(self, sim_s: float) -> int:
        return self.spec.epoch_ns + round(sim_s * NS)

    def sleep_until(self, sim_s: float) -> bool:
        """Sleep until simulated time ``sim_s``; ``False`` when the run is being stopped."""
        while not self.stop.is_set():
            left = sim_s - self.sim_t()
            if left <= 0:
                return True
            self.stop.wait(min(left, 0.2))
        return False

    @property
    def in_fault(self) -> bool:
        return self.fault[0] <= self.sim_t() < self.fault[1]

    # -- what the monitor saw ------------------------------------------------------------

    @property
    def seen(self) -> Any:
        assert self.monitor is not None
        return self.monitor.seen

    def latest_localization(self) -> np.ndarray | None:
        locs = self.seen.localization
        return np.array([locs[-1].x, locs[-1].y, locs[-1].theta]) if locs else None

    def camera(self, t0: float, t1: float) -> CameraFigures:
        est = [e for e in self.seen.camera
               if "multi_frame" not in e.flags and t0 <= self.sim_t(e.stamp_ns) < t1]
        err = self._errors(est)
        stamps = sorted([self.wall_ns(t0)] + [e.stamp_ns for e in est] + [self.wall_ns(t1)])
        gap = float(np.max(np.diff(stamps))) / NS
        if not est:
            return CameraFigures(0, 0.0, math.nan, math.nan, math.nan, gap)
        return CameraFigures(len(est), len(est) / max(t1 - t0, 1e-9),
                             100 * float(np.sqrt(np.mean(err**2))), 100 * float(np.mean(err)),
                             100 * float(np.mean(err > 1.0)), gap)

    def fused(self, t0: float, t1: float) -> tuple[int, float, float]:
        """(count, RMS cm, max cm) of the fused poses stamped in [t0, t1)."""
        est = [e for e in self.seen.fused if t0 <= self.sim_t(e.stamp_ns) < t1]
        err = self._errors(est)
        if not est:
            return 0, math.nan, math.nan
        return len(est), 100 * float(np.sqrt(np.mean(err**2))), 100 * float(np.max(err))

    def localization_error(self, t0: float, t1: float) -> np.ndarray:
        """The robot's own localization errors (m) stamped in [t0, t1)."""
        return self._errors([e for e in self.seen.localization
                             if t0 <= self.sim_t(e.stamp_ns) < t1])

    def localization_error_at(self, t: float) -> float:
        """The robot's own localization error (m) of the last report stamped before ``t``."""
        err = self.localization_error(-math.inf, t)
        return float(err[-1]) if err.size else math.nan

    def corrections(self, t0: float, t1: float) -> list[tuple[float, str, float]]:
        """(sim s, kind, distance from the truth m) of the corrections stamped in [t0, t1)."""
        out = []
        for c in self.seen.corrections:
            t = self.sim_t(c.stamp_ns)
            if t0 <= t < t1:
                truth = self.live.ground_truth(c.stamp_ns)
                out.append((t, c.kind, math.hypot(c.x - truth[0], c.y - truth[1])))
        return out

    def statuses(self, name: str, t0: float = -math.inf,
                 t1: float = math.inf) -> list[ServiceStatus]:
        assert self.monitor is not None
        return [s for at, s in self.monitor.statuses.get(name, []) if t0 <= self.sim_t(at) < t1]

    def counters(self, name: str, at: float = math.inf) -> dict[str, int]:
        """The counters of ``name``'s last status that arrived before sim time ``at``."""
        got = self.statuses(name, -math.inf, at)
        return dict(got[-1].counters) if got else {}

    def delta(self, name: str, counter: str, t0: float, t1: float = math.inf) -> int:
        return self.counters(name, t1).get(counter, 0) - self.counters(name, t0).get(counter, 0)

    def status_gap_s(self, name: str, t0: float, t1: float) -> float:
        assert self.monitor is not None
        at = [a for a, _ in self.monitor.statuses.get(name, []) if t0 <= self.sim_t(a) < t1]
        return float(np.max(np.diff([self.wall_ns(t0), *at, self.wall_ns(t1)]))) / NS

    def degraded(self, name: str, t0: float, t1: float) -> list[str]:
        """The distinct reasons (the parts of the status detail before ``|``) of ``name``'s
        degraded statuses in [t0, t1), in order of appearance; reasons that differ only in
        their numbers count once (the first is kept)."""
        out: list[str] = []
        shapes: set[str] = set()
        for s in self.statuses(name, t0, t1):
            if s.state != "degraded":
                continue
            for reason in s.detail.split(" | ")[0].split("; "):
                shape = re.sub(r"[-+]?\d+(\.\d+)?", "#", reason)
                if shape not in shapes:
                    shapes.add(shape)
                    out.append(reason)
        return out

    def _errors(self, estimates: Sequence[PoseEstimate]) -> np.ndarray:
        if not estimates:
            return np.zeros(0)
        est = np.array([[e.x, e.y] for e in estimates])
        truth = np.array([self.live.ground_truth(e.stamp_ns)[:2] for e in estimates])
        return np.asarray(np.hypot(*(est - truth).T))

    # -- running it ------------------------------------------------------------------------

    def execute(self, progress_s: float = 10.0) -> None:
        import zenoh

        probe = self.probe
        print(f"[{probe.key}] {probe.title}: services starting ({', '.join(self.stack.commands)})"
              f"; fault at t = {self.fault[0]:.0f}..{self.fault[1]:.0f} s of {self.run_s:.0f} s",
              flush=True)
        self.monitor = TimedMonitor(self.site, self.robot_id, self.endpoint)
        self.attacker = zenoh.open(loopback_config(listen=["tcp/127.0.0.1:0"],
                                                   connect=[self.endpoint]))
        self.stack.start()
        injector = threading.Thread(target=self._inject, name=f"probe-{probe.key}", daemon=True)
        sampler: RssSampler | None = None
        try:
            injector.start()
            next_progress = progress_s
            while self.sim_t() < self.run_s:
                time.sleep(0.1)
                self.monitor.drain()
                t = self.sim_t()
                if sampler is None and t >= self.fault[0]:
                    self.rss_fault_start_mib = self._rss()
                    sampler = RssSampler(self.stack.pid("backend")).__enter__()
                dead = [n for n in self.stack.unexpected_exits() if n not in self.died]
                for n in dead:
                    print(f"[{probe.key}] {n} exited unexpectedly (see {self.log_dir})",
                          flush=True)
                self.died += dead
                if t >= next_progress:
                    next_progress += progress_s
                    self._progress(t)
            self.rss_end_mib = self._rss()
        finally:
            self.stop.set()
            injector.join(30)
            if sampler is not None:
                sampler.__exit__()
                self.rss_peak_mib = sampler.peak_mib
            self.exit_codes = self.stack.stop()
            self.monitor.drain()
            self.monitor.close()
            self.attacker.close()

    def _rss(self) -> float:
        try:
            return rss_mib(self.stack.pid("backend"))
        except (OSError, RuntimeError):
            return math.nan

    def _inject(self) -> None:
        try:
            self.probe.inject(self)
        except Exception as exc:  # the run goes on; the row says the injection failed
            self.injector_error = f"{type(exc).__name__}: {exc}"
            print(f"[{self.probe.key}] injection failed: {self.injector_error}", flush=True)

    def _progress(self, t: float) -> None:
        backend = self.seen.status.get("backend/main")
        state = backend.state if backend else "-"
        truth = self.live.ground_truth(time.time_ns())
        loc = self.latest_localization()
        loc_err = f"{100 * math.hypot(*(loc[:2] - truth[:2])):.0f} cm" if loc is not None else "-"
        print(f"[{self.probe.key}] t={t:5.1f}/{self.run_s:.0f} s  camera poses "
              f"{len(self.seen.camera)}, fused {len(self.seen.fused)}, corrections "
              f"{len(self.seen.corrections)}, robot's localization error {loc_err}, backend "
              f"{state}, RSS {self._rss():.0f} MiB{' (fault on)' if self.in_fault else ''}",
              flush=True)

    @property
    def crashes(self) -> list[str]:
        """Services that exited on their own, or with a non-zero code when stopped."""
        killed = {id(p) for p in self.stack.killed}
        bad = [n for n, c in self.exit_codes.items()
               if c != 0 and id(self.stack.procs[n]) not in killed]
        return sorted(set(bad) | set(self.died))


# ------------------------------------------------------------------------------------------
# Probes
# ------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Verdict:
    """A probe's figures (phrases), whether it passed and against what."""

    figures: list[str]
    ok: bool
    criterion: str


@dataclasses.dataclass(frozen=True)
class Probe:
    """One fault: when it is on (simulated seconds of the ``run_s`` observed), how to inject
    it (``inject(run)``, in a thread; returns when done or ``run.stop`` is set) and how to
    judge it (``judge(run, reference)``; ``reference`` is the baseline run, or ``None``)."""

    key: str
    title: str
    before: str
    run_s: float
    fault: tuple[float, float]
    inject: Callable[[Run], None]
    judge: Callable[[Run, Run | None], Verdict]
    kidnapped: bool = False
    skip_agents: tuple[str, ...] = ()


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
            est = PoseEstimate(run.robot_id, now + round(ahead_s * NS), FAKE_SEQ0 + i,
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


# -- baseline ------------------------------------------------------------------------------


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
    return Verdict(figures, ok, "reference: fused < 10 cm RMS, localization < 20 cm at the end, "
                   "backend 'ok' in >= 90 % of its statuses")


# -- (a) fake fused pose, (a2) the same stamped now, (b) zero covariance, (c) sub-limit jumps


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
            crit = (f"every fake refused and counted, the robot's localization never > "
                    f"{100 * bound_m:.0f} cm off")
        else:
            ok = worst < bound_m and refused >= 1 and not run.crashes
            crit = (f"refusal counted (`{expect_refused}`), the robot's localization never "
                    f"> {100 * bound_m:.0f} cm off")
        return Verdict(figures, ok, crit)

    return judge


# -- (d) kidnapped, first fake 30 m away ----------------------------------------------------


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
    return Verdict(figures, ok, "the fake refused (`skip_outside_floor_area`), the robot "
                   "initialized from the genuine estimates within 30 cm")


# -- (e) odometry stamped 2**63-1, then odometry with a wrong pose ------------------------


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
    return Verdict(figures, ok, "far-future stamp counted and named in the status; fused poses "
                   "keep coming (>= 80 % of the baseline rate) and < 10 cm RMS 5 s after the "
                   "wrong odometry stops; no camera pose > 1 m off")


# -- (f) one camera 0.5 s ahead ---------------------------------------------------------


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
                    msg = dataclasses.replace(msg, stamp_ns=msg.stamp_ns + round(AHEAD_S * NS))
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
    return Verdict(figures, ok, f"{AHEAD_CAMERA}'s frames counted as future, <= 2 % of the "
                   "others' frames late, camera pose rate >= 80 % of without, no gap >= 3 s, "
                   "status degraded naming the camera")


# -- (g) rogue 1000 Hz source -----------------------------------------------------------


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
    return Verdict(figures, ok, "rogue frames cut and counted, status names the camera as rogue, "
                   "camera pose rate >= 80 % and RMS within 2 cm of without, status every "
                   f"< {MAX_STATUS_GAP_S:.0f} s")


# -- (h), (i) oversized bursts --------------------------------------------------------------


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
    return Verdict(figures, ok, "every message refused or dropped and counted, status and "
                   f"camera poses without a gap >= {MAX_STATUS_GAP_S:.0f} s, RSS back within "
                   f"{RSS_TOLERANCE_MIB:.0f} MiB")


# -- (j) backend killed and restarted -------------------------------------------------------


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
        return (later[0] - restarted) / NS if restarted and later else math.nan

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
    return Verdict(figures, ok, "odometry of the outage replayed, none lost; poses within 15 s "
                   "of the restart; bridge degraded while away, ok after; fused < 10 cm")


# -- the list --------------------------------------------------------------------------------

FAKE_COV: Final = 1e-4 * np.eye(3)

PROBES: Final[dict[str, Probe]] = {p.key: p for p in [
    Probe("baseline", "no fault (reference)", "-", 76.0, (5.0, 76.0), _no_fault,
          _judge_baseline),
    Probe("a", "fake fused pose (covariance 1e-4·I, stamp now+0.3 s, 0.95 m off) at 50 Hz "
          "from a non-backend peer",
          "a 0.95 m correction at each of 6 stops: localization error ~5 cm → 3.94 m; all "
          "2,849 genuine estimates discarded as late", 45.0, (2.0, 40.0),
          _fake_estimates((0.95, 0.0), covariance=FAKE_COV, ahead_s=0.3),
          _judge_fake("future_stamp_estimate")),
    Probe("a2", "probe (a) stamped now instead of now+0.3 s (what is left to the bridge "
          "without the router's ACL)", "(not probed)", 45.0, (2.0, 40.0),
          _fake_estimates((0.95, 0.0), covariance=FAKE_COV),
          _judge_fake("skip_jump_too_large", bound_m=1.2)),
    Probe("b", "zero-covariance fused estimate 1.5 m off, stamp now, 50 Hz",
          "gated on the sender's own covariance (policy.py:203)", 40.0, (2.0, 35.0),
          _fake_estimates((1.5, 0.0), covariance=np.zeros((3, 3))),
          _judge_fake("skip_jump_too_large")),
    Probe("c", "repeated sub-limit jumps: fused estimate 0.6 m off the current localization, "
          "stamp now, 50 Hz through 3 stops",
          "jump limit relative to a localization the attacker already moved: no bound on "
          "accumulation", 76.0, (2.0, 58.0),
          _fake_estimates((0.6, 0.0), covariance=FAKE_COV),
          _judge_fake("skip_jump_too_large", bound_m=0.75)),
    Probe("d", "--kidnapped, the first poses a fake 30 m away (outside the room)",
          "the fake accepted as the initialization; the 1 m jump limit then rejected the "
          "genuine estimates", 25.0, (-3.0, 3.0),
          _fake_estimates((30.0, 0.0), covariance=FAKE_COV), _judge_kidnapped, kidnapped=True),
    Probe("e", "one odometry stamped 2^63-1 on .../odom, then 200 valid odometry 1.1 m off",
          "fusion stopped for good, status 'ok'; 16 % of camera poses > 1 m off (up to "
          "1.77 km); ~219 wrong odometry → 295 graph restarts, fused error up to 1.3 m",
          40.0, (10.0, 20.0), _inject_odometry, _judge_odometry),
    Probe("f", f"one camera ({AHEAD_CAMERA}) 0.5 s ahead",
          "pose rate 15.4 → 6.9 Hz; 1,008 other cameras' frames late in 23 s; 12.4 s "
          "without a camera pose; camera error 3.9 → 19.2 cm; a correction with 15 cm error",
          40.0, (15.0, 40.0), _inject_camera_ahead, _judge_camera_ahead,
          skip_agents=(AHEAD_CAMERA,)),
    Probe("g", f"rogue 1000 Hz detection source for {ROGUE_CAMERA}", "not flagged", 35.0,
          (10.0, 30.0), _inject_rogue, _judge_rogue),
    Probe("h", "100 detection messages of 1.5 MB (nested detections)",
          "worker pinned ~30 s, poses up to 28.9 s stale, a correction missed, RSS 146 → "
          "322 MiB, not released", 25.0, (10.0, 25.0), _oversized("nested"),
          _judge_oversized),
    Probe("i", "20 valid detection messages padded to 50 MB (unknown key)",
          "accepted; backend at 1.53 GiB", 30.0, (10.0, 30.0), _oversized("padded"),
          _judge_oversized),
    Probe("j", "backend SIGKILLed and restarted 10 s later",
          "~148 odometry messages lost during the restart", 50.0, (15.0, 25.0),
          _inject_restart, _judge_restart),
]}


# ------------------------------------------------------------------------------------------
# CLI
# ------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Row:
    """One table row."""

    probe: Probe
    verdict: Verdict

    def markdown(self) -> str:
        p, v = self.probe, self.verdict
        return (f"| ({p.key}) {p.title} | {p.before} | {'; '.join(v.figures)} | "
                f"{'pass' if v.ok else 'FAIL'}: {v.criterion} |")


def run_probes(keys_: Sequence[str], seconds: float | None, out_dir: Path,
               progress_s: float = 10.0, startup_s: float = STARTUP_S) -> list[Row]:
    """Run the probes named ``keys_`` (the baseline first when named) and judge them;
    ``seconds``: simulated seconds observed per probe (default: each probe's own);
    ``startup_s``: between starting the services and the simulation's t = 0."""
    rows: list[Row] = []
    reference: Run | None = None
    order = sorted(keys_, key=lambda k: list(PROBES).index(k))
    for key in order:
        probe = PROBES[key]
        run = Run(probe, seconds or probe.run_s, out_dir, startup_s)
        run.execute(progress_s)
        try:
            verdict = probe.judge(run, reference if key != "baseline" else None)
        except Exception as exc:  # a judging bug must not lose the other rows
            verdict = Verdict([f"judging failed: {type(exc).__name__}: {exc}"], False, "-")
        if key == "baseline":
            reference = run
        row = Row(probe, verdict)
        rows.append(row)
        print(f"[{key}] {'pass' if verdict.ok else 'FAIL'}: {'; '.join(verdict.figures)}",
              flush=True)
    return rows


def _code_version() -> str:
    """The git commit of the code under test, ``+changes`` when tracked files differ from it
    (``unknown`` outside a git checkout)."""
    root = Path(__file__).resolve().parents[1]
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, check=True,
                             capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, check=True, capture_output=True, text=True,
                               timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return sha + ("+changes" if dirty else "")


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench reliability", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--probes", default=",".join(PROBES),
                        help=f"comma-separated probes (default: all: {','.join(PROBES)})")
    parser.add_argument("--seconds", type=float,
                        help="observe each probe for this many seconds of simulated time (the "
                        "fault window scaled to it; default: each probe's own, 25-76 s)")
    parser.add_argument("--out", default="runs/reliability", help="folder for the service logs")
    parser.add_argument("--progress-s", type=float, default=10.0, help="progress line period")
    parser.add_argument("--startup-s", type=float, default=STARTUP_S,
                        help="seconds between starting the services and the simulation's t = 0 "
                        f"(default {STARTUP_S:g})")
    args = parser.parse_args(list(argv))
    chosen = [k.strip() for k in args.probes.split(",") if k.strip()]
    unknown = [k for k in chosen if k not in PROBES]
    if unknown or not chosen:
        parser.error(f"unknown probe(s) {unknown}; choose from {','.join(PROBES)}")
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    print(f"smartedge bench reliability: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}, load {load:.1f}, code {_code_version()}, "
          f"{time.strftime('%Y-%m-%d %H:%M %Z')}; services as processes on Zenoh "
          f"loopback (no TLS, no router ACL), {TRAJECTORY}, detection noise model; logs in "
          f"{out_dir}", flush=True)
    t0 = time.monotonic()
    rows = run_probes(chosen, args.seconds, out_dir, args.progress_s, args.startup_s)
    print(f"\n{len(rows)} probes in {time.monotonic() - t0:.0f} s\n")
    print("| probe | before (issue 17) | now | verdict |")
    print("|---|---|---|---|")
    for row in rows:
        print(row.markdown())
    return 0 if all(r.verdict.ok for r in rows) else 1


__all__ = [
    "PROBES",
    "Probe",
    "Row",
    "RssSampler",
    "Run",
    "TimedMonitor",
    "Verdict",
    "hostile_payloads",
    "main",
    "rss_mib",
    "run_probes",
]
