"""``smartedge calibrate <verb>``: print a board, intrinsics from board views, extrinsics from
board sightings, and every camera's pose in the robot's map frame from a drive of the robot."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Final

from smartedge.commands import Command, run_command

#: verb → the module and function that run it (imported only when the verb runs)
VERBS: Final[dict[str, Command]] = {
    "board": Command("smartedge.commands.calibrate_board", "board_main",
                     "print a ChArUco board (PNG or PDF) and write its spec beside it"),
    "intrinsics": Command("smartedge.commands.calibrate_board", "intrinsics_main",
                          "one camera's intrinsics from ChArUco board views -> camera_info YAML"),
    "extrinsics": Command("smartedge.commands.calibrate_board", "extrinsics_main",
                          "every camera's pose from board sightings, solved jointly -> cameras:"),
    "robot": Command("smartedge.commands.calibrate_robot", "main",
                     "every camera's pose in the robot's map frame from a drive of the robot "
                     "(live or from a recording) -> updated site file"),
}


def usage() -> str:
    width = max(len(v) for v in VERBS)
    lines = ["usage: smartedge calibrate <verb> [options]", "", "verbs:"]
    lines += [f"  {name:<{width}}  {cmd.help}" for name, cmd in VERBS.items()]
    lines += ["", "smartedge calibrate <verb> --help shows a verb's options; "
              "docs/calibration.md walks through the whole flow."]
    return "\n".join(lines)


def main(argv: Sequence[str]) -> int:
    args = list(argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage())
        return 0 if args else 2
    verb = VERBS.get(args[0])
    if verb is None:
        print(f"smartedge calibrate: unknown verb {args[0]!r}\n\n{usage()}", file=sys.stderr)
        return 2
    return run_command(f"smartedge calibrate {args[0]}", verb, args[1:])
