"""Deferred upkeep: a backend's pose-graph marginalizations (10-20 ms ISAM2 rebuilds) run in its
worker's idle time, one robot per slice, never inside the message that filled the window."""

from __future__ import annotations

import numpy as np

from backend_service.fusion import FusionConfig
from backend_service.pipeline import BackendPipeline
from backend_service.service import BackendNode
from core.runtime import ScriptedRunner
from protocol import encode, keys
from protocol.messages import Odometry, PoseEstimate
from tests.backend_service.pose_synth import example_site

SITE = example_site()
ROBOT = next(iter(SITE.robots))
MS = 1_000_000
T0 = 1_700_000_000_000_000_000
SMALL_WINDOW = FusionConfig(max_keyframes=20, marginalize_batch=5)


def _odom(i: int) -> Odometry:
    """30 Hz odometry of a robot driving 1.5 m/s along x (a keyframe every 0.25 m)."""
    return Odometry(robot_id=ROBOT, stamp_ns=T0 + i * 33 * MS, seq=i, x=0.05 * i, y=0.0,
                    theta=0.0, vx=1.5)


def _initial(stamp_ns: int) -> PoseEstimate:
    return PoseEstimate(ROBOT, stamp_ns, 0, 1.0, 2.0, 0.0, np.diag([1e-4, 1e-4, 1e-5]), "robot")


def test_a_deferred_pipeline_marginalizes_only_in_maintain() -> None:
    pipe = BackendPipeline(SITE, fusion_config=SMALL_WINDOW, deferred_upkeep=True)
    fusion = pipe.tracks[ROBOT].fusion
    assert not pipe.maintain()  # nothing anchored, nothing due
    pipe.feed(_odom(0), T0 + 5 * MS)
    assert fusion.set_initial_pose(_initial(T0)) is not None
    for i in range(1, 400):
        pipe.feed(_odom(i), T0 + i * 33 * MS + 5 * MS)
        if fusion.marginalization_due:
            break
    assert fusion.marginalization_due >= SMALL_WINDOW.marginalize_batch
    assert fusion.counters["marginalizations"] == 0  # the message did not rebuild the graph
    before = fusion.num_keyframes
    assert pipe.maintain()
    assert fusion.counters["marginalizations"] == 1
    assert fusion.num_keyframes < before and fusion.marginalization_due == 0
    assert pipe.counter_snapshot()["upkeep.marginalizations"] == 1
    assert not pipe.maintain()


def test_an_inline_pipeline_keeps_marginalizing_in_the_message() -> None:
    pipe = BackendPipeline(SITE, fusion_config=SMALL_WINDOW, deferred_upkeep=False)
    fusion = pipe.tracks[ROBOT].fusion
    pipe.feed(_odom(0), T0 + 5 * MS)
    fusion.set_initial_pose(_initial(T0))
    for i in range(1, 400):
        pipe.feed(_odom(i), T0 + i * 33 * MS + 5 * MS)
    assert fusion.counters["marginalizations"] >= 3
    assert not pipe.maintain()


def test_the_backend_node_runs_marginalizations_as_idle_upkeep() -> None:
    node = BackendNode(SITE, fusion=SMALL_WINDOW)
    runner = ScriptedRunner(node)
    fusion = node.pipeline.tracks[ROBOT].fusion
    assert fusion.deferred_marginalization
    key = keys.odom_key(SITE.name, ROBOT)
    runner.feed(key, encode(_odom(0)), T0 + 5 * MS)
    fusion.set_initial_pose(_initial(T0))
    for i in range(1, 400):
        recv = T0 + i * 33 * MS + 5 * MS
        runner.feed(key, encode(_odom(i)), recv)
        if i % 10 == 0:
            runner.tick(recv)  # a tick, then the idle upkeep (ScriptedRunner)
    assert fusion.counters["marginalizations"] >= 3
    assert fusion.counters["marginalizations_overdue"] == 0
    assert node.counters()["upkeep.marginalizations"] == fusion.counters["marginalizations"]
    assert fusion.num_keyframes <= SMALL_WINDOW.max_keyframes + 2 * SMALL_WINDOW.marginalize_batch


def test_step_runs_the_upkeep_between_the_tick_and_the_message() -> None:
    """Replays and experiments drive the pipeline with step(): the marginalizations run where
    the service's worker runs them, before the next message, never overdue."""
    pipe = BackendPipeline(SITE, fusion_config=SMALL_WINDOW)
    fusion = pipe.tracks[ROBOT].fusion
    assert fusion.deferred_marginalization
    pipe.step(_odom(0), T0 + 5 * MS)
    fusion.set_initial_pose(_initial(T0))
    for i in range(1, 400):
        pipe.step(_odom(i), T0 + i * 33 * MS + 5 * MS)
    assert fusion.counters["marginalizations"] >= 3
    assert fusion.counters["marginalizations_overdue"] == 0
    assert pipe.counters["upkeep.marginalizations"] == fusion.counters["marginalizations"]
