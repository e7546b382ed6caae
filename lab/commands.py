"""The lab's commands, added to ``smartedge`` through the ``smartedge.commands`` entry point
(pyproject.toml; :data:`smartedge.cli.COMMAND_ENTRY_POINTS`): the app lists them without
importing the lab, and an installation without the lab's extras still runs the services."""

from __future__ import annotations

from typing import Final

from smartedge.commands import Command

#: command name → :class:`~smartedge.commands.Command` (module, function, one-line help)
COMMANDS: Final[dict[str, Command]] = {
    "demo": Command("lab.demo", "main", "run the whole system on the simulated paper site"),
    "evaluate": Command("lab.evaluate", "main", "trajectory metrics and the paper's experiments"),
    "bench": Command("lab.bench", "main",
                     "benchmarks (codec, pose, fusion, backend, map, ...) and the fault harness "
                     "(reliability)"),
    "render": Command("lab.render", "main", "rendered camera images with exact labels"),
    "train": Command("lab.train", "main", "train the detector / keypoint CNN on renders"),
    "sim-head": Command("lab.simulated_head", "main",
                        "the simulated robot's panning head as ROS 2 topics: /tf, /tf_static, "
                        "RGB-D images, camera info"),
}
