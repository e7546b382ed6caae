"""Scoring estimates against the simulator's ground truth: the one place the demo, the fault
harness, the benches and the experiments measure what the system published.

An estimate is anything with ``stamp_ns`` (int ns), ``x``, ``y`` (m), ``theta`` (rad) and a
``robot_id`` (:class:`protocol.messages.PoseEstimate`, ``PoseCorrection``, ...). The truth is a
function ``truth_at(stamp_ns, robot_id) -> (3,) (x, y, theta)`` in the world frame (a live
simulation's ``ground_truth``, a fleet's ``true_pose``). Pure numpy; the statistics over the
errors are :mod:`lab.evaluation.metrics`'.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, Protocol

import numpy as np

from lab.evaluation.metrics import heading_errors, translation_errors

#: the true planar pose (3,) (x, y, theta) of ``robot_id`` at ``stamp_ns`` (world frame)
TruthAt = Callable[[int, str], np.ndarray]


class StampedPlanar(Protocol):
    """What is scored: a robot's planar pose at a stamp."""

    robot_id: str
    stamp_ns: int
    x: float
    y: float
    theta: float


def pose_errors(estimates: Sequence[StampedPlanar], truth_at: TruthAt
                ) -> tuple[np.ndarray, np.ndarray]:
    """(N,) translation errors (m) and (N,) absolute heading errors (rad, wrapped) of
    ``estimates`` against the truth of each one's robot at its stamp; empty arrays for none."""
    if not estimates:
        return np.zeros(0), np.zeros(0)
    est = np.array([[e.x, e.y, e.theta] for e in estimates], dtype=np.float64)
    truth = np.array([truth_at(int(e.stamp_ns), e.robot_id) for e in estimates],
                     dtype=np.float64).reshape(-1, 3)
    return (translation_errors(truth[:, :2], est[:, :2]),
            heading_errors(truth[:, 2], est[:, 2]))


def nearer_another_robot(estimate: StampedPlanar, truth_at: TruthAt,
                         robot_ids: Iterable[str]) -> bool:
    """Whether ``estimate`` (of ``estimate.robot_id``) lies nearer another of ``robot_ids``'
    true positions than its own robot's at its stamp: an estimate, or a correction, that is
    really another robot's."""
    xy = np.array([estimate.x, estimate.y], dtype=np.float64)
    stamp = int(estimate.stamp_ns)
    own = float(np.hypot(*(np.asarray(truth_at(stamp, estimate.robot_id))[:2] - xy)))
    return any(float(np.hypot(*(np.asarray(truth_at(stamp, r))[:2] - xy))) < own
               for r in robot_ids if r != estimate.robot_id)


def wrong_robot_corrections(corrections: Sequence[StampedPlanar], truth_at: TruthAt,
                            robot_ids: Sequence[str],
                            key_robots: Sequence[str | None] | None = None,
                            tainted_from_ns: int | None = None) -> int:
    """Corrections that went to the wrong robot: sent on another robot's key (``key_robots``:
    the robot of the key each correction came on, ``None`` when not known), decided on data
    already holding another robot's detection (stamped at or after ``tainted_from_ns``), or
    placing the robot nearer another robot's true position than its own."""
    keys: Sequence[str | None] = key_robots if key_robots else [None] * len(corrections)

    def wrong(corr: StampedPlanar, key_robot: str | None) -> bool:
        on_another_key = bool(key_robot) and key_robot != corr.robot_id
        tainted = tainted_from_ns is not None and corr.stamp_ns >= tainted_from_ns
        return on_another_key or tainted or nearer_another_robot(corr, truth_at, robot_ids)

    return sum(wrong(c, k) for c, k in zip(corrections, keys, strict=True))


def rms_m(errors_m: np.ndarray) -> float:
    """Root mean square of ``errors_m`` (NaN when empty)."""
    e = np.asarray(errors_m, dtype=np.float64)
    return float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")


def live_truth(live: Any) -> TruthAt:
    """``truth_at`` of a live simulation (:class:`simulation.live.LiveSimulation`): each robot's
    own truth in a fleet, the one robot's otherwise (whatever id an estimate carries)."""
    runs = getattr(live, "runs", None)

    def truth_at(stamp_ns: int, robot_id: str) -> np.ndarray:
        if runs and len(runs) > 1 and robot_id in runs:
            return np.asarray(live.ground_truth(stamp_ns, robot_id))
        return np.asarray(live.ground_truth(stamp_ns))

    return truth_at


__all__ = ["StampedPlanar", "TruthAt", "live_truth", "nearer_another_robot", "pose_errors",
           "rms_m", "wrong_robot_corrections"]
