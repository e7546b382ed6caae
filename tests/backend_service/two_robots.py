"""Two identical robots on the paper's lab site, for the association tests.

The paper lab's site file with its one HSR replaced by two robots of the same model
(``hsr_a``, ``hsr_b``); each robot drives its own route through the simulation (motion,
drifting odometry, its own localization, the detection noise model), the two runs share the
cameras' capture phases, and every camera image's detections of both robots are merged into one
:class:`RobotDetections` message in random order with no robot id, as the edge agent reports
them. The truth of which robot each detection is stays with the test
(:attr:`TwoRobotRun.truth`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np
import yaml

from protocol.messages import Message, RobotDetections
from protocol.site import Site, parse_site
from simulation.runner import SimulationRun
from simulation.scenario import SITES_DIR, Scenario, Waypoint, load_scenario

ROBOTS = ("hsr_a", "hsr_b")


def two_robot_site() -> Site:
    """The paper lab with two HSRs of the same model."""
    path = SITES_DIR / "paper_lab.yaml"
    doc = yaml.safe_load(path.read_text())
    doc["robots"] = [{"id": rid, "model": "hsr"} for rid in ROBOTS]
    return parse_site(doc, str(path), path.parent)


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


def _scenario(base: Scenario, site: Site, robot_id: str, route: Sequence[Waypoint]
              ) -> Scenario:
    waypoints = {w.name: w for w in route}
    return base.with_overrides(site=site, robot_id=robot_id,
                               route_waypoints={**base.route_waypoints, **waypoints},
                               routes={**base.routes, "route": tuple(waypoints)})


def two_robot_run(routes: Mapping[str, Sequence[tuple[float, float, float]]], until_s: float,
                  seed: int = 3, localization: Sequence[str] = ROBOTS) -> TwoRobotRun:
    """Both robots of :func:`two_robot_site` driving ``routes`` (robot id → waypoints
    (x m, y m, theta deg), world frame) for ``until_s`` simulated seconds. ``localization``: the
    robots whose own localization is published (at the robot bridge's rate)."""
    from robot_bridge.service import LOCALIZATION_PERIOD_NS

    site = two_robot_site()
    base = load_scenario()
    runs: dict[str, SimulationRun] = {}
    for k, rid in enumerate(ROBOTS):
        route = [Waypoint(f"{rid}_{i}", x, y, math.radians(t))
                 for i, (x, y, t) in enumerate(routes[rid])]
        runs[rid] = SimulationRun(_scenario(base, site, rid, route), "route",
                                  seed=np.random.SeedSequence([seed, k]))
    first = runs[ROBOTS[0]]
    for rid in ROBOTS[1:]:
        runs[rid].camera_phase_s = dict(first.camera_phase_s)  # one camera, one capture time
    rate = 1e9 / LOCALIZATION_PERIOD_NS
    others: list[tuple[int, Message]] = []
    frames: dict[tuple[str, int], list[tuple[int, RobotDetections, str]]] = {}
    for rid, run in runs.items():
        for tm in run.messages(until_s=until_s,
                               localization_rate_hz=rate if rid in localization else None):
            msg = tm.message
            if isinstance(msg, RobotDetections):
                frames.setdefault((msg.camera_id, msg.stamp_ns), []).append(
                    (tm.arrival_ns, msg, rid))
            else:
                others.append((tm.arrival_ns, msg))
    rng = np.random.default_rng(seed)
    merged: list[tuple[int, Message]] = []
    truth: dict[int, tuple[str, ...]] = {}
    for (_cam, _stamp), parts in frames.items():
        dets = [(d, rid) for _, m, rid in parts for d in m.detections]
        order = rng.permutation(len(dets))
        msg = dataclasses.replace(parts[0][1], detections=tuple(
            dataclasses.replace(dets[i][0], robot_id="") for i in order))
        truth[id(msg)] = tuple(dets[i][1] for i in order)
        merged.append((max(a for a, _, _ in parts), msg))
    stream = sorted(others + merged, key=lambda am: am[0])
    return TwoRobotRun(site, stream, truth, runs)
