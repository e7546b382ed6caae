"""Bump detection on the simulated paper lab: how soon a moved camera is named, how often an
unmoved one is (``smartedge bench camera-health``).

Runs of the scenario's trajectories are driven back to back through one
:class:`~backend_service.pipeline.BackendPipeline` (noise-model detections, simulated time,
every stamp of a run shifted to follow the previous one, as one long session), optionally with a
camera bumped (:class:`simulation.detections.CameraBump`) at a given time. Figures:

- **false alarms per hour**: cameras named moved in runs without a bump (with ``action:
  report`` so that one alarm does not change what follows), and the largest test statistic an
  unmoved camera reached against the alarm threshold;
- **detection delay**: seconds of *robot visibility* of the bumped camera (frame-sets in which
  it saw the robot) between the bump and its naming, and the simulated seconds;
- **CPU** of the monitor per frame-set (thread CPU time of
  :meth:`~backend_service.camera_health.CameraHealthMonitor.observe` over all frame-sets).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Iterator, Sequence
from typing import Final

import numpy as np

from backend_service.camera_health import CameraHealthConfig
from backend_service.pipeline import BackendPipeline
from backend_service.pipeline_config import PipelineConfig
from protocol.messages import Message, Odometry, PoseEstimate, RobotDetections
from simulation.detections import CameraBump, DetectionSimulator
from simulation.runner import SimulationRun, TimedMessage
from simulation.scenario import Scenario, Seeds, load_scenario

#: the trajectories a long session cycles through (each forward and reversed)
TRAJECTORIES: Final = ("traj1", "traj2", "traj3")
#: the robot bridge's localization rate (``robot_bridge.service.LOCALIZATION_PERIOD_NS``)
LOCALIZATION_RATE_HZ: Final = 10.0


@dataclasses.dataclass(frozen=True)
class BumpSpec:
    """A bump ``at_s`` seconds into the session: ``camera_id`` moved by ``translation_m`` and
    rotated by ``rotation_deg`` (world axes; :class:`CameraBump`)."""

    camera_id: str
    at_s: float
    translation_m: tuple[float, float, float]
    rotation_deg: tuple[float, float, float]


@dataclasses.dataclass
class SessionResult:
    """What one session showed: ``duration_s`` simulated; ``alarms`` (camera, session time s)
    of every naming; ``max_chi2`` per camera over the session (of the unbumped cameras for a
    bump session: before the naming); ``visible_s`` per camera (frame-sets with it, s);
    ``detected_after_s`` / ``detected_after_visible_s``: the bump's naming after the bump in
    simulated seconds / seconds of the bumped camera's robot visibility (``None``: not named);
    ``detected_after_judgeable_s``: seconds of that visibility with enough other cameras
    (``min_other_cameras``) in the frame-set for it to be judged;
    ``estimate``: the named offset (cm, deg); ``final`` per camera: (chi2, offset cm, deg) at
    the end; ``monitor_cpu_s``, ``frame_sets``."""

    duration_s: float = 0.0
    alarms: list[tuple[str, float]] = dataclasses.field(default_factory=list)
    max_chi2: dict[str, float] = dataclasses.field(default_factory=dict)
    visible_s: dict[str, float] = dataclasses.field(default_factory=dict)
    detected_after_s: float | None = None
    detected_after_visible_s: float | None = None
    detected_after_judgeable_s: float | None = None
    estimate: tuple[float, float] | None = None
    final: dict[str, tuple[float, float, float]] = dataclasses.field(default_factory=dict)
    monitor_cpu_s: float = 0.0
    frame_sets: int = 0


def _shifted(msg: Message, offset_ns: int) -> Message:
    if offset_ns and isinstance(msg, (RobotDetections, Odometry, PoseEstimate)):
        return dataclasses.replace(msg, stamp_ns=msg.stamp_ns + offset_ns)
    return msg


def session_messages(scenario: Scenario, duration_s: float, seed: int,
                     bump: BumpSpec | None = None) -> Iterator[tuple[float, TimedMessage]]:
    """(session time s, message) of runs of :data:`TRAJECTORIES` back to back until
    ``duration_s``, stamps shifted to one continuous clock; the bump applies from ``at_s`` on
    (every later run starts with the camera already moved)."""
    offset_ns = 0
    k = 0
    while offset_ns * 1e-9 < duration_s:
        traj = TRAJECTORIES[(k // 2) % len(TRAJECTORIES)]
        reverse = bool(k % 2)
        bumps: list[CameraBump] = []
        if bump is not None:
            at_ns = scenario.start_stamp_ns + round(bump.at_s * 1e9) - offset_ns
            bumps.append(CameraBump(bump.camera_id, max(at_ns, 0), bump.translation_m,
                                    bump.rotation_deg))
        detector = DetectionSimulator(scenario, bumps=bumps)
        run = SimulationRun(scenario, traj, reverse, seed=np.random.SeedSequence([seed, k]),
                            detector=detector)
        end_ns = offset_ns
        for tm in run.messages(localization_rate_hz=LOCALIZATION_RATE_HZ):
            arrival = tm.arrival_ns + offset_ns
            t_s = (arrival - scenario.start_stamp_ns) * 1e-9
            if t_s > duration_s:
                return
            end_ns = max(end_ns, tm.arrival_ns - scenario.start_stamp_ns + offset_ns)
            yield t_s, TimedMessage(arrival, _shifted(tm.message, offset_ns))
        offset_ns = end_ns + 1_000_000_000  # a second between runs
        k += 1


def run_session(scenario: Scenario, duration_s: float, seed: int,
                health: CameraHealthConfig, bump: BumpSpec | None = None,
                progress: bool = False) -> SessionResult:
    """One session through the pipeline (camera estimates only: the pose graph does not
    change what the monitor sees); see :class:`SessionResult`."""
    config = dataclasses.replace(PipelineConfig.from_site(scenario.site), camera_health=health)
    pipeline = BackendPipeline(scenario.site, config, with_fusion=False)
    monitor = pipeline.camera_health
    result = SessionResult()
    cpu = 0.0
    observe = monitor.observe

    def timed_observe(*args: object, **kwargs: object) -> object:
        nonlocal cpu
        t0 = time.thread_time()
        try:
            return observe(*args, **kwargs)  # type: ignore[arg-type]
        finally:
            cpu += time.thread_time() - t0

    monitor.observe = timed_observe  # type: ignore[method-assign,assignment]
    named: set[str] = set()
    visible_after_bump = 0.0
    judgeable_after_bump = 0.0
    period_s = 1.0 / scenario.cameras.rate_hz
    next_report = 600.0
    t_s = 0.0
    for t_s, tm in session_messages(scenario, duration_s, seed, bump):
        out = pipeline.step(tm.message, tm.arrival_ns)
        for rec in out.solves:
            result.frame_sets += 1
            stamp_s = (rec.frame_set.stamp_ns - scenario.start_stamp_ns) * 1e-9
            for cid in rec.frame_set.camera_ids:
                result.visible_s[cid] = result.visible_s.get(cid, 0.0) + period_s
                if bump is not None and cid == bump.camera_id and stamp_s >= bump.at_s \
                        and result.detected_after_s is None:
                    visible_after_bump += period_s
                    if len(rec.frame_set.camera_ids) > health.min_other_cameras:
                        judgeable_after_bump += period_s
        for cid in sorted(scenario.site.cameras):
            st = monitor.state(cid)
            if st is None:
                continue
            if st.moved is not None and cid not in named:
                named.add(cid)
                result.alarms.append((cid, t_s))
                if bump is not None and cid == bump.camera_id and t_s >= bump.at_s:
                    result.detected_after_s = t_s - bump.at_s
                    result.detected_after_visible_s = visible_after_bump
                    result.detected_after_judgeable_s = judgeable_after_bump
                    result.estimate = (st.moved.translation_m * 100, st.moved.rotation_deg)
            elif st.moved is None:
                named.discard(cid)
            result.final[cid] = (st.chi2, st.translation_m * 100, st.rotation_deg)
            unmoved = bump is None or cid != bump.camera_id or t_s < bump.at_s
            if unmoved and st.evidence_s >= health.min_evidence_s and (
                    bump is None or result.detected_after_s is None):
                result.max_chi2[cid] = max(result.max_chi2.get(cid, 0.0), st.chi2)
        if progress and t_s >= next_report:
            print(f"  ... {t_s / 60:.0f} min simulated", file=sys.stderr, flush=True)
            next_report += 600.0
    result.duration_s = t_s
    result.monitor_cpu_s = cpu
    return result


def with_calibration_seed(scenario: Scenario, seed: int) -> Scenario:
    """The scenario with another draw of the cameras' calibration error."""
    return scenario.with_overrides(seeds=Seeds(calibration=seed, run=scenario.seeds.run))


def random_bump(rng: np.random.Generator, camera_id: str, at_s: float, translation_m: float,
                rotation_deg: float) -> BumpSpec:
    """A bump of the given size in a random direction (translation and rotation axis)."""
    def unit() -> np.ndarray:
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)

    t = tuple(float(v) for v in translation_m * unit())
    r = tuple(float(v) for v in rotation_deg * unit())
    return BumpSpec(camera_id, at_s, t, r)  # type: ignore[arg-type]


def pipeline_cpu_ms(n_cameras: int, frames: int, enabled: bool, rate_hz: float = 15.0,
                    warmup: int = 10) -> float:
    """Thread CPU (ms) per frame-set of the whole in-process pipeline (fusion included) on the
    ring site of :mod:`simulation.camera_ring` (every camera sees the robot), with the camera
    health monitor on or off; the first ``warmup`` frame-sets are not counted."""
    import tempfile
    from pathlib import Path

    import protocol
    from simulation.camera_ring import detection_payloads, robot_pose, write_ring_site

    with tempfile.TemporaryDirectory(prefix="smartedge-health-") as tmp:
        site = write_ring_site(Path(tmp) / "ring.yaml", n_cameras)
    rng = np.random.default_rng(0)
    period_ns = round(1e9 / rate_hz)
    start_ns = 1_000_000_000
    frames_msgs: list[list[protocol.Message]] = [[protocol.decode(p) for _, p in detection_payloads(
        site, robot_pose(k / rate_hz), start_ns + k * period_ns, k, rng)]
        for k in range(warmup + frames)]
    config = PipelineConfig.from_site(site)
    config = dataclasses.replace(config, camera_health=dataclasses.replace(
        config.camera_health, enabled=enabled))
    pipe = BackendPipeline(site, config)
    cpu = 0.0
    solved = 0
    for k, msgs in enumerate(frames_msgs):
        arrival_ns = start_ns + k * period_ns + 2_000_000
        t0 = time.thread_time()
        for msg in msgs:
            out = pipe.poll(arrival_ns)
            out += pipe.feed(msg, arrival_ns)
            if k >= warmup:
                solved += len(out.solves)
        if k >= warmup:
            cpu += time.thread_time() - t0
    return cpu / max(solved, 1) * 1e3


def print_cpu(camera_counts: Sequence[int], frames: int) -> None:
    """The pipeline's CPU per frame-set with and without the monitor (alternating runs)."""
    print(f"pipeline CPU per frame-set, ring site, {frames} frame-sets at 15 Hz, camera health "
          "off / on (two alternating runs each)")
    for n in camera_counts:
        pipeline_cpu_ms(n, 5, True)  # warm-up: CasADi builds its functions for this size
        off = [pipeline_cpu_ms(n, frames, False) for _ in range(2)]
        on = [pipeline_cpu_ms(n, frames, True) for _ in range(2)]
        off_ms, on_ms = min(off), min(on)
        print(f"{n:>4} cameras: off {off_ms:.3f} ms, on {on_ms:.3f} ms, ratio "
              f"{on_ms / off_ms:.3f}", flush=True)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench camera-health",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hours", type=float, default=1.0,
                        help="simulated hours without a bump per calibration seed (default 1)")
    parser.add_argument("--calibration-seeds", type=int, nargs="+", default=[7],
                        help="draws of the cameras' calibration error (default: the site's, 7)")
    parser.add_argument("--bumps", type=int, default=4,
                        help="bump sessions per size and calibration seed (default 4)")
    parser.add_argument("--sizes", default="0.05:1.0,0.02:0.5",
                        help="bump sizes, metres:degrees, comma-separated")
    parser.add_argument("--bump-at-s", type=float, default=200.0)
    parser.add_argument("--bump-session-s", type=float, default=600.0)
    parser.add_argument("--cpu", type=int, nargs="*", metavar="CAMERAS",
                        help="only the CPU cost: the pipeline with the monitor on and off on the "
                        "ring site with these camera counts (e.g. 4 16 64)")
    parser.add_argument("--cpu-frames", type=int, default=300)
    parser.add_argument("--detections", choices=("noise", "cnn"), default="noise",
                        help="cnn: runs rendered through the shipped ONNX models, the monitor "
                        "as the site sets it against counting every frame "
                        "(lab.bench.camera_health_cnn)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1],
                        help="--detections cnn: run seeds (default 0 1)")
    parser.add_argument("--trajectories", nargs="+", default=list(TRAJECTORIES),
                        help="--detections cnn: trajectories, each forward and reversed")
    parser.add_argument("--bump-cameras", nargs="+", default=["cam1", "cam3"],
                        help="--detections cnn: cameras given a calibration off by 5 cm / 1 "
                        "deg, one at a time (default cam1 cam3)")
    args = parser.parse_args(argv)
    if args.detections == "cnn":
        from lab.bench.camera_health_cnn import run as run_cnn

        run_cnn(args.seeds, args.trajectories, args.bump_cameras)
        return 0
    if args.cpu:
        print_cpu(args.cpu, args.cpu_frames)
        return 0
    base = load_scenario()
    site = base.site
    health = CameraHealthConfig.from_site(site)
    report = dataclasses.replace(health, action="report")
    cams = sorted(site.cameras)
    sizes = [tuple(float(x) for x in s.split(":")) for s in args.sizes.split(",") if s]
    for cal in args.calibration_seeds:
        scenario = with_calibration_seed(base, cal)
        if args.hours > 0:
            t0 = time.perf_counter()
            res = run_session(scenario, args.hours * 3600.0, seed=1000 + cal, health=report,
                              progress=True)
            worst = max(res.max_chi2.items(), key=lambda kv: kv[1], default=("-", 0.0))
            per_fs_us = res.monitor_cpu_s / max(res.frame_sets, 1) * 1e6
            print(f"calibration seed {cal}: {res.duration_s / 3600:.2f} h, "
                  f"{len(res.alarms)} false alarms {res.alarms}, largest chi2 of an unmoved "
                  f"camera {worst[1]:.1f} ({worst[0]}; alarm at {health.alarm_chi2}), "
                  f"monitor {per_fs_us:.0f} us CPU per frame-set over {res.frame_sets} "
                  f"frame-sets ({time.perf_counter() - t0:.0f} s wall)", flush=True)
        for size_m, size_deg in sizes:
            rng = np.random.default_rng([cal, round(size_m * 1000), round(size_deg * 100)])
            delays = []
            for i in range(args.bumps):
                bump = random_bump(rng, cams[i % len(cams)], args.bump_at_s, size_m, size_deg)
                res = run_session(scenario, args.bump_session_s, seed=2000 + 17 * cal + i,
                                  health=health, bump=bump)
                wrong = [a for a in res.alarms if a[0] != bump.camera_id]
                est = "" if res.estimate is None else \
                    f" (named ~{res.estimate[0]:.0f} cm / {res.estimate[1]:.1f} deg)"
                seen = "not named" if res.detected_after_visible_s is None else \
                    (f"named after {res.detected_after_visible_s:.1f} s of visibility, "
                     f"{res.detected_after_judgeable_s:.1f} s with another camera "
                     f"({res.detected_after_s:.0f} s after the bump){est}")
                print(f"calibration seed {cal}: bump {size_m * 100:.0f} cm / {size_deg} deg of "
                      f"{bump.camera_id}: {seen}; other cameras named: {wrong or 'none'}",
                      flush=True)
                delays.append(res.detected_after_visible_s)
            found = [d for d in delays if d is not None]
            summary = (f"max {max(found):.1f} s, mean {sum(found) / len(found):.1f} s"
                       if found else "-")
            print(f"calibration seed {cal}: {size_m * 100:.0f} cm / {size_deg} deg: "
                  f"{len(found)}/{len(delays)} named, visibility before naming: {summary}",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["BumpSpec", "SessionResult", "main", "random_bump", "run_session",
           "session_messages", "with_calibration_seed"]
