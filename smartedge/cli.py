"""The ``smartedge`` command: one entry point, one module per subcommand, imported lazily so an
edge board (``smartedge[edge]``) can run ``smartedge edge-agent`` without the backend's
dependencies installed."""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from collections.abc import Mapping, MutableMapping, Sequence
from typing import Final

from smartedge import __version__
from smartedge.commands import Command, run_command

#: exit status when the reader of our output closed the pipe (128 + SIGPIPE, as a shell reports)
EXIT_BROKEN_PIPE: Final = 141

#: the app's subcommands → :class:`~smartedge.commands.Command` (module, function taking argv
#: and returning an exit code, one-line help): the services (started through the composition
#: root, :mod:`smartedge.services`, where something is registered into them first) and the
#: operator's tools (:mod:`smartedge.commands`, one module per command).
COMMANDS: Final[dict[str, Command]] = {
    "edge-agent": Command("smartedge.services", "edge_agent_main",
                          "run an edge agent (one camera)"),
    "backend": Command("backend_service.service", "main", "run the backend service"),
    "mapper": Command("mapper.service", "main",
                      "run the semantic mapping service (clouds in, one semantic voxel map out)"),
    "robot-bridge": Command("smartedge.services", "robot_bridge_main", "run the robot bridge"),
    "robot-camera": Command("smartedge.services", "robot_camera_main",
                            "the robot's head RGB-D camera as semantic clouds in base_link "
                            "(--source ros: the real robot's topics; sim: the simulated head)"),
    "viewer": Command("smartedge.viewer", "main",
                      "watch a running system in Rerun (a sink of the keys)"),
    "router": Command("smartedge.commands.router", "main",
                      "run the site's Zenoh router (zenohd optional)"),
    "certs": Command("smartedge.commands.certs", "main",
                     "the site's CA, one certificate per identity, router ACL"),
    "calibrate": Command("smartedge.commands.calibrate", "main",
                         "calibrate the site: ChArUco board, intrinsics, extrinsics, and the "
                         "robot itself as the target"),
    "site": Command("smartedge.commands.site", "main",
                    "check a site file or a camera calibration file"),
    "map": Command("smartedge.commands.map", "main", "semantic map files: info, export to PLY"),
    "dataset": Command("smartedge.commands.dataset", "main",
                       "labelled frames (COCO keypoints): info, show, split, merge, import"),
    "status": Command("smartedge.commands.status", "status_main",
                      "the live services: state, rates, latencies, problem counters"),
    "echo": Command("smartedge.commands.status", "echo_main",
                    "print every message on a key, decoded"),
    "record": Command("smartedge.commands.record", "record_main",
                      "capture the traffic into an MCAP file"),
    "replay": Command("smartedge.commands.record", "replay_main", "publish an MCAP recording back"),
    "export": Command("smartedge.commands.export", "main",
                      "data out of a recording: poses as a TUM trajectory"),
}

#: the entry-point group through which an installed package adds commands to ``smartedge``
#: (as ``ros2cli`` extensions do): each entry point names a mapping of command name →
#: :class:`~smartedge.commands.Command`. The lab wing registers its commands here (``demo``,
#: ``evaluate``, ``bench``, ``render``, ``train``, ``sim-head``; pyproject.toml), so the app
#: never imports it and an installation without it simply lacks those commands.
COMMAND_ENTRY_POINTS: Final = "smartedge.commands"


def plugin_commands(group: str = COMMAND_ENTRY_POINTS) -> dict[str, Command]:
    """The commands the installed packages register in ``group``; an entry point that cannot
    be loaded, is not a mapping of :class:`Command`, or takes a name already taken is logged
    and left out (the rest of the CLI still works)."""
    from importlib.metadata import entry_points

    log = logging.getLogger(__name__)
    found: dict[str, Command] = {}
    for entry in sorted(entry_points(group=group), key=lambda e: e.name):
        try:
            table = entry.load()
        except (ImportError, AttributeError) as exc:
            log.warning("commands of %s (%s) not available: %s", entry.name, entry.value, exc)
            continue
        if not isinstance(table, Mapping):
            log.warning("entry point %s (%s) is not a mapping of commands", entry.name,
                        entry.value)
            continue
        for name, command in table.items():
            if not isinstance(command, Command):
                log.warning("%s: command %r is not a smartedge.commands.Command", entry.value,
                            name)
            elif name in COMMANDS or name in found:
                log.warning("%s: command %r is taken; left out", entry.value, name)
            else:
                found[name] = command
    return found


#: the global options that take a value (the token after them is not the command)
_VALUED_OPTIONS: Final = ("--log-level", "--log-format")


def command_name(argv: Sequence[str]) -> str | None:
    """The subcommand of a ``smartedge`` command line (the first word that is neither a global
    option nor its value), ``None`` when there is none."""
    skip = False
    for word in argv:
        if skip:
            skip = False
        elif word in _VALUED_OPTIONS:
            skip = True
        elif not word.startswith("-"):
            return word
    return None


def all_commands() -> dict[str, Command]:
    """The app's :data:`COMMANDS` followed by the registered ones (:func:`plugin_commands`)."""
    return {**COMMANDS, **plugin_commands()}



class JsonFormatter(logging.Formatter):
    """One JSON object per line (for journald/Loki/Elastic): time, level, logger, message,
    and the exception text when there is one."""

    def format(self, record: logging.LogRecord) -> str:
        import json

        doc = {
            "ts": self.formatTime(record, "%Y-%m-%dT%H:%M:%S") + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
            "pid": record.process,
            "thread": record.threadName,
        }
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc)


def _configure_logging(level: str, fmt: str) -> None:
    handler = logging.StreamHandler(sys.stderr)
    if fmt == "json":
        formatter: logging.Formatter = JsonFormatter()
        formatter.converter = time.gmtime  # type: ignore[attr-defined]
    else:
        formatter = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    handler.setFormatter(formatter)
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), handlers=[handler])


#: environment defaults every ``smartedge`` command starts with (a value already set wins).
#: ``OPENBLAS_NUM_THREADS=1``: numpy's BLAS on the calling thread only. Its matrices here are
#: small (3 x 3 to a few hundred elements), a service's parallelism is its processes, and
#: OpenBLAS's worker thread, once woken by a call it chose to split, busy-waits for the next
#: one with sched_yield for a long while: on a loaded host it takes a core's share from the
#: services. In the fleet benchmark each backend's worker thread burnt 40-110 ms of CPU in
#: bursts every few seconds, every backend at once, and those bursts were the latency tail
#: (docs/benchmarks.md, "The BLAS thread"). Read when numpy loads, so set before any import.
PROCESS_DEFAULTS: Final = {"OPENBLAS_NUM_THREADS": "1"}


def apply_process_defaults(environ: MutableMapping[str, str] | None = None) -> dict[str, str]:
    """Set :data:`PROCESS_DEFAULTS` in ``environ`` (default ``os.environ``, and so in the
    processes this one starts) where unset; returns what it set. Effective only before numpy
    is imported in this process (a warning says so otherwise)."""
    env = os.environ if environ is None else environ
    applied = {k: v for k, v in PROCESS_DEFAULTS.items() if k not in env}
    env.update(applied)
    if applied and environ is None and "numpy" in sys.modules:
        logging.getLogger(__name__).warning(
            "numpy was imported before the process defaults %s were set: its BLAS keeps its "
            "threads in this process (its children get them)", applied)
    return applied


def main(argv: Sequence[str] | None = None) -> int:
    apply_process_defaults()
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog="smartedge",
        description="Marker-less mobile robot localization from static smart edge cameras.",
    )
    parser.add_argument("--version", action="version", version=f"smartedge {__version__}")
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING, ERROR")
    parser.add_argument(
        "--log-format",
        choices=("text", "json"),
        default="text",
        help="log lines as text or as one JSON object per line",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    # an app command (every service) starts without looking for plug-in commands: reading the
    # installed packages' entry points costs ~0.14 s per start
    commands = dict(COMMANDS) if command_name(argv) in COMMANDS else all_commands()
    for name, command in commands.items():
        sub.add_parser(name, help=command.help, add_help=False)
    args, rest = parser.parse_known_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    _configure_logging(args.log_level, args.log_format)
    try:
        return run_command(f"smartedge {args.command}", commands[args.command], rest)
    except BrokenPipeError:
        # the reader went away (`smartedge evaluate ate ... | head`): no traceback; stdout is
        # pointed at /dev/null so that the interpreter's final flush does not fail again
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_BROKEN_PIPE


if __name__ == "__main__":
    raise SystemExit(main())
