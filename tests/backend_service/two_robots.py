"""Two identical robots on the paper's lab site, for the association tests.

The paper lab's site file with its one HSR replaced by two robots of the same model
(``hsr_a``, ``hsr_b``), built by :mod:`simulation.fleet`: each robot drives its own route
through the simulation (motion, drifting odometry, its own localization, the detection noise
model), the two runs share the cameras' capture phases, and every camera image's detections of
both robots are merged into one :class:`RobotDetections` message in random order with no robot
id, as the edge agent reports them. The truth of which robot each detection is stays with the
test (:attr:`TwoRobotRun.truth`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np

from core.site import Site
from protocol.messages import Message
from simulation.fleet import fleet_run, fleet_site, merged_messages
from simulation.runner import SimulationRun

ROBOTS = ("hsr_a", "hsr_b")


def two_robot_site() -> Site:
    """The paper lab with two HSRs of the same model (each in its own ROS namespace)."""
    return fleet_site(ROBOTS)


@dataclasses.dataclass(frozen=True, eq=False)
class TwoRobotRun:
    """``messages``: (arrival_ns, message) in arrival order; ``truth``: for a merged detections
    message (by ``id``), the true robot of each of its detections, in order; ``runs``: the
    simulation run of each robot (ground truth: ``runs[rid].ground_truth_at``)."""

    site: Site
    messages: list[tuple[int, Message]]
    truth: Mapping[int, tuple[str, ...]]
    runs: Mapping[str, SimulationRun]

    def true_pose(self, robot_id: str, stamp_ns: int) -> np.ndarray:
        return self.runs[robot_id].ground_truth_at(np.array([stamp_ns]))[0]


def two_robot_run(routes: Mapping[str, Sequence[tuple[float, float, float]]], until_s: float,
                  seed: int = 3, localization: Sequence[str] = ROBOTS) -> TwoRobotRun:
    """Both robots of :func:`two_robot_site` driving ``routes`` (robot id → waypoints
    (x m, y m, theta deg), world frame) for ``until_s`` simulated seconds. ``localization``: the
    robots whose own localization is published (at the robot bridge's rate)."""
    from robot_bridge.service import LOCALIZATION_PERIOD_NS

    fleet = fleet_run({rid: routes[rid] for rid in ROBOTS}, until_s=until_s, seed=seed,
                      site=two_robot_site())
    messages = merged_messages(fleet, 1e9 / LOCALIZATION_PERIOD_NS, localization)
    return TwoRobotRun(fleet.site, messages, fleet.truth, fleet.runs)
