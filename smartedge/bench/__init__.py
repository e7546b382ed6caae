"""``smartedge bench <what>``: benchmarks print figures; results are recorded in
docs/benchmarks.md with the machine and the command. ``smartedge bench reliability`` is the
fault harness (:mod:`smartedge.bench.faults`): hostile and faulty input against the running
services, one verdict per probe (docs/reliability.md)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Final

from smartedge.commands import Command, run_command

#: benchmark → :class:`~smartedge.commands.Command` (module, function taking argv and returning
#: an exit code, one-line help)
BENCHES: Final[dict[str, Command]] = {
    "codec": Command("smartedge.bench.codec", "main",
                     "encode+decode throughput of detections and clouds"),
    "pose": Command("smartedge.bench.pose", "main", "pose solve latency vs pyceres and scipy"),
    "robust": Command("smartedge.bench.robust", "main",
                      "robust losses: MSE vs the Cramer-Rao bound"),
    "single-camera": Command("smartedge.bench.single_camera", "main",
                             "single-camera treatments and covariance consistency (NEES)"),
    "sim": Command("smartedge.bench.sim", "main", "simulated seconds per wall second"),
    "fusion": Command("smartedge.bench.fusion", "main", "ISAM2 latency and memory over 1 h"),
    "association": Command("smartedge.bench.association", "main",
                           "CPU of matching detections to several robots per frame-set"),
    "backend": Command("smartedge.bench.backend", "main", "throughput/latency over real Zenoh"),
    "fleet": Command("smartedge.bench.fleet", "main",
                     "a facility on loopback: robots, cameras, routers, 1..3 backends"),
    "ros-source": Command("smartedge.bench.ros_source", "main",
                          "edge agent frames/s from a ROS 2 image topic"),
    "render": Command("smartedge.bench.render", "main", "rendered images/s with exact labels"),
    "edge": Command("smartedge.bench.edge", "main",
                    "detector + keypoint latency with onnxruntime"),
    "map": Command("smartedge.bench.map", "main",
                   "semantic map fusion (M points/s) and ICP latency"),
    "bridge": Command("smartedge.bench.bridge", "main",
                      "robot bridge ROS output: encoding per flavour, loopback latency"),
    "camera-health": Command("smartedge.bench.camera_health", "main",
                             "bumped-camera detection: delay, false alarms per hour, CPU"),
    "reliability": Command("smartedge.bench.faults", "main",
                           "the fault harness: hostile and faulty input against the running "
                           "services (issue 17's probes)"),
}


def main(argv: Sequence[str]) -> int:
    argv = list(argv)
    if not argv or argv[0] not in BENCHES:  # help, or a clear error listing the benchmarks
        parser = argparse.ArgumentParser(prog="smartedge bench", description=__doc__)
        parser.add_argument("what", choices=sorted(BENCHES), help="which benchmark")
        parser.parse_args(argv)
        return 2
    what, rest = argv[0], argv[1:]  # the benchmark parses its own options (and --help)
    return run_command(f"smartedge bench {what}", BENCHES[what], rest)
