"""``smartedge calibrate robot``: every camera's pose in the robot's map frame, from a drive of the
robot (a ``smartedge record`` MCAP, or live on the bus), solved jointly with its trajectory
(:mod:`calibration.robot_target`); writes an updated site file.

    smartedge calibrate robot --site site.yaml --recording drive.mcap --out site_new.yaml
    smartedge calibrate robot --site site.yaml --live --duration 300 --out site_new.yaml
    smartedge calibrate robot --site site.yaml --live --duration 120 --camera cam3 --out s.yaml

Only the ``cameras:`` poses change in the written file (as ``T_world_cam: {translation_m,
quaternion_xyzw}``); everything else is kept, but YAML comments are not (the file is re-written
from its parsed content; a header line says so). ``--camera`` recalibrates the named cameras and
holds the others at the site file's poses (they still pin the robot's trajectory); ``--frame
site`` keeps the recalibrated cameras' mean position and heading (the map frame) from the site
file instead of taking it from the robot's localization. A camera the
drive does not constrain is refused with the reason and the drive that would fix it; nothing is
written then (exit 3) unless ``--partial`` writes the others.

Exit codes: 0 written, 1 bad input (site, recording), 3 refused, 4 no usable data.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from core.site import Site, load_site
from protocol import keys
from protocol.codec import decode
from protocol.errors import DecodeError, SmartedgeError, ValidationError

EXIT_OK = 0
EXIT_BAD_INPUT = 1
EXIT_REFUSED = 3
EXIT_NO_DATA = 4

#: wire topics the calibration reads
ROBOT_TOPICS = ("odom", "localization")


class InputCounters:
    """What was read and what was not used, by reason (printed, and in ``--report``)."""

    def __init__(self) -> None:
        self.counts: collections.Counter[str] = collections.Counter()
        self.first_error: dict[str, str] = {}

    def bad(self, reason: str, detail: str) -> None:
        self.counts[reason] += 1
        self.first_error.setdefault(reason, detail)


def feed_recording(path: str | Path, data: Any, counters: InputCounters,
                   progress: Callable[[str], None] = print) -> int:
    """Feed the messages of an MCAP recording (``smartedge record``) for ``data.site`` into
    ``data`` (:class:`CalibrationData`); keys of other sites and topics are skipped, payloads
    that do not decode are counted with the first error. Returns the messages read."""
    from smartedge.commands.record import read_recording

    site = data.site.name
    n = 0
    t0 = time.monotonic()
    for key, _receive_ns, payload in read_recording(path):
        n += 1
        _feed_one(key, payload, site, data, counters)
        if n % 20000 == 0:
            progress(f"  read {n} messages ({time.monotonic() - t0:.1f} s)")
    return n


def _feed_one(key: str, payload: bytes, site: str, data: Any, counters: InputCounters) -> None:
    try:
        parsed = keys.parse_key(key)
    except ValidationError:
        counters.bad("foreign_key", key[:120])
        return
    if parsed.site != site:
        counters.bad("other_site", parsed.site)
        return
    wanted = (parsed.scope == "edge" and parsed.topic == "detections") or (
        parsed.scope == "robot" and parsed.topic in ROBOT_TOPICS)
    if not wanted:
        counters.counts["other_topic"] += 1
        return
    try:
        msg = decode(payload)
    except DecodeError as exc:
        counters.bad("undecodable", f"{key}: {exc}")
        return
    if parsed.message_type is not None and not isinstance(msg, parsed.message_type):
        counters.bad("wrong_type_on_key", f"{key}: {type(msg).__name__}")
        return
    if parsed.scope == "edge" and getattr(msg, "camera_id", None) != parsed.source_id:
        counters.bad("camera_id_not_key", f"{key}: camera_id {msg.camera_id!r}")
        return
    counters.counts["messages_used"] += 1
    data.add(msg)


def feed_live(site: Site, data: Any, counters: InputCounters, duration_s: float,
              session_args: argparse.Namespace, robot_id: str,
              progress: Callable[[str], None] = print) -> int:
    """Subscribe to the site's detections, the robot's odometry and localization for
    ``duration_s`` (Ctrl-C ends early) and feed them into ``data``. Returns messages read."""
    import zenoh

    from core.session import make_config, options_from_args

    queue: collections.deque[tuple[str, bytes]] = collections.deque()
    key_exprs = [keys.detections_key(site.name, "*"), keys.odom_key(site.name, robot_id),
                 keys.localization_key(site.name, robot_id)]
    n = 0
    with zenoh.open(make_config(options_from_args(session_args))) as session:
        subs = [session.declare_subscriber(
            k, lambda s: queue.append((str(s.key_expr), s.payload.to_bytes())))
            for k in key_exprs]
        progress(f"listening on {', '.join(key_exprs)} for {duration_s:.0f} s "
                 f"(Ctrl-C to stop early)")
        deadline = time.monotonic() + duration_s
        next_report = time.monotonic() + 5.0
        try:
            while time.monotonic() < deadline:
                while queue:
                    key, payload = queue.popleft()
                    n += 1
                    _feed_one(key, payload, site.name, data, counters)
                if time.monotonic() >= next_report:
                    next_report += 5.0
                    seen = {c: len(v) for c, v in data.sightings.items()}
                    progress(f"  {n} messages, sightings {seen}, "
                             f"{time.monotonic() - deadline + duration_s:.0f}/{duration_s:.0f} s")
                time.sleep(0.01)
        except KeyboardInterrupt:
            progress("stopped early")
        for sub in subs:
            sub.undeclare()
        while queue:
            key, payload = queue.popleft()
            n += 1
            _feed_one(key, payload, site.name, data, counters)
    return n


# --------------------------------------------------------------------------------------------
# the command
# --------------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="smartedge calibrate robot", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--site", required=True, help="the current site file (the initial guess)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--recording", help="an MCAP file written by smartedge record")
    src.add_argument("--live", action="store_true", help="listen on the bus")
    p.add_argument("--duration", type=float, default=300.0,
                   help="--live: seconds to listen (default 300)")
    p.add_argument("--camera", action="append", default=None, metavar="ID",
                   help="recalibrate only this camera (repeat for several); the others are "
                        "held at the site file's poses")
    p.add_argument("--robot", default=None, help="the robot that drove (default: the site's "
                                                 "only robot)")
    p.add_argument("--out", required=True, help="the updated site file to write")
    p.add_argument("--frame", choices=("localization", "site"), default="localization",
                   help="what places the cameras in the map frame: the robot's localization "
                        "(default; as good as its average error over the drive) or the site "
                        "file (the recalibrated cameras keep their mean position and heading; "
                        "the drive fixes everything else)")
    p.add_argument("--partial", action="store_true",
                   help="write the cameras that were constrained even if others were refused")
    p.add_argument("--report", default=None, help="also write the results as JSON here")
    p.add_argument("--min-sightings", type=int, default=None,
                   help="refuse a camera with fewer usable frames (default 30)")
    p.add_argument("--max-sigma-cm", type=float, default=None,
                   help="refuse a camera its own sightings constrain worse than this (default 1)")
    p.add_argument("--max-sigma-deg", type=float, default=None,
                   help="the same for rotation (default 0.1)")
    p.add_argument("--node-spacing", type=float, default=None,
                   help="seconds between trajectory nodes (default 0.5)")
    p.add_argument("--max-rate", type=float, default=None,
                   help="sightings per camera and second used at most (default 5; 0 = all)")
    from core.session import add_session_arguments

    add_session_arguments(p)
    return p


def _config(args: argparse.Namespace) -> Any:
    from calibration.robot_target import RobotTargetConfig

    changes: dict[str, Any] = {}
    if args.min_sightings is not None:
        changes["min_sightings"] = args.min_sightings
    if args.max_sigma_cm is not None:
        changes["max_sigma_m"] = args.max_sigma_cm / 100.0
    if args.max_sigma_deg is not None:
        changes["max_sigma_deg"] = args.max_sigma_deg
    if args.node_spacing is not None:
        changes["node_spacing_s"] = args.node_spacing
    if args.max_rate is not None:
        changes["max_frame_rate_hz"] = args.max_rate
    return RobotTargetConfig(**changes)


def format_table(result: Any) -> str:
    """The per-camera table: correction, uncertainty, sightings, RMS, status."""
    head = (f"{'camera':<8} {'status':<9} {'corr cm':>8} {'corr deg':>8} {'sigma cm':>8} "
            f"{'sigma deg':>9} {'own cm':>7} {'own deg':>7} {'frames':>6} {'rms px':>6}  init")
    rows = [head, "-" * len(head)]

    def f(v: float, fmt: str) -> str:
        width = int(fmt.split(".")[0])
        return format(v, fmt) if math.isfinite(v) else "-".rjust(width)

    for cid, r in sorted(result.cameras.items()):
        status = "fixed" if r.fixed else ("REFUSED" if r.refused else "ok")
        rows.append(f"{cid:<8} {status:<9} {f(r.correction_m * 100, '8.2f')} "
                    f"{f(r.correction_deg, '8.3f')} {f(r.sigma_m * 100, '8.2f')} "
                    f"{f(r.sigma_deg, '9.3f')} {f(r.own_sigma_m * 100, '7.2f')} "
                    f"{f(r.own_sigma_deg, '7.3f')} {r.sightings:>6} {f(r.rms_px, '6.2f')}  "
                    f"{r.init}")
    return "\n".join(rows)


def _report_json(result: Any, counters: InputCounters, written: Sequence[str]) -> dict:
    cams = {}
    for cid, r in sorted(result.cameras.items()):
        cams[cid] = {
            "status": "fixed" if r.fixed else ("refused" if r.refused else "ok"),
            "T_world_cam": np.asarray(r.T_world_cam).round(9).tolist(),
            "correction_m": r.correction_m, "correction_deg": r.correction_deg,
            "sigma_m": r.sigma_m, "sigma_deg": r.sigma_deg, "own_sigma_m": r.own_sigma_m,
            "own_sigma_deg": r.own_sigma_deg, "sightings": r.sightings, "rms_px": r.rms_px,
            "refused": r.refused, "init": r.init}
    return {"cameras": cams, "written": list(written), "rms_px": result.rms_px,
            "iterations": result.iterations, "seconds": result.seconds,
            "solver_counters": result.counters, "input_counters": dict(counters.counts),
            "first_errors": counters.first_error}


def main(argv: Sequence[str]) -> int:
    args = _parser().parse_args(list(argv))
    t0 = time.monotonic()
    from calibration.robot_target import (
        CalibrationData,
        CalibrationError,
        calibrate,
    )
    from calibration.site_file import write_site_with_cameras
    from smartedge.commands.record import RecordingError

    try:
        site = load_site(args.site)
        config = _config(args)
        data = CalibrationData(site, args.robot)
        if args.camera:
            unknown = sorted(set(args.camera) - set(site.cameras))
            if unknown:
                raise CalibrationError(f"--camera {unknown}: not in site {site.name!r} "
                                       f"({args.site}); known: {sorted(site.cameras)}")
    except (SmartedgeError, ValueError) as exc:
        print(f"smartedge calibrate robot: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    counters = InputCounters()
    try:
        if args.recording:
            print(f"reading {args.recording}", flush=True)
            n = feed_recording(args.recording, data, counters)
        else:
            if args.duration <= 0:
                print("smartedge calibrate robot: --duration must be > 0", file=sys.stderr)
                return EXIT_BAD_INPUT
            n = feed_live(site, data, counters, args.duration, args, data.robot_id)
    except RecordingError as exc:
        print(f"smartedge calibrate robot: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"{n} messages read in {time.monotonic() - t0:.1f} s: "
          f"{data.counters.get('sightings', 0)} sightings, "
          f"{data.counters.get('odometry', 0)} odometry, "
          f"{data.counters.get('localization', 0)} localization", flush=True)
    _print_counters(counters, data)
    if n == 0:
        print("smartedge calibrate robot: no messages (an empty recording, or nothing on the "
              "bus: are the edge agents and the robot bridge running?)", file=sys.stderr)
        return EXIT_NO_DATA
    try:
        result = calibrate(data, config, solve_cameras=args.camera, frame=args.frame,
                           progress=lambda m: print(m, flush=True))
    except CalibrationError as exc:
        print(f"smartedge calibrate robot: {exc}", file=sys.stderr)
        return EXIT_NO_DATA
    print()
    print(format_table(result))
    print(f"\njoint adjustment: {result.iterations} iterations, RMS {result.rms_px:.2f} px, "
          f"{result.seconds.get('total', math.nan):.1f} s")
    print("corr: change from the site file; sigma: 1-sigma of the weakest direction, placement "
          "in the map frame (the robot's localization) included; own: from the camera's own "
          "sightings with the trajectory fixed (decides refusals)")
    refused = result.refused
    for cid, reason in sorted(refused.items()):
        print(f"REFUSED {cid}: {reason}", file=sys.stderr)
    solved = result.solved
    written: list[str] = []
    code = EXIT_OK
    if refused and not args.partial:
        print(f"smartedge calibrate robot: nothing written to {args.out}: "
              f"{len(refused)} camera(s) refused (--partial writes the others)", file=sys.stderr)
        code = EXIT_REFUSED
    elif not solved:
        print("smartedge calibrate robot: no camera could be calibrated; nothing written",
              file=sys.stderr)
        code = EXIT_REFUSED
    else:
        header = (f"written by smartedge calibrate robot from "
                  f"{args.recording or 'the live bus'}: cameras {sorted(solved)} recalibrated")
        try:
            write_site_with_cameras(args.site, args.out, solved, header)
        except (SmartedgeError, OSError) as exc:
            print(f"smartedge calibrate robot: cannot write {args.out}: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        written = sorted(solved)
        print(f"wrote {args.out} (cameras {', '.join(written)}; comments of {args.site} "
              f"are not kept)")
    if args.report:
        Path(args.report).write_text(json.dumps(_report_json(result, counters, written),
                                                indent=1, default=float), encoding="utf-8")
    print(f"total {time.monotonic() - t0:.1f} s")
    return code


def _print_counters(counters: InputCounters, data: Any) -> None:
    skipped = {k: v for k, v in counters.counts.items() if k != "messages_used"}
    for k in ("unknown_camera", "wrong_keypoint_count", "non_finite_keypoints",
              "ambiguous_detection", "other_robot", "localization_wrong_frame"):
        if data.counters.get(k):
            skipped[k] = data.counters[k]
    if not skipped:
        return
    print("not used: " + ", ".join(f"{k} {v}" for k, v in sorted(skipped.items())))
    for k, detail in sorted(counters.first_error.items()):
        print(f"  first {k}: {detail}")
    if data.unknown_cameras:
        print(f"  cameras not in the site: {dict(data.unknown_cameras)}")
