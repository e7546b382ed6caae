"""Lazy subcommands: a command's module is imported only when the command runs.

``smartedge <command>`` (:data:`smartedge.cli.COMMANDS`) and ``smartedge bench <what>``
(:data:`smartedge.bench.BENCHES`) are tables of :class:`Command`; :func:`run_command` imports
the module, calls its function with the remaining arguments and turns a missing module or a
missing optional dependency into a one-line error, so an edge board (``smartedge[edge]``) can
run ``smartedge edge-agent`` without the backend's dependencies installed.
"""

from __future__ import annotations

import importlib
import sys
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
    return int(getattr(module, command.function)(list(argv)) or 0)


__all__ = ["EXIT_UNAVAILABLE", "Command", "run_command"]
