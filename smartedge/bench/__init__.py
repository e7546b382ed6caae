"""``smartedge bench <what>``: benchmarks print figures; results are recorded in
docs/benchmarks.md with the machine and the command."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from typing import Final

#: benchmark → (module, function taking argv and returning an exit code, one-line help)
BENCHES: Final[dict[str, tuple[str, str, str]]] = {
    "codec": ("smartedge.bench.codec", "main", "encode+decode throughput of detections and clouds"),
    "pose": ("smartedge.bench.pose", "main", "pose solve latency vs pyceres and scipy"),
    "robust": ("smartedge.bench.robust", "main", "robust losses: MSE vs the Cramer-Rao bound"),
    "single-camera": ("smartedge.bench.single_camera", "main",
                      "single-camera treatments and covariance consistency (NEES)"),
    "sim": ("smartedge.bench.sim", "main", "simulated seconds per wall second"),
    "fusion": ("smartedge.bench.fusion", "main", "ISAM2 latency and memory over 1 h"),
    "backend": ("smartedge.bench.backend", "main", "throughput/latency over real Zenoh"),
    "render": ("smartedge.bench.render", "main", "rendered images/s with exact labels"),
    "edge": ("smartedge.bench.edge", "main", "detector + keypoint latency with onnxruntime"),
    "map": ("smartedge.bench.map", "main", "semantic map fusion (M points/s) and ICP latency"),
    "bridge": ("smartedge.bench.bridge", "main",
               "robot bridge ROS output: encoding per flavour, loopback latency"),
    "reliability": ("smartedge.reliability", "main",
                    "hostile and faulty input against the running services (issue 17 probes)"),
}


def main(argv: Sequence[str]) -> int:
    argv = list(argv)
    if not argv or argv[0] not in BENCHES:  # help, or a clear error listing the benchmarks
        parser = argparse.ArgumentParser(prog="smartedge bench", description=__doc__)
        parser.add_argument("what", choices=sorted(BENCHES), help="which benchmark")
        parser.parse_args(argv)
        return 2
    what, rest = argv[0], argv[1:]  # the benchmark parses its own options (and --help)
    module_name, func_name, _ = BENCHES[what]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name:
            print(f"smartedge bench {what}: not available in this version", file=sys.stderr)
            return 2
        raise
    return int(getattr(module, func_name)(rest) or 0)
