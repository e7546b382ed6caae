"""Adapter for the simulated robot of :mod:`simulation` (drifting odometry and localization,
accepts corrections only while static).

The adapter is written against the small structural interface :class:`SimulatedRobotPort`, so
it does not import :mod:`simulation` itself: any object with these three methods works.

* ``read_odometry()`` → readings since the last call, oldest first; each has ``stamp_ns``,
  ``x``, ``y``, ``theta`` (odom frame) and ``vx``, ``vy``, ``wz`` (body frame), optionally
  ``covariance`` (3, 3) and ``frame_id``.
* ``localization()`` → the robot's own map-frame pose (``stamp_ns``, ``x``, ``y``, ``theta``,
  optionally ``lost``, ``covariance``) or ``None`` while the robot is not localized
  (kidnapped).
* ``apply_correction(stamp_ns, x, y, theta)`` → ``True`` when the robot set its localization
  to that map-frame pose, ``False`` when it refused (it moves, or the pose is invalid).
"""

from __future__ import annotations

import logging
import math
from typing import Any, Protocol, runtime_checkable

import numpy as np

from protocol.messages import PoseCorrection
from robot_bridge.adapters.base import LocalizationPose, OdometrySample, RobotAdapter

log = logging.getLogger(__name__)


@runtime_checkable
class SimulatedRobotPort(Protocol):
    """What :class:`SimRobotAdapter` needs from a simulated robot (module docstring)."""

    def read_odometry(self) -> Any: ...

    def localization(self) -> Any: ...

    def apply_correction(self, stamp_ns: int, x: float, y: float, theta: float) -> bool: ...


def _odometry_sample(reading: Any) -> OdometrySample:
    cov = getattr(reading, "covariance", None)
    return OdometrySample(
        stamp_ns=reading.stamp_ns,
        x=reading.x,
        y=reading.y,
        theta=reading.theta,
        vx=getattr(reading, "vx", 0.0),
        vy=getattr(reading, "vy", 0.0),
        wz=getattr(reading, "wz", 0.0),
        covariance=np.zeros((3, 3)) if cov is None else np.asarray(cov, dtype=np.float64),
        frame_id=getattr(reading, "frame_id", "odom"),
    )


class SimRobotAdapter(RobotAdapter):
    """:class:`RobotAdapter` over a :class:`SimulatedRobotPort` object (in-process)."""

    name = "sim"

    def __init__(self, robot: SimulatedRobotPort) -> None:
        super().__init__()
        missing = [m for m in ("read_odometry", "localization", "apply_correction")
                   if not callable(getattr(robot, m, None))]
        if missing:
            raise TypeError(f"{type(robot).__name__} lacks {missing} (see SimulatedRobotPort)")
        self.robot = robot

    def read_odometry(self) -> list[OdometrySample]:
        out = []
        for reading in self.robot.read_odometry() or ():
            try:
                out.append(_odometry_sample(reading))
            except (AttributeError, TypeError, ValueError) as exc:
                self._count("invalid_odometry")
                log.debug("dropped simulated odometry: %s", exc)
        return out

    def read_localization(self) -> LocalizationPose | None:
        pose = self.robot.localization()
        if pose is None:
            return None
        try:
            cov = getattr(pose, "covariance", None)
            return LocalizationPose(
                stamp_ns=int(pose.stamp_ns),
                x=float(pose.x),
                y=float(pose.y),
                theta=float(pose.theta),
                lost=bool(getattr(pose, "lost", False)),
                covariance=None if cov is None else np.asarray(cov, dtype=np.float64),
                frame_id=getattr(pose, "frame_id", "map"),
            )
        except (AttributeError, TypeError, ValueError) as exc:
            self._count("invalid_localization")
            log.debug("dropped simulated localization: %s", exc)
            return None

    def apply_correction(self, correction: PoseCorrection) -> bool:
        if not all(math.isfinite(v) for v in (correction.x, correction.y, correction.theta)):
            return False
        accepted = bool(
            self.robot.apply_correction(
                correction.stamp_ns, correction.x, correction.y, correction.theta
            )
        )
        self._count("corrections_accepted" if accepted else "corrections_refused")
        return accepted
