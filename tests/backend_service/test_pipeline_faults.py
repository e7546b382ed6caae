"""The pipeline against poisoned inputs (issue #17): future stamps on odometry and
localization are dropped against the arrival clock, counted and reported."""

from __future__ import annotations

import numpy as np

from backend_service.pipeline import BackendPipeline
from protocol.messages import Odometry, PoseEstimate
from tests.backend_service.pose_synth import example_site

SITE = example_site()
ROBOT = next(iter(SITE.robots))
MS = 1_000_000
T0 = 1_700_000_000_000_000_000


def odom(stamp_ns: int, x: float, seq: int) -> Odometry:
    return Odometry(robot_id=ROBOT, stamp_ns=stamp_ns, seq=seq, x=x, y=0.0, theta=0.0,
                    vx=0.5)


def test_odometry_stamped_in_the_far_future_is_dropped_and_reported() -> None:
    pipe = BackendPipeline(SITE)
    fusion = pipe.tracks[ROBOT].fusion
    for i in range(30):
        pipe.feed(odom(T0 + i * 33 * MS, 0.016 * i, i), T0 + i * 33 * MS + 5 * MS)
    accepted = fusion.counters["odometry_accepted"]
    t = T0 + 30 * 33 * MS
    pipe.feed(odom(2**63 - 1, 0.5, 30), t)  # the probe
    pipe.feed(odom(t + 400 * MS, 0.5, 31), t)  # 0.4 s ahead: beyond the 100 ms tolerance
    for i in range(31, 60):
        pipe.feed(odom(T0 + i * 33 * MS, 0.016 * i, i + 1), T0 + i * 33 * MS + 5 * MS)
    assert pipe.counters["odometry_future"] == 2
    assert fusion.counters["odometry_accepted"] == accepted + 29  # none lost after the probe
    assert fusion.counters["odometry_out_of_order"] == 0
    problems = pipe.problems(T0 + 60 * 33 * MS)
    assert any("odometry" in p and "ahead" in p for p in problems), problems
    assert pipe.problems(T0 + 60 * 33 * MS + 6_000 * MS) == [
        p for p in pipe.problems(T0 + 60 * 33 * MS + 6_000 * MS) if "odometry" not in p]
    counters = pipe.counter_snapshot()
    assert counters["odometry_future"] == 2


def test_localization_stamped_ahead_is_not_used_as_a_prior() -> None:
    pipe = BackendPipeline(SITE)
    loc = PoseEstimate(ROBOT, T0 + 5_000 * MS, 0, 30.0, 30.0, 0.0, np.eye(3) * 1e-4, "robot")
    pipe.feed(loc, T0)
    assert pipe.counters["localization_future"] == 1
    assert pipe.tracks[ROBOT].prior(T0 + 5_000 * MS)[0] is None
