"""Multi-frame averaging of camera pose estimates while the robot is static (the paper's
"Cameras (5 frames)" row in Table I).

:class:`MultiFrameAverager` keeps the last ``k`` successful results. A result that jumps away
from the current window (more than ``max_jump_m`` / ``max_jump_rad`` from its mean) or comes
after a gap longer than ``max_gap_s`` means the robot moved: the window restarts with it. Once
``k`` results agree it returns their average (mean position, circular-mean yaw, covariance of
the mean) flagged ``multi_frame``; after that every new agreeing result returns the average of
the last ``k``. Callers that know the robot moved (odometry) call :meth:`reset`. The average's
covariance keeps the estimates' systematic part (camera calibration, a shared prior) whole and
shrinks their per-frame part only as far as consecutive frames are independent
(``frame_correlation``).
"""

from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np

from backend_service.covariance import CovarianceParts
from backend_service.estimate import PoseResult
from backend_service.pose_init import circular_mean
from core.geometry import angle_diff
from core.pose import PlanarPose


@dataclasses.dataclass(frozen=True)
class MultiFrameConfig:
    """Averaging while static: ``count`` estimates (the paper's 5 frames); an estimate more than
    ``max_jump_m`` / ``max_jump_deg`` from the window's mean, or after a gap over ``max_gap_s``,
    restarts the window. ``once_per_stop``: one average per stop (the paper's "sparsely at
    waypoints"); further averages of the same stop see the same robot from the same cameras,
    so their errors are not independent and fusing each would make the pose graph
    overconfident. ``frame_correlation``: how alike the per-frame errors of consecutive frames
    of a static robot are, 0 (independent draws) to 1 (the same error every frame: a
    deterministic detector on a still image sees the same pixels). The average's covariance is
    the frames' systematic part plus their per-frame part times
    ``frame_correlation + (1 - frame_correlation) / count``; 1 (the default) claims nothing
    from averaging, which is what the shipped CNN measures (docs/pose_estimation.md)."""

    count: int = 5
    max_jump_m: float = 0.15
    max_jump_deg: float = 5.0
    max_gap_s: float = 5.0
    once_per_stop: bool = True
    frame_correlation: float = 1.0

    def __post_init__(self) -> None:
        if not (isinstance(self.count, int) and self.count >= 1):
            raise ValueError(f"MultiFrameConfig.count must be an integer >= 1, got {self.count!r}")
        for name in ("max_jump_m", "max_jump_deg", "max_gap_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"MultiFrameConfig.{name} must be > 0, got {value!r}")
        if not (math.isfinite(self.frame_correlation) and 0.0 <= self.frame_correlation <= 1.0):
            raise ValueError("MultiFrameConfig.frame_correlation must be within [0, 1], got "
                             f"{self.frame_correlation!r}")


class MultiFrameAverager:
    """Average the last ``k`` camera estimates of one robot while it is static."""

    @classmethod
    def from_config(cls, config: MultiFrameConfig) -> MultiFrameAverager:
        return cls(config.count, config.max_jump_m, math.radians(config.max_jump_deg),
                   config.max_gap_s, config.frame_correlation)

    def __init__(self, k: int, max_jump_m: float = 0.15, max_jump_rad: float = math.radians(5.0),
                 max_gap_s: float = 5.0, frame_correlation: float = 1.0) -> None:
        if k < 1:
            raise ValueError("k must be >= 1")
        self.frame_correlation = float(frame_correlation)
        self.k = int(k)
        self.max_jump_m = float(max_jump_m)
        self.max_jump_rad = float(max_jump_rad)
        self.max_gap_ns = int(max_gap_s * 1e9)
        self._window: collections.deque[PoseResult] = collections.deque(maxlen=self.k)

    def reset(self) -> None:
        """Forget the window (the robot moved)."""
        self._window.clear()

    def __len__(self) -> int:
        return len(self._window)

    def _mean_pose(self) -> PlanarPose:
        poses = [r.pose for r in self._window if r.pose is not None]
        return PlanarPose(float(np.mean([p.x for p in poses])),
                          float(np.mean([p.y for p in poses])),
                          circular_mean(np.array([p.theta for p in poses])))

    def add(self, result: PoseResult) -> PoseResult | None:
        """Add one frame-set's result; the average of the last ``k`` when that many agree,
        else ``None``. Results without an estimate are ignored (they neither count nor reset)."""
        if not result.ok or result.pose is None or result.estimate is None:
            return None
        if self._window:
            last = self._window[-1].estimate
            mean = self._mean_pose()
            jump = math.hypot(result.pose.x - mean.x, result.pose.y - mean.y)
            turn = abs(angle_diff(result.pose.theta, mean.theta))
            gap = result.estimate.stamp_ns - last.stamp_ns  # type: ignore[union-attr]
            if (jump > self.max_jump_m or turn > self.max_jump_rad or gap > self.max_gap_ns
                    or gap < 0):
                self._window.clear()
        self._window.append(result)
        if len(self._window) < self.k:
            return None
        return self._average()

    def _average(self) -> PoseResult:
        items = list(self._window)
        mean = self._mean_pose()
        newest = items[-1].estimate
        assert newest is not None
        covs = np.stack([r.estimate.covariance for r in items])  # type: ignore[union-attr]
        systematic = np.stack([r.covariance_parts.systematic if r.covariance_parts is not None
                               else np.zeros((3, 3)) for r in items]).mean(axis=0)
        per_frame = covs.mean(axis=0) - systematic
        # the per-frame part averages down only as far as the frames' errors are independent
        rho = self.frame_correlation
        shrink = rho + (1.0 - rho) / len(items)
        cov = systematic + per_frame * shrink
        rmse = float(np.sqrt(np.mean([r.estimate.reprojection_rmse_px**2  # type: ignore[union-attr]
                                      for r in items])))
        cams = tuple(sorted({c for r in items for c in r.estimate.camera_ids}))  # type: ignore[union-attr]
        flags = tuple(dict.fromkeys([f for r in items for f in r.estimate.flags]  # type: ignore[union-attr]
                                    + ["multi_frame"]))
        est = dataclasses.replace(newest, x=mean.x, y=mean.y, theta=mean.theta, covariance=cov,
                                  camera_ids=cams, reprojection_rmse_px=rmse, flags=flags)
        parts = CovarianceParts(per_frame * shrink, systematic)
        return dataclasses.replace(items[-1], estimate=est, pose=mean, T_world_robot=None,
                                   covariance_parts=parts)
