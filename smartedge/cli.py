"""The ``smartedge`` command: one entry point, one module per subcommand, imported lazily so an
edge board (``smartedge[edge]``) can run ``smartedge edge-agent`` without the backend's
dependencies installed."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence
from typing import Final

from smartedge import __version__

#: subcommand → (module, function taking argv and returning an exit code, one-line help)
COMMANDS: Final[dict[str, tuple[str, str, str]]] = {
    "demo": ("smartedge.demo", "main", "run the whole system on the simulated paper site"),
    "edge-agent": ("edge_agent.service", "main", "run an edge agent (one camera)"),
    "backend": ("backend_service.service", "main", "run the backend service"),
    "robot-bridge": ("robot_bridge.service", "main", "run the robot bridge"),
    "evaluate": ("smartedge.evaluate", "main", "trajectory metrics and the paper's experiments"),
    "bench": ("smartedge.bench", "main", "benchmarks: codec, pose, sim, fusion, backend"),
    "site": ("smartedge.site_tool", "main", "check a site file or a camera calibration file"),
}


def _configure_logging(level: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog="smartedge",
        description="Marker-less mobile robot localization from static smart edge cameras.",
    )
    parser.add_argument("--version", action="version", version=f"smartedge {__version__}")
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, _, help_txt) in COMMANDS.items():
        sub.add_parser(name, help=help_txt, add_help=False)
    args, rest = parser.parse_known_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    _configure_logging(args.log_level)
    module_name, func_name, _ = COMMANDS[args.command]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name:
            print(f"smartedge {args.command}: not available in this version", file=sys.stderr)
            return 2
        print(
            f"smartedge {args.command}: missing dependency {exc.name!r}; install the extra that "
            "provides it (e.g. pip install 'smartedge[backend]')",
            file=sys.stderr,
        )
        return 2
    return int(getattr(module, func_name)(rest) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
