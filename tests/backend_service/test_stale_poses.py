"""After a stall, the backend drops stale poses instead of publishing them (issue 17, item 4)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("gtsam")

from backend_service.pipeline import PipelineOutput
from backend_service.pipeline_config import PipelineConfig
from backend_service.service import BackendNode
from core.runtime import Outgoing, ScriptedRunner
from core.site import ClockPolicy, Site, load_site
from protocol import encode, keys
from protocol.errors import SiteConfigError
from protocol.messages import Odometry, PoseEstimate, RobotDetections
from simulation.runner import SimulationRun
from simulation.scenario import load_scenario

S_NS = 1_000_000_000
T0_NS = 1_700_000_000 * S_NS
REPO = Path(__file__).resolve().parents[2]
SIM_S = 12.0


def _pose(stamp_ns: int, source: str = "fused") -> PoseEstimate:
    return PoseEstimate("hsr", stamp_ns, 0, 1.0, 2.0, 0.0, np.eye(3) * 0.01, source)


class _Clock:
    """The publish-time clock of a stalled worker: set by hand."""

    def __init__(self) -> None:
        self.now_ns = T0_NS

    def __call__(self) -> int:
        return self.now_ns


def _scripted(site: Site, config: PipelineConfig | None = None
              ) -> tuple[ScriptedRunner, BackendNode, _Clock]:
    """A backend node whose pipeline echoes each odometry stamp as a fused pose and each tick's
    ``now_ns - 0.2 s`` as a camera pose, with a hand-set publish clock."""
    node = BackendNode(site, config=config)
    runner = ScriptedRunner(node)
    clock = _Clock()
    node.clock = clock
    node.pipeline.feed = lambda msg, arrival_ns: PipelineOutput(  # type: ignore[method-assign]
        fused=[_pose(msg.stamp_ns)])
    node.pipeline.poll = lambda now_ns: PipelineOutput(  # type: ignore[method-assign]
        camera=[_pose(now_ns - S_NS // 5, "cameras")])
    return runner, node, clock


def _odometry(runner: ScriptedRunner, stamp_ns: int, recv_ns: int) -> list[Outgoing]:
    msg = Odometry("hsr", stamp_ns, 0, 0.0, 0.0, 0.0)
    return runner.feed(keys.odom_key(runner.node.site, "hsr"), encode(msg), recv_ns)


def test_a_pose_older_than_the_limit_at_publish_time_is_dropped_and_counted(example_site) -> None:
    runner, node, clock = _scripted(example_site)
    clock.now_ns = T0_NS + 20_000_000
    assert len(_odometry(runner, T0_NS, T0_NS + 10_000_000)) == 1  # 20 ms old: published
    # the worker was stalled: the message arrived in time but is handled 1.5 s later
    clock.now_ns = T0_NS + 3 * S_NS
    assert _odometry(runner, T0_NS + 3 * S_NS // 2, T0_NS + 3 * S_NS // 2 + 10_000_000) == []
    assert runner.tick(T0_NS + S_NS) == []  # a camera pose stamped 1.8 s before publishing
    counters = node.counters()
    assert counters["stale_dropped"] == 2
    assert counters["stale_dropped.pose"] == 1 and counters["stale_dropped.camera_pose"] == 1
    clock.now_ns = T0_NS + 4 * S_NS
    assert len(runner.tick(T0_NS + 4 * S_NS)) == 1  # caught up: published again


def test_the_limit_is_the_site_clock_policy(tmp_path: Path, example_site) -> None:
    site = dataclasses.replace(example_site, clock=ClockPolicy(max_age_ms=5000.0))
    runner, _, clock = _scripted(site)
    clock.now_ns = T0_NS + 3 * S_NS
    assert len(_odometry(runner, T0_NS, T0_NS)) == 1
    doc = yaml.safe_load((REPO / "deploy" / "site.example.yaml").read_text())
    doc["clock"] = {"max_age_ms": 250}
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(doc))
    assert load_site(tmp_path / "site.yaml").clock.max_age_ms == 250
    doc["clock"] = {"max_age_ms": 0}
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(SiteConfigError, match=r"clock.*max_age_ms"):
        load_site(tmp_path / "site.yaml")
    # the backend's own setting it replaced names the new key
    del doc["clock"]
    doc["pose"]["publish_max_age_s"] = 0.25
    (tmp_path / "site.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(SiteConfigError, match=r"pose\.publish_max_age_s.*clock\.max_age_ms"):
        load_site(tmp_path / "site.yaml")


def test_a_replayed_recording_with_old_stamps_is_not_stale(example_site) -> None:
    runner, node, clock = _scripted(example_site)
    replay_offset = 3 * 3600 * S_NS  # the recording is three hours old
    clock.now_ns = T0_NS + replay_offset + 30_000_000
    assert len(_odometry(runner, T0_NS, T0_NS + replay_offset + 10_000_000)) == 1
    clock.now_ns += 2 * S_NS  # but a replay stalled for 2 s is stale
    assert _odometry(runner, T0_NS + 10_000_000, T0_NS + replay_offset + 20_000_000) == []
    assert node.counters()["stale_dropped"] == 1


def test_a_future_stamped_input_does_not_make_every_pose_stale(example_site) -> None:
    runner, node, clock = _scripted(example_site)
    clock.now_ns = T0_NS
    _odometry(runner, T0_NS + 3600 * S_NS, T0_NS)  # an hour ahead: published (it is not old)
    assert len(_odometry(runner, T0_NS - 10_000_000, T0_NS)) == 1
    assert node.counters().get("stale_dropped", 0) == 0


def test_a_stall_drops_exactly_the_stale_outputs_of_the_real_pipeline() -> None:
    """The simulated site through the real node twice: once live, once with the worker stalled
    for 3 s. The stalled run publishes nothing older than the limit, drops what the live run
    published late, and publishes again after the stall."""
    sc = load_scenario()
    messages = list(SimulationRun(sc, "traj1", seed=7).messages(until_s=SIM_S))
    start = messages[0].arrival_ns
    stall_from, stall_to = start + 5 * S_NS, start + 8 * S_NS

    def run(stalled: bool) -> tuple[list[tuple[int, Outgoing]], dict[str, int]]:
        node = BackendNode(sc.site)
        runner = ScriptedRunner(node)
        clock = _Clock()
        node.clock = clock
        out: list[tuple[int, Outgoing]] = []
        for tm in messages:
            # a stalled worker handles what arrived during the stall when the stall ends
            handled_ns = stall_to if stalled and stall_from <= tm.arrival_ns < stall_to else (
                tm.arrival_ns)
            clock.now_ns = handled_ns
            out += [(handled_ns, o) for o in runner.tick(tm.arrival_ns)]
            key = (keys.detections_key(sc.site.name, tm.message.camera_id)
                   if isinstance(tm.message, RobotDetections)
                   else keys.odom_key(sc.site.name, tm.message.robot_id)
                   if isinstance(tm.message, Odometry)
                   else keys.localization_key(sc.site.name, tm.message.robot_id))
            out += [(handled_ns, o) for o in runner.feed(key, encode(tm.message), tm.arrival_ns)]
        return out, node.counters()

    live, live_counters = run(False)
    stalled, counters = run(True)
    limit_ns = ClockPolicy().max_age_ns
    assert live_counters.get("stale_dropped", 0) == 0
    assert counters["stale_dropped"] > 20
    assert len(stalled) + counters["stale_dropped"] == len(live)
    floor_ns = 5_000_000  # the simulated inputs' smallest stamp-to-arrival delay
    assert all(at - o.message.stamp_ns - floor_ns <= limit_ns for at, o in stalled)
    after = [o for at, o in stalled if at > stall_to]
    assert sum(o.key.endswith("/pose") for o in after) > 50
    assert sum(o.key.endswith("/camera_pose") for o in after) > 5
