"""Adapter for the simulated robot of :mod:`simulation.robot` (drifting odometry and
localization, accepts corrections only while static).

Written against the structural interface :class:`SimulatedRobotPort`, which
:class:`simulation.robot.SimulatedRobot` satisfies, so this module does not import
:mod:`simulation`:

* ``step_to(t_s)`` → the :class:`protocol.Odometry` messages of the ticks up to ``t_s``
  (s since the run start);
* ``localization_pose()`` → (3,) the robot's own map-frame pose (x, y, theta) now;
* ``apply_correction(pose, stamp_ns)`` → ``True`` when the robot set its localization to
  ``pose`` (it refuses while moving);
* ``stamp_ns(t_s)`` and ``t_s``: the common clock.

Who advances simulated time: either the adapter (:meth:`SimRobotAdapter.advance_to`) or a
runner that steps the robot itself and hands the odometry over with :meth:`~SimRobotAdapter.feed`.

``localized=False`` plays the kidnapped robot: its localizer reports nothing until the first
pose pushed to it is accepted.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Any, Protocol, runtime_checkable

import numpy as np

from protocol.messages import Odometry, PoseCorrection, PoseEstimate
from robot_bridge.adapters.base import (
    LocalizationPose,
    MapToOdom,
    OdometrySample,
    RobotAdapter,
)

log = logging.getLogger(__name__)


@runtime_checkable
class SimulatedRobotPort(Protocol):
    """What :class:`SimRobotAdapter` needs from a simulated robot (module docstring)."""

    @property
    def t_s(self) -> float: ...

    def stamp_ns(self, t_s: float) -> int: ...

    def step_to(self, t_s: float) -> list[Odometry]: ...

    def localization_pose(self) -> np.ndarray: ...

    def apply_correction(self, pose: Any, stamp_ns: int) -> bool: ...


def sample_from_odometry(msg: Odometry) -> OdometrySample:
    """A protocol :class:`Odometry` message as the bridge's :class:`OdometrySample`."""
    return OdometrySample(
        stamp_ns=msg.stamp_ns, x=msg.x, y=msg.y, theta=msg.theta, vx=msg.vx, vy=msg.vy,
        wz=msg.wz, covariance=np.array(msg.covariance), frame_id=msg.frame_id,
    )


class SimRobotAdapter(RobotAdapter):
    """:class:`RobotAdapter` over a simulated robot in the same process."""

    name = "sim"

    def __init__(self, robot: SimulatedRobotPort, *, localized: bool = True) -> None:
        super().__init__()
        missing = [m for m in ("step_to", "localization_pose", "apply_correction", "stamp_ns")
                   if not callable(getattr(robot, m, None))]
        if missing:
            raise TypeError(f"{type(robot).__name__} lacks {missing} (see SimulatedRobotPort)")
        self.robot = robot
        self.localized = localized
        self._pending: list[OdometrySample] = []
        #: the newest pose output per stream and transform (the simulated robot has no
        #: robot_localization to feed; kept for inspection and tests)
        self.published_poses: dict[str, PoseEstimate] = {}
        self.published_transform: MapToOdom | None = None

    def advance_to(self, t_s: float) -> list[Odometry]:
        """Step the robot to ``t_s`` (s since the run start); its odometry is queued for
        :meth:`read_odometry` and also returned (for logging / ground truth bookkeeping)."""
        msgs = list(self.robot.step_to(t_s))
        self.feed(msgs)
        return msgs

    def feed(self, odometry: Iterable[Odometry]) -> None:
        """Queue odometry messages produced by whoever steps the robot."""
        for msg in odometry:
            if isinstance(msg, Odometry):
                self._pending.append(sample_from_odometry(msg))
            else:
                self._count("invalid_odometry")

    def read_odometry(self) -> list[OdometrySample]:
        out, self._pending = self._pending, []
        return out

    def read_localization(self) -> LocalizationPose | None:
        if not self.localized:
            return None
        pose = np.asarray(self.robot.localization_pose(), dtype=np.float64).reshape(3)
        return LocalizationPose(
            stamp_ns=int(self.robot.stamp_ns(self.robot.t_s)),
            x=float(pose[0]), y=float(pose[1]), theta=float(pose[2]),
        )

    def apply_correction(self, correction: PoseCorrection) -> bool:
        pose = np.array([correction.x, correction.y, correction.theta])
        accepted = bool(self.robot.apply_correction(pose, correction.stamp_ns))
        if accepted:
            self.localized = True
        self._count("corrections_accepted" if accepted else "corrections_refused")
        return accepted

    def publish_pose(self, estimate: PoseEstimate, stream: str = "fused") -> bool:
        self.published_poses[stream] = estimate
        self._count(f"pose_{stream}_published")
        return True

    def publish_transform(self, transform: MapToOdom) -> bool:
        self.published_transform = transform
        self._count("tf_published")
        return True
