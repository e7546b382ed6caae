"""``smartedge bench backend``: sustained detections throughput of the backend over real Zenoh.

For N cameras (default 4, 16, 64) on a ring around a robot that drives a slow circle, this
process publishes every camera's ``RobotDetections`` at 30 Hz (stamped with the capture time)
to a backend running as its own OS process (``smartedge backend``, no Rerun), and listens to
the camera-only poses it publishes. Reported per N: frame-sets per second, latency from the
detection stamp to the received pose (p50/p99; it includes both Zenoh hops, the
synchronizer and the solve), and dropped frame-sets (published frames without a pose).
Every frame's payloads are projected and encoded before the run (the cameras do that on their
own boards; ``--live-encode`` does it during the run, on the backend's cores, as the bench did
before), so only sending them shares the backend's cores with it.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import platform
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from core.session import loopback_config
from core.site import Site
from lab.launcher import free_port, start_service
from protocol import decode, keys
from protocol.messages import PoseEstimate, ServiceStatus
from simulation.camera_ring import detection_payloads, robot_pose, write_ring_site
from simulation.scenario import load_scenario


def _prepared_frames(site: Site, n_frames: int, rate_hz: float,
                     rng: np.random.Generator) -> tuple[int, list[list[tuple[str, bytes]]]]:
    """(first stamp, every frame's payloads) encoded before the run: the cameras project and
    encode on their own boards, so that work must not run on the backend's cores while it is
    measured. The first stamp lies far enough ahead for the encoding to finish (its time
    extrapolated from two frames, doubled, plus a second); a frame still sent late is counted
    (``late_publish``)."""
    t0 = time.perf_counter()
    for k in range(2):
        detection_payloads(site, robot_pose(0.0), 0, k, np.random.default_rng(k))
    per_frame_s = (time.perf_counter() - t0) / 2
    period_ns = round(1e9 / rate_hz)
    start_ns = time.time_ns() + round((2.0 * per_frame_s * n_frames + 1.0) * 1e9)
    frames = [detection_payloads(site, robot_pose(k / rate_hz), start_ns + k * period_ns, k, rng)
              for k in range(n_frames)]
    return start_ns, frames


def run_case(n_cameras: int, seconds: float, rate_hz: float, warmup_s: float,
             workdir: Path, live_encode: bool = False) -> dict[str, float]:
    """One case: a backend process fed ``n_cameras`` cameras at ``rate_hz`` for ``warmup_s``
    (not measured) + ``seconds``. ``live_encode``: each frame is projected and encoded by this
    process during the run (the previous bench: that work shares the backend's cores) instead
    of all frames before it."""
    import zenoh

    site_path = workdir / f"ring_{n_cameras}.yaml"
    site = write_ring_site(site_path, n_cameras)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    backend = start_service(
        ["backend", "--site", str(site_path), "--connect", endpoint, "--listen",
         "tcp/127.0.0.1:0"], workdir / f"backend_{n_cameras}.log", log_level="WARNING")
    poses: list[tuple[int, int]] = []  # (receive ns, stamp ns)
    statuses: list[ServiceStatus] = []
    try:
        with zenoh.open(loopback_config(listen=[endpoint])) as session:
            session.declare_subscriber(
                keys.camera_pose_key(site.name, "hsr"),
                lambda s: poses.append((time.time_ns(), s.payload.to_bytes())))
            session.declare_subscriber(
                keys.status_key(site.name, "backend", "*"),
                lambda s: statuses.append(s.payload.to_bytes()))
            deadline = time.monotonic() + 60
            while not statuses and time.monotonic() < deadline:
                time.sleep(0.1)  # the backend is up once it publishes its status
            if not statuses:
                raise RuntimeError(f"backend did not start; see {workdir}")
            pubs = {cam: session.declare_publisher(
                keys.detections_key(site.name, cam),
                congestion_control=zenoh.CongestionControl.BLOCK) for cam in site.cameras}
            rng = np.random.default_rng(0)
            period_ns = round(1e9 / rate_hz)
            n_frames = int((seconds + warmup_s) * rate_hz)
            warm_frames = int(warmup_s * rate_hz)
            if live_encode:
                start_ns = time.time_ns() + 200_000_000
                prepared: list[list[tuple[str, bytes]]] = []
            else:
                start_ns, prepared = _prepared_frames(site, n_frames, rate_hz, rng)
            measured_stamps: list[int] = []
            late_publish = 0
            for k in range(n_frames):
                stamp = start_ns + k * period_ns
                # each camera encodes its own frame in parallel on its own board: all the
                # payloads of a frame are ready before its capture time and sent together
                frame = prepared[k] if prepared else detection_payloads(
                    site, robot_pose(k / rate_hz), stamp, k, rng)
                while (now := time.time_ns()) < stamp:
                    time.sleep(min(0.002, (stamp - now) * 1e-9))
                if now - stamp > period_ns:
                    late_publish += 1
                for key, payload in frame:
                    pubs[key.split("/")[3]].put(payload)
                if k >= warm_frames:
                    measured_stamps.append(stamp)
            time.sleep(1.0)
        decoded = [(rx, decode(p)) for rx, p in poses]
        stamps = set(measured_stamps)
        latencies = np.array([(rx - est.stamp_ns) * 1e-6 for rx, est in decoded
                              if isinstance(est, PoseEstimate) and est.stamp_ns in stamps
                              and "multi_frame" not in est.flags])
        got = {est.stamp_ns for _, est in decoded if est.stamp_ns in stamps}
        last = decode(statuses[-1]) if statuses else None
        return {
            "cameras": n_cameras,
            "frame_sets_per_s": len(got) / seconds,
            "p50_ms": float(np.percentile(latencies, 50)) if latencies.size else math.nan,
            "p99_ms": float(np.percentile(latencies, 99)) if latencies.size else math.nan,
            "dropped": len(stamps) - len(got),
            "frames": len(stamps),
            "late_publish": late_publish,
            "backend_dropped": float(last.counters.get("dropped", 0)) if last else math.nan,
            "backend_shed": float(last.counters.get("shed", 0)) if last else math.nan,
        }
    finally:
        backend.stop(timeout_s=20.0)


def _busy_loop() -> None:
    while True:
        pass


@contextlib.contextmanager
def competing_load(n_processes: int) -> Iterator[None]:
    """``n_processes`` processes spinning on the CPU for the duration (a busy host)."""
    import multiprocessing

    procs = [multiprocessing.Process(target=_busy_loop, daemon=True) for _ in range(n_processes)]
    for p in procs:
        p.start()
    try:
        yield
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.join(5)


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench backend", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cameras", default="4,16,64", help="comma-separated camera counts")
    parser.add_argument("--seconds", type=float, default=10.0, help="measured time per case")
    parser.add_argument("--warmup", type=float, default=2.0, help="unmeasured start per case")
    parser.add_argument("--rate", type=float, default=30.0, help="frames per second")
    parser.add_argument("--stage-frames", type=int, default=60,
                        help="frame-sets per case of the in-process stage breakdown (0: skip)")
    parser.add_argument("--load", default="0",
                        help="comma-separated numbers of competing busy processes: each "
                             "Zenoh case runs once per value, e.g. 0,2 for quiet and busy")
    parser.add_argument("--no-zenoh", action="store_true",
                        help="only the in-process stage breakdown")
    parser.add_argument("--live-encode", action="store_true",
                        help="project and encode each frame during the run, on the backend's "
                             "cores (the previous bench); default: every frame before the run, "
                             "as the cameras do it on their own boards")
    args = parser.parse_args(list(argv))
    counts = [int(v) for v in args.cameras.split(",")]
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}")
    if args.stage_frames > 0:
        from lab.bench.backend_stages import print_stage_table

        print_stage_table(counts, args.stage_frames)
        print()
    if args.no_zenoh:
        return 0
    n_kp = len(load_scenario().site.robot_model().keypoint_names)  # the ring's robot
    print(f"backend in its own process, Zenoh on loopback, {args.rate:.0f} Hz, {n_kp} keypoints "
          f"per camera, {args.seconds:.0f} s per case, payloads encoded "
          + ("during the run (--live-encode)" if args.live_encode else "before the run"))
    print(f"{'cameras':>8}{'load':>6}{'frame-sets/s':>14}{'p50 ms':>9}{'p99 ms':>9}"
          f"{'dropped':>10}{'shed':>7}{'late pub':>10}")
    with tempfile.TemporaryDirectory(prefix="smartedge-bench-") as tmp:
        for n in counts:
            for load in (int(v) for v in args.load.split(",")):
                with competing_load(load):
                    r = run_case(n, args.seconds, args.rate, args.warmup, Path(tmp),
                                 args.live_encode)
                print(f"{n:>8}{load:>6}{r['frame_sets_per_s']:>14.1f}{r['p50_ms']:>9.2f}"
                      f"{r['p99_ms']:>9.2f}{int(r['dropped']):>6}/{int(r['frames']):<4}"
                      f"{int(r['backend_shed']):>6}{int(r['late_publish']):>9}", flush=True)
    print("latency: detection stamp -> camera pose received by a subscriber (both Zenoh hops, "
          "sync, solve); dropped: frames without a pose; shed: detections the backend dropped "
          "after waiting longer than pose.max_input_delay_s; load: competing busy processes; "
          "late pub: frames this publisher sent more than one period late (the load generator "
          "shares the cores)")
    return 0
