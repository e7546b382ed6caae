"""``smartedge bench <what>``: benchmarks print figures; results are recorded in
docs/benchmarks.md with the machine and the command. ``smartedge bench reliability`` is the
fault harness (:mod:`lab.bench.faults`): hostile and faulty input against the running
services, one verdict per probe (docs/reliability.md).

One module per benchmark: ``codec`` (wire codec round trips), ``pose`` (pose solve latency),
``robust`` (robust losses of the pose solver), ``single_camera`` (single-camera treatments,
covariance consistency), ``sim`` (simulated seconds per wall second), ``fusion`` (ISAM2 latency
and memory), ``association`` (CPU of matching detections to robots), ``backend`` (throughput
over real Zenoh), ``backend_stages`` (CPU per frame-set by pipeline stage), ``fleet`` (a
simulated facility on loopback), ``ros_source`` (edge frames/s from a ROS 2 topic), ``render``
(rendered images per second), ``edge`` (edge pipeline latency with onnxruntime), ``map``
(semantic map fusion and ICP), ``bridge`` (the robot bridge's ROS output), ``camera_health``
(bumped-camera detection), ``camera_health_cnn`` (the same on the shipped CNN's keypoints) and
``calibration_solver`` (the board adjustment's numpy Levenberg-Marquardt against GTSAM);
``faults``: the fault harness. Part of the lab wing: may import every other package.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Final

from smartedge.commands import Command, run_command

#: benchmark → :class:`~smartedge.commands.Command` (module, function taking argv and returning
#: an exit code, one-line help)
BENCHES: Final[dict[str, Command]] = {
    "codec": Command("lab.bench.codec", "main",
                     "encode+decode throughput of detections and clouds"),
    "pose": Command("lab.bench.pose", "main", "pose solve latency vs pyceres and scipy"),
    "robust": Command("lab.bench.robust", "main",
                      "robust losses: MSE vs the Cramer-Rao bound"),
    "single-camera": Command("lab.bench.single_camera", "main",
                             "single-camera treatments and covariance consistency (NEES)"),
    "sim": Command("lab.bench.sim", "main", "simulated seconds per wall second"),
    "fusion": Command("lab.bench.fusion", "main", "ISAM2 latency and memory over 1 h"),
    "association": Command("lab.bench.association", "main",
                           "CPU of matching detections to several robots per frame-set"),
    "backend": Command("lab.bench.backend", "main", "throughput/latency over real Zenoh"),
    "fleet": Command("lab.bench.fleet", "main",
                     "a facility on loopback: robots, cameras, routers, 1..3 backends"),
    "ros-source": Command("lab.bench.ros_source", "main",
                          "edge agent frames/s from a ROS 2 image topic"),
    "render": Command("lab.bench.render", "main", "rendered images/s with exact labels"),
    "edge": Command("lab.bench.edge", "main",
                    "detector + keypoint latency with onnxruntime"),
    "map": Command("lab.bench.map", "main",
                   "semantic map fusion (M points/s) and ICP latency"),
    "bridge": Command("lab.bench.bridge", "main",
                      "robot bridge ROS output: encoding per flavour, loopback latency"),
    "camera-health": Command("lab.bench.camera_health", "main",
                             "bumped-camera detection: delay, false alarms per hour, CPU"),
    "calibration-solver": Command("lab.bench.calibration_solver", "main",
                                  "board adjustment: numpy LM vs a GTSAM factor graph"),
    "reliability": Command("lab.bench.faults", "main",
                           "the fault harness: hostile and faulty input against the running "
                           "services, one verdict per probe"),
}


def main(argv: Sequence[str]) -> int:
    argv = list(argv)
    if not argv or argv[0] not in BENCHES:  # help, or a clear error listing the benchmarks
        parser = argparse.ArgumentParser(prog="smartedge bench",
                                         description=__doc__.split("\n\n")[0])
        parser.add_argument("what", choices=sorted(BENCHES), help="which benchmark")
        parser.parse_args(argv)
        return 2
    what, rest = argv[0], argv[1:]  # the benchmark parses its own options (and --help)
    return run_command(f"smartedge bench {what}", BENCHES[what], rest)
