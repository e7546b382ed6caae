"""The one planar pose type: (x, y, theta) of a robot base in a frame (REP-103 axes: x
forward, y left, theta counter-clockwise from x), metres and radians. The backend's solver and
estimates, the evaluation, the benches and the examples all use :class:`PlanarPose`; stamped
trajectories are :class:`core.trajectory.Trajectory`."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from core.geometry import se3_from_planar, wrap_angle


@dataclasses.dataclass(frozen=True)
class PlanarPose:
    """A planar pose (x, y in metres, theta in radians) of the robot base in some frame."""

    x: float
    y: float
    theta: float

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.theta])

    def T(self) -> np.ndarray:
        """(4, 4) homogeneous transform of this pose (robot base → frame), z = 0."""
        return se3_from_planar(self.x, self.y, self.theta)

    @classmethod
    def of(cls, obj: object) -> PlanarPose:
        """The planar pose of anything with ``x``, ``y``, ``theta`` (a
        :class:`~protocol.messages.PoseEstimate`, a correction, a robot's localization)."""
        return cls(float(obj.x), float(obj.y), float(obj.theta))  # type: ignore[attr-defined]

    @classmethod
    def from_array(cls, xytheta: np.ndarray | Sequence[float]) -> PlanarPose:
        """From (3,) (x, y, theta)."""
        x, y, theta = (float(v) for v in np.asarray(xytheta, dtype=np.float64).reshape(3))
        return cls(x, y, theta)

    def is_finite(self) -> bool:
        return all(math.isfinite(v) for v in (self.x, self.y, self.theta))

    def distance_to(self, other: PlanarPose) -> tuple[float, float]:
        """(translation m, |heading difference| rad, wrapped) from ``other`` to this pose."""
        return (math.hypot(self.x - other.x, self.y - other.y),
                abs(wrap_angle(self.theta - other.theta)))
