"""The small interface between the bridge and one robot, and the data that crosses it.

An adapter speaks the robot's own language (a simulated robot object, ROS 2 topics over Zenoh,
...) and hands the bridge plain planar readings. It never blocks: ``read_*`` return what has
arrived since the last call (possibly nothing) and ``apply_correction`` returns at once. The
bridge core never imports an adapter; the service shell (or :func:`robot_bridge.bridge.pump`)
moves data between the two. :class:`AdapterSetup` is what an ``--adapter`` plug-in builds
(:mod:`robot_bridge.adapters.registry`).
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from core.pose import PlanarPose
from protocol.messages import PoseCorrection, PoseEstimate

if TYPE_CHECKING:
    from core.site import Site


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
    def pose(self) -> PlanarPose:
        """The pose as the one planar pose type."""
        return PlanarPose(self.x, self.y, self.theta)

    @property
    def is_finite(self) -> bool:
        return all(
            isinstance(v, (int, float)) and math.isfinite(v) for v in (self.x, self.y, self.theta)
        )


@dataclasses.dataclass(frozen=True, eq=False)
class MapToOdom:
    """The transform from the world (map) frame to the robot's odometry frame, as a
    localization stack publishes it on ``/tf``: the pose of ``child_frame`` (``odom``) in
    ``parent_frame`` (the site's world frame), planar: ``x``, ``y`` (m), ``theta`` (rad).

    ``stamp_ns``: the time it is valid from (the estimate's time plus the configured
    ``transform_tolerance_s``, as AMCL does, so ``map -> base_link`` lookups at "now" succeed).
    """

    stamp_ns: int
    x: float
    y: float
    theta: float
    parent_frame: str = "map"
    child_frame: str = "odom"

    @property
    def pose(self) -> PlanarPose:
        """``odom`` in the parent frame as the one planar pose type."""
        return PlanarPose(self.x, self.y, self.theta)


class MapMessages(Protocol):
    """The semantic map as ROS messages (:class:`robot_bridge.map_output.MapSnapshot`): the
    ``sensor_msgs/PointCloud2`` and ``nav_msgs/OccupancyGrid`` wire bytes, CDR or ROS 1
    (``ros1``); ``None`` for an output that is off. They raise ``ValueError`` (a
    ``RosConversionError``) when the map cannot be encoded."""

    def cloud_payload(self, *, ros1: bool = False, seq: int = 0) -> bytes | None: ...

    def grid_payload(self, *, ros1: bool = False, seq: int = 0) -> bytes | None: ...


#: the pose-output streams: the fused estimate and the camera-only one
POSE_STREAMS: tuple[str, ...] = ("fused", "cameras")


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

    def publish_pose(self, estimate: PoseEstimate, stream: str = "fused") -> bool:
        """Publish a backend estimate as the robot's continuous pose input (a
        ``PoseWithCovarianceStamped`` topic robot_localization can fuse). ``stream`` is one of
        :data:`POSE_STREAMS`. ``True`` when it went out; the default (an adapter with no pose
        output) says ``False`` and the bridge counts ``pose_output_<stream>_failed``."""
        return False

    def publish_transform(self, transform: MapToOdom) -> bool:
        """Publish the map -> odom transform (``/tf``); ``False`` when the adapter cannot."""
        return False

    def publish_map(self, messages: MapMessages) -> bool:
        """Publish the semantic map as ROS messages (cloud and obstacle grid); ``True`` when
        what is on went out. The default (an adapter without ROS topics) says ``False`` and the
        bridge counts ``map_output_failed``."""
        return False

    def close(self) -> None:  # noqa: B027 (optional hook, default does nothing)
        """Release transport resources; idempotent."""


@dataclasses.dataclass(frozen=True)
class AdapterSetup:
    """What an adapter plug-in builds for one bridge.

    ``factory(session)`` builds the adapter once the Zenoh session is open (the ROS adapters
    are Zenoh clients themselves). ``advance(now_ns)``: called before every pump with the wall
    clock (ns), for a robot simulated in the bridge's process; ``None`` for a real robot.
    ``site`` and ``robot_id``: what the adapter brings along (the simulated site and its
    robot), used when ``--site`` / ``--robot`` are not given.
    """

    factory: Callable[[Any], RobotAdapter]
    advance: Callable[[int], None] | None = None
    site: Site | None = None
    robot_id: str | None = None
