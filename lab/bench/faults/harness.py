"""The fault harness: the running services as OS processes, an attacker session, and what a
monitor saw, for one probe at a time.

:class:`Run` starts the services the way ``smartedge demo --processes`` does (backend, four
simulated edge agents with the detection noise model, the robot bridge on the simulated HSR; no
viewer, no clouds) on Zenoh loopback, drives the paper site's :data:`TRAJECTORY`, runs the
probe's injector in a thread with its own *attacker* Zenoh session, and answers the judges'
questions (camera and fused pose figures against the simulator's ground truth, the services'
counters and statuses by simulated time, the backend's RSS, crashes). :class:`Probe` and
:class:`Verdict` are what :mod:`lab.bench.faults.probes` defines and returns.

Time: ``sim_t`` is simulated seconds since the trajectory's t = 0 (a wall-clock epoch shared by
every process of the live simulation); stamps are nanoseconds on the same clock.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import math
import re
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from core.session import loopback_config
from lab.demo import Monitor, Services
from lab.evaluation.scoring import live_truth, pose_errors, rms_m
from lab.launcher import (
    RssSampler,
    ServiceProcess,
    free_port,
    rss_mib,
    start_service,
    stop_services,
)
from protocol import decode
from protocol.errors import DecodeError
from protocol.messages import NS_PER_S, PoseCorrection, PoseEstimate, ServiceStatus

#: seconds between starting the services and the simulation's t = 0
STARTUP_S: Final = 10.0
#: sequence numbers of the attacker's own messages start here (so the monitor can tell them)
FAKE_SEQ0: Final = 1_000_000_000
#: the simulated robot's dwell at each waypoint and top speed (the demo's)
STOP_S: Final = 4.0
MAX_SPEED_MPS: Final = 0.4
TRAJECTORY: Final = "traj3"
#: how long :meth:`Stack.stop` waits for a process after SIGTERM before it SIGKILLs it (s)
STOP_TIMEOUT_S: Final = 20.0


# ------------------------------------------------------------------------------------------
# Observation and processes
# ------------------------------------------------------------------------------------------


class TimedMonitor(Monitor):
    """The demo's :class:`~lab.demo.Monitor` that also keeps every status message with
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
        self.procs: dict[str, ServiceProcess] = {}
        self.killed: list[ServiceProcess] = []
        self._starts: collections.Counter[str] = collections.Counter()

    def start(self, name: str | None = None) -> None:
        for n in [name] if name else list(self.commands):
            suffix = f".{self._starts[n]}" if self._starts[n] else ""
            self._starts[n] += 1
            self.procs[n] = start_service(
                self.commands[n], self.log_dir / f"{n.replace('/', '_')}{suffix}.log", name=n)

    def kill(self, name: str) -> None:
        proc = self.procs[name]
        proc.kill()
        self.killed.append(proc)

    def pid(self, name: str) -> int:
        return self.procs[name].pid

    def unexpected_exits(self) -> list[str]:
        killed = {id(p) for p in self.killed}
        return [n for n, p in self.procs.items() if not p.running() and id(p) not in killed]

    def stop(self) -> dict[str, int]:
        """SIGTERM to every process still running (last started first), SIGKILL after
        :data:`STOP_TIMEOUT_S`; the exit codes by name."""
        return stop_services([self.procs[n] for n in reversed(self.procs)],
                             timeout_s=STOP_TIMEOUT_S)


# ------------------------------------------------------------------------------------------
# What a probe is, what it returns
# ------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Verdict:
    """What a probe's judge found: the figures (phrases) and whether the probe passed."""

    figures: list[str]
    ok: bool


@dataclasses.dataclass(frozen=True)
class Probe:
    """One fault. ``name`` is how ``--probes`` selects it; ``sends`` says what the attacker
    does (or what is done to a process) and ``holds`` what must hold for a pass; ``before`` is
    what the first fault survey measured before the fixes. The fault is on in ``fault``
    (simulated seconds of the ``run_s`` observed); ``inject(run)`` runs it in a thread
    (returns when done or ``run.stop`` is set) and ``judge(run, reference)`` measures it
    (``reference``: the baseline run, or ``None``)."""

    name: str
    sends: str
    holds: str
    before: str
    run_s: float
    fault: tuple[float, float]
    inject: Callable[[Run], None]
    judge: Callable[[Run, Run | None], Verdict]
    kidnapped: bool = False
    skip_agents: tuple[str, ...] = ()

    @property
    def summary(self) -> str:
        """One line: what the probe sends and what must hold."""
        return f"{self.sends}; must hold: {self.holds}"


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
                                epoch_ns=time.time_ns() + round(startup_s * NS_PER_S),
                                stop_s=STOP_S, max_speed_mps=MAX_SPEED_MPS)
        self.live = LiveSimulation(self.spec, scenario)
        self.site = scenario.site.name
        self.robot_id = self.live.robot_id
        self.cameras = sorted(scenario.site.cameras)
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        args = argparse.Namespace(no_feedback=False, kidnapped=probe.kidnapped, processes=True,
                                  detections="noise", no_clouds=True)
        agents = [c for c in self.cameras if c not in probe.skip_agents]
        services = Services(args, self.spec, Path(scenario.site.source_path), self.endpoint,
                            "none", agents)
        self.log_dir = out_dir / probe.name
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
        return ((time.time_ns() if wall_ns is None else wall_ns) - self.spec.epoch_ns) / NS_PER_S

    def wall_ns(self, sim_s: float) -> int:
        return self.spec.epoch_ns + round(sim_s * NS_PER_S)

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
        gap = float(np.max(np.diff(stamps))) / NS_PER_S
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
        return len(est), 100 * rms_m(err), 100 * float(np.max(err))

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
        return float(np.max(np.diff([self.wall_ns(t0), *at, self.wall_ns(t1)]))) / NS_PER_S

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
        """Translation errors (m) against the simulated robot's truth."""
        return pose_errors(estimates, live_truth(self.live))[0]

    # -- running it ------------------------------------------------------------------------

    def execute(self, progress_s: float = 10.0) -> None:
        import zenoh

        probe = self.probe
        print(f"[{probe.name}] {probe.sends}: services starting ({', '.join(self.stack.commands)})"
              f"; fault at t = {self.fault[0]:.0f}..{self.fault[1]:.0f} s of {self.run_s:.0f} s",
              flush=True)
        self.monitor = TimedMonitor(self.site, self.robot_id, self.endpoint)
        self.attacker = zenoh.open(loopback_config(listen=["tcp/127.0.0.1:0"],
                                                   connect=[self.endpoint]))
        self.stack.start()
        injector = threading.Thread(target=self._inject, name=f"probe-{probe.name}", daemon=True)
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
                    print(f"[{probe.name}] {n} exited unexpectedly (see {self.log_dir})",
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
            print(f"[{self.probe.name}] injection failed: {self.injector_error}", flush=True)

    def _progress(self, t: float) -> None:
        backend = self.seen.status.get("backend/main")
        state = backend.state if backend else "-"
        truth = self.live.ground_truth(time.time_ns())
        loc = self.latest_localization()
        loc_err = f"{100 * math.hypot(*(loc[:2] - truth[:2])):.0f} cm" if loc is not None else "-"
        print(f"[{self.probe.name}] t={t:5.1f}/{self.run_s:.0f} s  camera poses "
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


__all__ = [
    "FAKE_SEQ0",
    "STARTUP_S",
    "TRAJECTORY",
    "CameraFigures",
    "Probe",
    "Run",
    "Stack",
    "TimedMonitor",
    "Verdict",
]
