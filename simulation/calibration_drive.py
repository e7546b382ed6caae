"""A simulated calibration drive: the robot drives a route of the scenario for a while, the
edge cameras' noise-model detections, the robot's odometry and its own localization come out as
wire messages on their keys, in arrival order, on simulated time (what ``smartedge record``
would capture on the bus), for ``smartedge calibrate robot`` and its tests and evaluation.

Also: a site's camera poses perturbed deterministically by given magnitudes (every camera moved
by exactly ``translation_m`` in a random direction and turned by exactly ``rotation_deg`` about
a random axis), the start of the robot-target calibration's evaluation.

:func:`record_drive` hands them to a writer: the top floor passes
``smartedge.commands.record.Recorder``'s.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from core.geometry import rotation_from_rotvec
from core.site import Site
from protocol import keys
from protocol.codec import encode
from protocol.messages import Odometry, PoseEstimate, RobotDetections
from simulation.runner import SimulationRun
from simulation.scenario import Scenario

#: the robot's localization rate on the bus (as the robot bridge publishes it)
LOCALIZATION_RATE_HZ = 10.0


@dataclasses.dataclass(frozen=True)
class DriveMessage:
    """One message of the drive as the bus carries it: key, arrival (common clock, ns),
    encoded payload."""

    key: str
    arrival_ns: int
    payload: bytes


@dataclasses.dataclass
class DriveSummary:
    """What a drive produced: message counts per kind and per camera (detections with the
    robot in them), the simulated duration."""

    duration_s: float = 0.0
    messages: int = 0
    odometry: int = 0
    localization: int = 0
    detections: dict[str, int] = dataclasses.field(default_factory=dict)
    sightings: dict[str, int] = dataclasses.field(default_factory=dict)


def drive_messages(scenario: Scenario, route: str = "traj3x3", *, duration_s: float = 300.0,
                   seed: int = 0, reverse: bool = False, cameras: Iterable[str] | None = None,
                   localization_rate_hz: float = LOCALIZATION_RATE_HZ,
                   summary: DriveSummary | None = None) -> Iterator[DriveMessage]:
    """The drive's messages in arrival order: ``route`` (a trajectory or route of the
    scenario) for at most ``duration_s`` of simulated time. ``cameras``: keep only these
    cameras' detections (default: all), e.g. to make one camera see the robot rarely.
    ``summary`` is filled in as the messages go."""
    run = SimulationRun(scenario, route, reverse=reverse, seed=seed)
    site = scenario.site.name
    robot = scenario.robot_id
    keep = None if cameras is None else set(cameras)
    s = summary if summary is not None else DriveSummary()
    s.duration_s = min(duration_s, run.duration_s)
    for tm in run.messages(until_s=duration_s, localization_rate_hz=localization_rate_hz):
        msg = tm.message
        if isinstance(msg, RobotDetections):
            if keep is not None and msg.camera_id not in keep:
                continue
            key = keys.detections_key(site, msg.camera_id)
            s.detections[msg.camera_id] = s.detections.get(msg.camera_id, 0) + 1
            if msg.detections:
                s.sightings[msg.camera_id] = s.sightings.get(msg.camera_id, 0) + 1
        elif isinstance(msg, Odometry):
            key = keys.odom_key(site, robot)
            s.odometry += 1
        elif isinstance(msg, PoseEstimate):
            key = keys.localization_key(site, robot)
            s.localization += 1
        else:  # pragma: no cover - the runner yields only these
            continue
        s.messages += 1
        yield DriveMessage(key, tm.arrival_ns, encode(msg))


def perturbed_camera_poses(site: Site, translation_m: float, rotation_deg: float,
                           seed: int = 0) -> dict[str, np.ndarray]:
    """``T_world_cam`` (4, 4) of every camera of ``site``, moved by exactly ``translation_m``
    along a random direction and rotated by exactly ``rotation_deg`` about a random axis
    through its optical centre (one generator seeded by ``seed``, cameras in id order)."""
    rng = np.random.default_rng(seed)
    out: dict[str, np.ndarray] = {}
    for cam_id in sorted(site.cameras):
        T = site.cameras[cam_id].T_world_cam.copy()
        d = rng.normal(size=3)
        axis = rng.normal(size=3)
        d /= np.linalg.norm(d)
        axis /= np.linalg.norm(axis)
        T[:3, :3] = rotation_from_rotvec(axis * math.radians(rotation_deg)) @ T[:3, :3]
        T[:3, 3] += translation_m * d
        out[cam_id] = T
    return out


def record_drive(write: Callable[[str, bytes, int], None], scenario: Scenario,
                 route: str = "traj3x3", **options: Any) -> DriveSummary:
    """Hand every message of :func:`drive_messages` (same options) to ``write(key, payload,
    receive_ns)``, e.g. ``smartedge.commands.record.Recorder(path).write`` to get the MCAP recording
    ``smartedge record`` would have made of the drive. Returns the summary."""
    summary = DriveSummary()
    for m in drive_messages(scenario, route, summary=summary, **options):
        write(m.key, m.payload, m.arrival_ns)
    return summary
