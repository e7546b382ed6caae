"""The small interface between the bridge and one robot, and the data that crosses it.

An adapter speaks the robot's own language (a simulated robot object, ROS 2 topics over Zenoh,
...) and hands the bridge plain planar readings. It never blocks: ``read_*`` return what has
arrived since the last call (possibly nothing) and ``apply_correction`` returns at once. The
bridge core never imports an adapter; the service shell (or :func:`robot_bridge.bridge.pump`)
moves data between the two.
"""

from __future__ import annotations

import abc
import dataclasses
import math

import numpy as np

from protocol.messages import PoseCorrection


def _zero_cov() -> np.ndarray:
    return np.zeros((3, 3))


@dataclasses.dataclass(frozen=True, eq=False)
class OdometrySample:
    """One odometry reading of the robot base in its odometry frame.

    ``stamp_ns``: robot sensor clock, ns since the Unix epoch. ``x``, ``y`` (m) and ``theta``
    (rad) of the base in ``frame_id`` (usually ``odom``); ``vx``, ``vy`` (m/s) and ``wz``
    (rad/s) in the base frame. ``covariance``: (3, 3) of (x, y, theta), SI units.
    Not validated here: the bridge checks every field and counts what is wrong.
    """

    stamp_ns: int
    x: float
    y: float
    theta: float
    vx: float = 0.0
    vy: float = 0.0
    wz: float = 0.0
    covariance: np.ndarray = dataclasses.field(default_factory=_zero_cov)
    frame_id: str = "odom"


@dataclasses.dataclass(frozen=True, eq=False)
class LocalizationPose:
    """The robot's own estimate of its pose in the map (world) frame.

    ``x``, ``y`` (m), ``theta`` (rad) of the base in ``frame_id`` (``map``); ``stamp_ns`` the
    time it refers to. ``lost``: the robot's localizer says it does not know where it is (or
    has never been initialized); the pose is then meaningless and the bridge treats the robot
    as kidnapped. ``covariance``: (3, 3) of (x, y, theta) or ``None`` when not reported.
    """

    stamp_ns: int
    x: float
    y: float
    theta: float
    lost: bool = False
    covariance: np.ndarray | None = None
    frame_id: str = "map"

    @property
    def is_finite(self) -> bool:
        return all(
            isinstance(v, (int, float)) and math.isfinite(v) for v in (self.x, self.y, self.theta)
        )


class RobotAdapter(abc.ABC):
    """What the bridge needs from a robot. Implementations must never block and never raise
    on bad data from the robot (they drop and count it in :attr:`counters`)."""

    #: short name for logs and status (``sim``, ``ros2``...)
    name: str = "robot"

    def __init__(self) -> None:
        self.counters: dict[str, int] = {}

    def _count(self, what: str, n: int = 1) -> None:
        self.counters[what] = self.counters.get(what, 0) + n

    @abc.abstractmethod
    def read_odometry(self) -> list[OdometrySample]:
        """Odometry readings received since the last call, oldest first (maybe empty)."""

    @abc.abstractmethod
    def read_localization(self) -> LocalizationPose | None:
        """The latest localization pose of the robot in the map frame, or ``None`` when the
        robot has reported none (yet)."""

    @abc.abstractmethod
    def apply_correction(self, correction: PoseCorrection) -> bool:
        """Hand a pose correction / initial pose to the robot's localization. ``True`` when it
        was sent (or accepted, for robots that can say so), ``False`` when it was refused."""

    def close(self) -> None:  # noqa: B027 (optional hook, default does nothing)
        """Release transport resources; idempotent."""
