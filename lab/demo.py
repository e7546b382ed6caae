"""``smartedge demo``: the whole system on the simulated paper site, over Zenoh on loopback.

Four edge agents (simulated cameras), the backend (sync, pose solve, pose graph), the viewer
(Rerun recording, with the simulator's ground truth), the robot bridge (simulated HSR with
drifting localization that accepts corrections while static) and the robot's head camera
talk over real Zenoh sessions on 127.0.0.1 (no router, no multicast). The head looks around
while the robot drives, as a ROS 2 robot: ``smartedge sim-head`` publishes its pan and tilt on
``/tf`` and its RGB-D frames on the HSR's topics the rmw_zenoh way, and ``smartedge
robot-camera --source ros`` (the node a real robot runs) makes the semantic clouds in
base_link, the camera's pose looked up in TF at each image stamp (``--no-clouds`` leaves both
and the edge clouds out).
By default they run as threads of this process, each with its own Zenoh session; with
``--processes`` each is its own OS process started with the same command a deployment uses.
A monitor session listens to everything, prints progress, and at the end prints the accuracy
summary against the simulator's ground truth.

``--robots N`` (N > 1): a fleet on crossing routes (:mod:`simulation.fleet`): two identical
HSR-like robots passing within 0.5 m of each other, and with ``--robots 3`` a robot of a second
type, a box base (``box_c``), crossing both their lanes; one robot bridge per robot
(``--adapter sim --robot <id>``), the site written to the output folder with both robot models
and every robot in its own ROS namespace, and the backend assigning the edge agents' unnamed
detections to the robots (each detection names its robot's type, as an edge running each
type's detector reports it, so the box base's go only to the box base). The rendered cameras
draw one robot, so a fleet's edge agents take their detections from the noise model
(``--detections noise``), and the head camera's clouds are left out.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import math
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from core.session import loopback_config
from core.site import Site
from lab.evaluation import scoring
from lab.evaluation.scoring import live_truth, pose_errors, rms_m
from lab.launcher import ServiceProcess, free_port, start_service, stop_services
from protocol import decode, keys
from protocol.messages import PoseCorrection, PoseEstimate, ServiceStatus

STARTUP_S: Final = 4.0
STARTUP_PROCESSES_S: Final = 10.0
DEMO_STOP_S: Final = 4.0
DEMO_MAX_SPEED_MPS: Final = 0.4
#: a fleet of this many robots or more mixes two types (the last robot a box base)
MIXED_FLEET_FROM: Final = 3


@dataclasses.dataclass
class Observed:
    """What the monitor saw (decoded on the main thread)."""

    camera: list[PoseEstimate] = dataclasses.field(default_factory=list)
    fused: list[PoseEstimate] = dataclasses.field(default_factory=list)
    localization: list[PoseEstimate] = dataclasses.field(default_factory=list)
    corrections: list[PoseCorrection] = dataclasses.field(default_factory=list)
    status: dict[str, ServiceStatus] = dataclasses.field(default_factory=dict)
    status_count: int = 0
    #: the robot each correction's key was for (same order as ``corrections``)
    correction_keys: list[str] = dataclasses.field(default_factory=list)


class Monitor:
    """A Zenoh session that records camera/fused/robot poses, corrections and statuses."""

    def __init__(self, site: str, robot_id: str | Sequence[str], endpoint: str) -> None:
        import zenoh

        self._raw: collections.deque[tuple[str, bytes]] = collections.deque()
        self.seen = Observed()
        self.session = zenoh.open(loopback_config(listen=["tcp/127.0.0.1:0"], connect=[endpoint]))
        topics = ("camera_pose", "pose", "localization", "correction")
        robots = [robot_id] if isinstance(robot_id, str) else list(robot_id)
        #: correction key → the robot it is for
        self._correction_keys = {keys.robot_key(site, r, "correction"): r for r in robots}
        self._subs = [
            self.session.declare_subscriber(keys.robot_key(site, r, t), self._on)
            for r in robots for t in topics
        ] + [self.session.declare_subscriber(keys.status_key(site, "*", "*"), self._on)]

    def _on(self, sample: Any) -> None:  # Zenoh thread: hand over only
        self._raw.append((str(sample.key_expr), sample.payload.to_bytes()))

    def drain(self) -> None:
        seen = self.seen
        while self._raw:
            key, payload = self._raw.popleft()
            msg = decode(payload)
            if isinstance(msg, ServiceStatus):
                seen.status[f"{msg.service}/{msg.instance_id}"] = msg
                seen.status_count += 1
            elif isinstance(msg, PoseCorrection):
                seen.corrections.append(msg)
                seen.correction_keys.append(self._correction_keys.get(key, ""))
            elif key.endswith("/camera_pose"):
                seen.camera.append(msg)
            elif key.endswith("/pose"):
                seen.fused.append(msg)
            elif key.endswith("/localization"):
                seen.localization.append(msg)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self.session.close()


def _errors(estimates: list[PoseEstimate], live: Any) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and orientation (rad) errors of estimates against ground truth."""
    return pose_errors(estimates, live_truth(live))


def _fmt(values_m: np.ndarray) -> str:
    if values_m.size == 0:
        return "    -   "
    return f"{100 * np.mean(values_m):5.1f} cm"


def summarize(seen: Observed, live: Any, out: Any = sys.stdout) -> dict[str, float]:
    """Print the accuracy summary; returns the headline figures (for tests)."""
    figures: dict[str, float] = {}
    print("\naccuracy against the simulator's ground truth", file=out)
    single = [e for e in seen.camera if "multi_frame" not in e.flags]
    multi = [e for e in seen.camera if "multi_frame" in e.flags]
    print(f"  {'source':<34}{'n':>6}{'mean':>10}{'median':>10}{'RMS':>10}{'deg':>8}", file=out)
    rows = [("cameras, 1 frame", single)]
    for n in (1, 2, 3, 4):
        sel = [e for e in single if len(e.camera_ids) == n]
        if sel:
            rows.append((f"  seen by {n} camera{'s' if n > 1 else ''}", sel))
    rows += [
        ("cameras, averaged while static", multi),
        ("fused (pose graph)", seen.fused),
        ("robot's own localization", seen.localization),
    ]
    for name, estimates in rows:
        dt, dth = _errors(estimates, live)
        if dt.size == 0:
            print(f"  {name:<34}{0:>6}{'-':>10}{'-':>10}{'-':>10}{'-':>8}", file=out)
            continue
        rms = rms_m(dt)
        print(
            f"  {name:<34}{dt.size:>6}{100 * dt.mean():>7.1f} cm{100 * np.median(dt):>7.1f} cm"
            f"{100 * rms:>7.1f} cm{math.degrees(float(np.mean(dth))):>8.2f}",
            file=out,
        )
        figures[name.strip()] = rms
    kinds = collections.Counter(c.kind for c in seen.corrections)
    print(
        f"  corrections pushed to the robot: {len(seen.corrections)} "
        f"({', '.join(f'{k}: {v}' for k, v in sorted(kinds.items())) or 'none'})",
        file=out,
    )
    figures["corrections"] = float(len(seen.corrections))
    robot_ids = list(getattr(live, "robot_ids", ()))
    if len(robot_ids) > 1:
        figures.update(summarize_fleet(seen, live, out))
    return figures


def summarize_fleet(seen: Observed, live: Any, out: Any = sys.stdout) -> dict[str, float]:
    """Per robot of a fleet: estimates and RMS errors, corrections, and the corrections that
    went to the wrong robot (on another robot's key, or placing it nearer another robot's
    true pose than its own); figures by name (``<robot> fused``, ``wrong_corrections``)."""
    figures: dict[str, float] = {}
    print("\nper robot (fleet)", file=out)
    print(f"  {'robot':<10}{'model':<10}{'camera n':>9}{'RMS':>9}{'fused n':>9}{'RMS':>9}"
          f"{'corrections':>13}", file=out)
    models = getattr(getattr(live, "site", None), "robots", {})
    for rid in live.robot_ids:
        single = [e for e in seen.camera if e.robot_id == rid and "multi_frame" not in e.flags]
        fused = [e for e in seen.fused if e.robot_id == rid]
        dc, _ = _errors(single, live)
        df, _ = _errors(fused, live)
        rc, rf = rms_m(dc), rms_m(df)
        n_corr = sum(c.robot_id == rid for c in seen.corrections)
        print(f"  {rid:<10}{models.get(rid, '?'):<10}{dc.size:>9}{100 * rc:>6.1f} cm"
              f"{df.size:>9}{100 * rf:>6.1f} cm{n_corr:>13}", file=out)
        figures[f"{rid} cameras"] = rc
        figures[f"{rid} fused"] = rf
        figures[f"{rid} fused n"] = float(df.size)
    wrong = wrong_robot_corrections(seen, live)
    print(f"  corrections to the wrong robot: {wrong}", file=out)
    figures["wrong_corrections"] = float(wrong)
    backend = next((st for name, st in sorted(seen.status.items())
                    if name.startswith("backend/")), None)
    if backend is not None:
        counts = {k: int(backend.counters.get(f"association.detections_{k}", 0))
                  for k in ("assigned", "ambiguous", "unassigned", "no_prediction",
                            "unknown_model")}
        print("  the backend's assignment of unnamed detections (last status): "
              + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in counts.items()), file=out)
        figures.update({f"detections_{k}": float(v) for k, v in counts.items()})
    return figures


def wrong_robot_corrections(seen: Observed, live: Any) -> int:
    """Corrections that went to the wrong robot: sent on another robot's key, or placing the
    robot nearer another robot's true position than its own
    (:func:`lab.evaluation.scoring.wrong_robot_corrections`)."""
    return scoring.wrong_robot_corrections(
        seen.corrections, live_truth(live), list(live.robot_ids),
        key_robots=seen.correction_keys or None)


class Services:
    """Starts and stops the services, in threads or processes."""

    def __init__(
        self,
        args: argparse.Namespace,
        spec: Any,
        site_path: Path,
        endpoint: str,
        rrd: str,
        camera_ids: Sequence[str],
        out_dir: Path | None = None,
    ) -> None:
        self.args = args
        self.out_dir = out_dir
        self.spec = spec
        self.site_path = site_path
        self.endpoint = endpoint
        self.rrd = rrd
        self.camera_ids = list(camera_ids)
        self.procs: list[ServiceProcess] = []
        self.runners: list[Any] = []
        self.threads: list[threading.Thread] = []

    def commands(self) -> list[tuple[str, list[str]]]:
        """(name, smartedge argv) of every service, as a deployment would start them."""
        sim = self.spec.to_argv()
        site = ["--site", str(self.site_path)]
        listen_any = ["--listen", "tcp/127.0.0.1:0", "--connect", self.endpoint]
        backend = ["backend", *site, "--listen", self.endpoint, "--connect", self.endpoint]
        viewer = ["viewer", *site, "--rerun", self.rrd, "--sim-truth", *sim, *listen_any]
        bridge = ["robot-bridge", *site, "--adapter", "sim", *sim, *listen_any]
        if self.args.no_feedback:
            bridge.append("--no-feedback")
        if self.args.kidnapped:
            bridge.append("--kidnapped")
        robots = self.robot_ids()
        # a fleet: one bridge per robot, each driving its own simulated robot
        bridges = ([("robot-bridge", bridge)] if len(robots) == 1 else
                   [(f"robot-bridge/{r}", [*bridge, "--robot", r]) for r in robots])
        mode = getattr(self.args, "detections", DEFAULT_DETECTIONS)
        detections = ["--detections", mode]
        if mode == "cnn":
            rate = getattr(self.args, "render_rate", DEFAULT_RENDER_RATE_HZ)
            # four agents share the machine: one onnxruntime thread each
            detections += ["--render-rate", f"{rate:g}", "--threads", "1",
                           "--preview-rate", f"{DEMO_PREVIEW_RATE_HZ:g}"]
        clouds = not getattr(self.args, "no_clouds", False)
        if mode == "cnn" and clouds:
            # semantic clouds from the rendered RGB-D frames (one onnxruntime thread each)
            detections += ["--cloud-rate", f"{DEMO_CLOUD_RATE_HZ:g}"]
        elif mode == "cnn":
            detections += ["--cloud-rate", "0"]
        edges = [
            ["edge-agent", *site, "--camera", c, "--source", "sim", *sim, *detections,
             *listen_any]
            for c in self.camera_ids
        ]
        # the robot's head camera: the simulated robot publishes its panning head as ROS 2
        # topics (/tf, RGB-D); the real robot's node makes the clouds in base_link from them
        sim_head = ["sim-head", "--rate", f"{DEMO_HEAD_RATE_HZ:g}", *sim, *listen_any]
        robot_camera = ["robot-camera", "--source", "ros", *site, "--cloud-rate",
                        f"{DEMO_CLOUD_RATE_HZ:g}", "--threads", "1", *listen_any]
        # the semantic map, from the empty room's prior model, kept in the output folder (only
        # with one: run_demo writes the prior model there)
        mapper = [] if self.out_dir is None else [
            "mapper", *site, "--prior-model", str(self.out_dir / PRIOR_MODEL_FILE),
            "--snapshot", str(self.out_dir / MAP_FILE), *listen_any]
        return [
            ("backend", backend),
            *((f"edge-agent/{c}", e) for c, e in zip(self.camera_ids, edges, strict=True)),
            *bridges,
            *([("sim-head", sim_head), ("robot-camera", robot_camera)] if clouds else []),
            *([("mapper", mapper)] if clouds and mapper else []),
            *([("viewer", viewer)] if self.rrd != "none" else []),
        ]

    def robot_ids(self) -> list[str]:
        """The robots of the simulation (one unless the spec is a fleet)."""
        count = int(getattr(self.spec, "robots", 1) or 1)
        if count == 1:
            return [""]
        from simulation.fleet import fleet_robot_ids

        return fleet_robot_ids(count, bool(getattr(self.spec, "mixed", False)))

    def start(self, log_dir: Path) -> None:
        if self.args.processes:
            for name, argv in self.commands():
                self.procs.append(start_service(
                    argv, log_dir / f"{name.replace('/', '_')}.log", name=name))
            return
        from core.runtime import ZenohRunner

        for name, argv in self.commands():
            node, config = _build_in_process(argv)
            runner = ZenohRunner(node, config)
            thread = threading.Thread(target=runner.run, name=name, daemon=True)
            thread.start()
            self.runners.append(runner)
            self.threads.append(thread)

    def alive(self) -> bool:
        if self.procs:
            return all(p.running() for p in self.procs)
        return all(t.is_alive() for t in self.threads)

    def stop(self) -> list[int]:
        """Stop everything (SIGTERM for processes); returns the exit codes."""
        codes = list(stop_services(list(reversed(self.procs)), timeout_s=20.0).values())
        for runner in reversed(self.runners):
            runner.stop()
        for thread in reversed(self.threads):
            thread.join(20)
            codes.append(0 if not thread.is_alive() else -1)
        return codes


def _build_in_process(argv: list[str]) -> tuple[Any, Any]:
    """The node and Zenoh config a service would build from ``argv`` (same code path)."""
    import importlib

    from core.session import make_config, options_from_args
    from smartedge.simulated_site import register_simulation

    register_simulation()
    command, rest = argv[0], argv[1:]
    module = {
        "backend": "backend_service.service",
        "robot-bridge": "robot_bridge.service",
        "edge-agent": "edge_agent.service",
        "robot-camera": "smartedge.simulated_head_camera",
        "sim-head": "lab.simulated_head",
        "mapper": "mapper.service",
        "viewer": "smartedge.viewer",
    }[command]
    source = rest[rest.index("--source") + 1] if "--source" in rest[:-1] else "sim"
    if command == "robot-camera" and source == "ros":
        module = "edge_agent.robot_camera"  # the real robot's node (what --source ros runs)
    svc = importlib.import_module(module)
    args = svc.build_parser().parse_args(rest)
    return svc.build_node(args), make_config(options_from_args(args))


#: how the demo's edge agents detect the robot, and the rendered frame rate per camera
DEFAULT_DETECTIONS = "cnn"
DEFAULT_RENDER_RATE_HZ = 5.0
#: the demo's edge agents send the viewer one camera image per second (the Rerun view shows
#: each camera's image with its detected box and keypoints)
DEMO_PREVIEW_RATE_HZ = 1.0
#: semantic clouds per second from each edge camera (with --detections cnn) and from the
#: robot's head camera
DEMO_CLOUD_RATE_HZ = 1.0
#: RGB-D frames per second the simulated head publishes (the robot camera takes one a second)
DEMO_HEAD_RATE_HZ = 2.0
#: in the output folder: the empty room's prior model (PLY) the mapper starts from, and the map
PRIOR_MODEL_FILE = "room_prior.ply"
MAP_FILE = "semantic_map.npz"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smartedge demo",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--duration",
        type=float,
        help="seconds of simulated operation (default: one trajectory run)",
    )
    parser.add_argument("--trajectory", default="traj3", help="traj1, traj2 or traj3")
    parser.add_argument("--seed", type=int, default=0, help="noise seed")
    parser.add_argument("--out", default="runs/demo", help="output folder (recording, logs)")
    parser.add_argument(
        "--rerun",
        help="viewer target: save:PATH.rrd (default save:OUT/smartedge.rrd), spawn, "
        "connect[:URL], serve, or none (no viewer)",
    )
    parser.add_argument(
        "--processes", action="store_true", help="run every service as its own OS process"
    )
    parser.add_argument(
        "--no-feedback",
        action="store_true",
        help="never push corrections to the robot (to compare)",
    )
    parser.add_argument(
        "--kidnapped",
        action="store_true",
        help="the robot starts without localization (initialized by cameras)",
    )
    parser.add_argument(
        "--detections", choices=("noise", "cnn"), default=DEFAULT_DETECTIONS,
        help="edge agents: the detection noise model, or rendered images through the shipped "
        f"ONNX models (closed loop) (default {DEFAULT_DETECTIONS})",
    )
    parser.add_argument(
        "--render-rate", type=float, default=DEFAULT_RENDER_RATE_HZ, metavar="HZ",
        help="--detections cnn: frames per second per camera (default "
        f"{DEFAULT_RENDER_RATE_HZ:g}: what 2 CPU cores render and infer for 4 cameras)",
    )
    parser.add_argument(
        "--no-clouds", action="store_true",
        help="no semantic clouds: the edge agents make none, and neither the simulated head "
        f"(smartedge sim-head) nor the robot camera (smartedge robot-camera --source ros, "
        f"{DEMO_CLOUD_RATE_HZ:g} Hz) runs",
    )
    parser.add_argument(
        "--robots", type=int, default=1, metavar="N",
        help="robots (1-3, default 1); more than one: a fleet on crossing routes, one robot "
        "bridge each, detections from the noise model (typed), no clouds; 2: two identical "
        "HSR-like robots; 3: two HSR-like robots and a box base",
    )
    parser.add_argument("--progress-s", type=float, default=5.0, help="progress line period")
    return parser


@dataclasses.dataclass
class DemoResult:
    """What a demo run produced: the monitor's observations, the headline figures (RMS
    translation errors in metres by source, corrections count), the services' exit codes and
    the recording."""

    seen: Observed
    figures: dict[str, float]
    exit_codes: list[int]
    rrd_path: Path | None
    out_dir: Path
    live: Any

    @property
    def ok(self) -> bool:
        return bool(self.seen.camera) and all(c == 0 for c in self.exit_codes)


def main(argv: Sequence[str]) -> int:
    return 0 if run_demo(argv).ok else 1


def run_demo(argv: Sequence[str]) -> DemoResult:
    """Run the demo (see :func:`build_parser` for the options) and print its summary."""
    from simulation.live import LiveSimSpec, LiveSimulation
    from simulation.scenario import load_scenario

    parser = build_parser()
    args = parser.parse_args(list(argv))
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    rrd = args.rerun or f"save:{out_dir / 'smartedge.rrd'}"
    scenario = load_scenario()
    site_path = Path(scenario.site.source_path)
    if args.robots < 1:
        parser.error("--robots must be >= 1")
    if args.robots > 1:
        site_path = _fleet_setup(args, parser, scenario.site, out_dir)
    startup_s = STARTUP_PROCESSES_S if args.processes else STARTUP_S
    spec = LiveSimSpec(
        trajectory=args.trajectory,
        seed=args.seed,
        epoch_ns=time.time_ns() + round(startup_s * 1e9),
        stop_s=DEMO_STOP_S,
        max_speed_mps=DEMO_MAX_SPEED_MPS,
        robots=args.robots,
        mixed=args.robots >= MIXED_FLEET_FROM,
    )
    live = LiveSimulation(spec, scenario)
    duration_s = args.duration if args.duration else live.duration_s + 1.0
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    mode = "separate processes" if args.processes else "threads of one process"
    what = (f"robot {live.robot_id!r}, {args.trajectory} "
            f"({live.run.plan.path_length_m:.1f} m, {live.duration_s:.0f} s)"
            if args.robots == 1 else
            f"{args.robots} robots "
            f"{', '.join(f'{r} ({live.site.robots[r]})' for r in live.robot_ids)} on crossing "
            f"routes ({live.duration_s:.0f} s), site {site_path}")
    print(
        f"smartedge demo: site {scenario.site.name!r}, {len(scenario.site.cameras)} cameras, "
        f"{what}, services as {mode}, Zenoh on {endpoint}, correction "
        f"feedback {'off' if args.no_feedback else 'on'}"
    )
    if not args.no_clouds:
        from lab.experiments.mapping import write_prior_model

        (out_dir / MAP_FILE).unlink(missing_ok=True)  # a fresh map every demo
        write_prior_model(scenario, out_dir / PRIOR_MODEL_FILE)
    services = Services(args, spec, site_path, endpoint, rrd, sorted(scenario.site.cameras),
                        out_dir)
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    monitor = None
    try:
        monitor = Monitor(scenario.site.name, list(live.robot_ids), endpoint)
        services.start(out_dir)
        end_ns = spec.epoch_ns + round(duration_s * 1e9)
        next_progress = time.monotonic() + args.progress_s
        while time.time_ns() < end_ns and not stop.is_set():
            time.sleep(0.1)
            monitor.drain()
            if not services.alive():
                print("a service exited unexpectedly; see the logs in", out_dir, file=sys.stderr)
                break
            if time.monotonic() >= next_progress:
                next_progress += args.progress_s
                _progress(monitor.seen, live, spec.epoch_ns)
        time.sleep(0.5)
        monitor.drain()
    finally:
        codes = services.stop()
        if monitor is not None:
            monitor.drain()
            monitor.close()
        signal.signal(signal.SIGINT, previous)
    seen = monitor.seen if monitor else Observed()
    figures = summarize(seen, live)
    print(
        f"  status messages received: {seen.status_count} from "
        f"{', '.join(sorted(seen.status)) or 'nobody'}"
    )
    tum = write_trajectories(seen, live, out_dir / "tum")
    rrd_path = Path(rrd[5:]) if rrd.startswith("save:") else None
    if tum:
        one = out_dir / "tum" / (live.robot_id if args.robots > 1 else "")
        print(f"\ntrajectories (TUM): {out_dir / 'tum'}/{{{','.join(tum)}}}.tum  (e.g. "
              f"evo_ape tum {one / 'ground_truth.tum'} "
              f"{one / 'fused.tum'}, or smartedge evaluate ate ...)")
    if not args.no_clouds:
        figures.update(summarize_map(scenario, out_dir))
    if rrd_path is not None:
        print(f"\nRerun recording: {rrd_path}  (open with: rerun {rrd_path})")
    if args.processes:
        print(f"service logs: {out_dir}/*.log; exit codes {codes}")
    return DemoResult(seen, figures, codes, rrd_path, out_dir, live)


#: the fleet's site file in the demo's output folder
FLEET_SITE_FILE = "fleet_site.yaml"


def _fleet_setup(args: argparse.Namespace, parser: argparse.ArgumentParser, site: Site,
                 out_dir: Path) -> Path:
    """``--robots N`` > 1: the noise-model detections and no clouds (said so), and the
    fleet's site file (every robot in its own ROS namespace; a mixed fleet's models: the site's
    and the box base's) written to ``out_dir``."""
    import yaml

    from simulation.fleet import fleet_site_document, fleet_spec

    try:
        models = fleet_spec(args.robots, args.robots >= MIXED_FLEET_FROM)  # 1..3 robots
    except ValueError as exc:
        parser.error(f"--robots: {exc}")
    if args.detections == "cnn":
        print("smartedge demo: --robots > 1: the rendered cameras draw one robot; the edge "
              "agents use the detection noise model (--detections noise)")
        args.detections = "noise"
    if not args.no_clouds:
        print("smartedge demo: --robots > 1: no semantic clouds (the head camera and the "
              "rendered cameras follow one robot)")
        args.no_clouds = True
    path = out_dir / FLEET_SITE_FILE
    path.write_text(yaml.safe_dump(fleet_site_document(site, models), sort_keys=False))
    return path


def summarize_map(scenario: Any, out_dir: Path, out: Any = sys.stdout) -> dict[str, float]:
    """Print the semantic map's coverage and label accuracy against the simulation's ground
    truth (the map the mapper saved when it stopped); the figures by name."""
    from lab.experiments.mapping import ground_truth, map_scores
    from mapper.map_io import load_map_npz
    from mapper.semantic_map import MapError

    path = out_dir / MAP_FILE
    try:
        m = load_map_npz(path)
    except MapError as exc:
        print(f"\nsemantic map: none ({exc})", file=out)
        return {}
    scores = map_scores(m, ground_truth(scenario, m.config.voxel_size_m))
    print(f"\nsemantic map: {len(m)} voxels, {scores.labelled_voxels} with semantics; "
          f"{scores.coverage:.1%} of the room's surfaces covered, label accuracy "
          f"{scores.accuracy:.1%} ({path}; smartedge map export {path} map.ply)", file=out)
    return {"map_coverage": scores.coverage, "map_accuracy": scores.accuracy}


def write_trajectories(seen: Observed, live: Any, folder: Path) -> list[str]:
    """TUM files of every pose source the demo saw (``camera`` = single-frame camera
    estimates, ``camera_averaged``, ``fused``, ``localization``) and ``ground_truth`` at the
    fused stamps (the densest source). Returns the names written. A fleet: the same per
    robot, in ``folder/<robot>/`` (names ``<robot>/<source>``)."""
    from core.trajectory import write_estimates_tum

    robot_ids = list(getattr(live, "robot_ids", ()))
    if len(robot_ids) > 1:
        written_all: list[str] = []
        for rid in robot_ids:
            mine = Observed(
                camera=[e for e in seen.camera if e.robot_id == rid],
                fused=[e for e in seen.fused if e.robot_id == rid],
                localization=[e for e in seen.localization if e.robot_id == rid])
            written_all += [f"{rid}/{n}" for n in _write_robot_trajectories(
                mine, live, folder / rid, write_estimates_tum)]
        return written_all
    return _write_robot_trajectories(seen, live, folder, write_estimates_tum)


def _write_robot_trajectories(seen: Observed, live: Any, folder: Path, write: Any
                              ) -> list[str]:
    write_estimates_tum = write
    sources = {
        "camera": [e for e in seen.camera if "multi_frame" not in e.flags],
        "camera_averaged": [e for e in seen.camera if "multi_frame" in e.flags],
        "fused": seen.fused,
        "localization": seen.localization,
    }
    written = []
    for name, estimates in sources.items():
        if estimates:
            write_estimates_tum(folder / f"{name}.tum", estimates)
            written.append(name)
    reference = seen.fused or seen.camera or seen.localization
    truth_at = live_truth(live)
    if reference:
        truth = [dataclasses.replace(e, x=float(g[0]), y=float(g[1]), theta=float(g[2]))
                 for e in reference
                 for g in [truth_at(e.stamp_ns, e.robot_id)]]
        write_estimates_tum(folder / "ground_truth.tum", truth)
        written.append("ground_truth")
    return written


def _progress(seen: Observed, live: Any, epoch_ns: int) -> None:
    t = (time.time_ns() - epoch_ns) * 1e-9
    if t < 0:
        print(f"  t={t:6.1f} s  waiting for the start")
        return
    truth = live.ground_truth(time.time_ns())
    recent = [e for e in seen.camera[-30:] if "multi_frame" not in e.flags
              and e.robot_id == live.robot_id]
    cams = len(recent[-1].camera_ids) if recent else 0
    dt_cam, _ = _errors(recent, live)
    dt_fused, _ = _errors([e for e in seen.fused[-90:] if e.robot_id == live.robot_id], live)
    dt_loc, _ = _errors([e for e in seen.localization[-30:] if e.robot_id == live.robot_id],
                        live)
    who = "robot" if len(getattr(live, "robot_ids", ())) <= 1 else live.robot_id
    print(
        f"  t={t:6.1f}/{live.duration_s:.0f} s  {who} at ({truth[0]:5.2f}, {truth[1]:5.2f})  "
        f"seen by {cams} cam  error: cameras {_fmt(dt_cam)}, fused {_fmt(dt_fused)}, "
        f"robot's own {_fmt(dt_loc)}  corrections {len(seen.corrections)}",
        flush=True,
    )
