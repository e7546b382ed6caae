"""Lazy subcommands: a command's module is imported only when the command runs.

``smartedge <command>`` (:data:`smartedge.cli.COMMANDS`) and ``smartedge bench <what>``
(:data:`lab.bench.BENCHES`) are tables of :class:`Command`; :func:`run_command` imports
the module, calls its function with the remaining arguments and turns a missing module or a
missing optional dependency into a one-line error, so an edge board (``smartedge[edge]``) can
run ``smartedge edge-agent`` without the backend's dependencies installed.

The operator's commands, one module per command:

- ``calibrate``: ``smartedge calibrate <verb>``; ``calibrate_board``: its ``board``,
  ``intrinsics`` and ``extrinsics``; ``calibrate_robot``: its ``robot`` (every camera's pose
  from a drive of the robot);
- ``certs``: ``smartedge certs``: the site's certificates and its router config with access
  control;
- ``router``: ``smartedge router``: the site's Zenoh router;
- ``site``: ``smartedge site check | calib | reference``;
- ``status``: ``smartedge status`` and ``smartedge echo``: what is live on the network;
- ``record``: ``smartedge record`` / ``smartedge replay``: the traffic into MCAP and back;
- ``export``: ``smartedge export``: data out of a recording (TUM trajectories);
- ``map``: ``smartedge map``: the semantic map files the mapper keeps;
- ``dataset``: ``smartedge dataset``: labelled camera frames in COCO keypoints files.

Part of the app wing (:mod:`smartedge`): never imports the lab.
"""

from __future__ import annotations

import importlib
import signal
import sys
import threading
from collections.abc import Sequence
from typing import Final, NamedTuple

#: exit status of a command that cannot run here (module or dependency missing)
EXIT_UNAVAILABLE: Final = 2


class Command(NamedTuple):
    """One subcommand: ``function`` of ``module`` takes the remaining argv and returns an exit
    code (``None`` counts as 0); ``help`` is its one-line description."""

    module: str
    function: str
    help: str


def run_command(prog: str, command: Command, argv: Sequence[str]) -> int:
    """Import ``command.module`` and run its function on ``argv``; ``prog`` (e.g. ``smartedge
    bench map``) names the command in the error printed when its module is not in this version
    or an optional dependency it imports is not installed (exit :data:`EXIT_UNAVAILABLE`)."""
    try:
        module = importlib.import_module(command.module)
    except ModuleNotFoundError as exc:
        if exc.name == command.module:
            print(f"{prog}: not available in this version", file=sys.stderr)
            return EXIT_UNAVAILABLE
        print(
            f"{prog}: missing dependency {exc.name!r}; install the extra that provides it "
            "(e.g. pip install 'smartedge[backend]')",
            file=sys.stderr,
        )
        return EXIT_UNAVAILABLE
    unwind_on_sigterm()
    return int(getattr(module, command.function)(list(argv)) or 0)


def _raise_exit(signum: int, _frame: object) -> None:
    raise SystemExit(128 + signum)


def unwind_on_sigterm() -> None:
    """Turn SIGTERM and SIGHUP into ``SystemExit`` (exit 128 + the signal) where they would
    kill the process outright, so a command stopped by a supervisor, ``kill`` or a closed
    terminal runs its ``finally`` blocks: a benchmark or the demo then stops the routers and
    services it started instead of leaving them running. Services install their own handlers
    afterwards (a clean stop); only in the main thread, and only over the default action."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(sig) is signal.SIG_DFL:
            signal.signal(sig, _raise_exit)


__all__ = ["EXIT_UNAVAILABLE", "Command", "run_command", "unwind_on_sigterm"]
