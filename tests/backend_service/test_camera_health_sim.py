"""A bumped camera through the whole backend: the simulated paper lab (noise-model detections,
simulated time), one camera's true pose moved mid-run; the backend node (real decode path,
:class:`~core.runtime.ScriptedRunner`) names it in its status and leaves it out of the solve,
and an unmoved camera is never named."""

from __future__ import annotations

import re

import pytest

pytest.importorskip("gtsam")

from backend_service.camera_health import CameraHealthConfig
from backend_service.service import BackendNode
from core.runtime import ScriptedRunner, make_status
from lab.bench.camera_health import BumpSpec, run_session, session_messages
from protocol import keys
from protocol.codec import encode
from protocol.messages import Odometry, PoseEstimate, RobotDetections
from simulation.scenario import load_scenario

#: the issue's bump: 5 cm / 1 deg (world axes, not along one axis), 40 s into the run
BUMP = BumpSpec("cam3", 40.0, (0.03, 0.04, 0.0), (0.0, 0.6, 0.8))
#: the issue's target: named within this much robot visibility of the bumped camera
TARGET_VISIBLE_S = 60.0
TEXT = re.compile(r"cam3 moved ~(\d+) cm / (\d+\.\d) deg since calibration")


def _key(site: str, msg: object) -> str:
    if isinstance(msg, RobotDetections):
        return keys.detections_key(site, msg.camera_id)
    if isinstance(msg, Odometry):
        return keys.odom_key(site, msg.robot_id)
    assert isinstance(msg, PoseEstimate)
    return keys.localization_key(site, msg.robot_id)


def test_a_bumped_camera_is_named_in_the_status_and_left_out() -> None:
    scenario = load_scenario()
    node = BackendNode(scenario.site)
    runner = ScriptedRunner(node)
    period_s = 1.0 / scenario.cameras.rate_hz
    visible_after_bump = 0.0
    named_after: float | None = None
    named_at_s = 0.0
    next_status_s = 0.0
    for t_s, tm in session_messages(scenario, 200.0, seed=11, bump=BUMP):
        if named_after is not None and t_s > named_at_s + 10.0:
            break  # ten more seconds with the camera left out
        runner.tick(tm.arrival_ns)
        runner.feed(_key(node.site, tm.message), encode(tm.message), tm.arrival_ns)
        msg = tm.message
        if (isinstance(msg, RobotDetections) and msg.camera_id == BUMP.camera_id
                and msg.detections and t_s >= BUMP.at_s and named_after is None):
            visible_after_bump += period_s
        if t_s >= next_status_s:
            next_status_s += 0.5
            state, detail = node.state()
            if named_after is None and "moved" in detail:
                assert t_s >= BUMP.at_s, f"named before the bump: {detail}"
                assert state == "degraded" and TEXT.search(detail), detail
                named_after = visible_after_bump
                named_at_s = t_s
    assert named_after is not None, "the bumped camera was never named"
    assert 0 < named_after <= TARGET_VISIBLE_S
    status = make_status(node, 0, 0.0)
    assert status.state == "degraded"
    match = TEXT.search(status.detail)
    assert match, status.detail
    assert 3 <= int(match.group(1)) <= 7 and 0.7 <= float(match.group(2)) <= 1.3
    assert "left out of the solve" in status.detail
    assert status.detail.count(" moved ~") == 1  # only the bumped camera
    assert status.counters["camera_health.moved.cam3"] == 1
    assert status.counters["camera_health.moved"] == 1
    assert status.counters["camera_health.excluded_views"] > 0
    # recalibration is the site's business; an explicit reset puts the camera back
    node.pipeline.reset_camera_health("cam3")
    assert "moved" not in node.state()[1]


@pytest.mark.slow
def test_unmoved_cameras_are_never_named_in_five_minutes() -> None:
    """Five simulated minutes of the usual noise, the three trajectories back to back (the
    one-hour figure is ``smartedge bench camera-health``, docs/calibration.md)."""
    scenario = load_scenario()
    health = CameraHealthConfig.from_site(scenario.site)
    result = run_session(scenario, 300.0, seed=5, health=health)
    assert result.duration_s >= 295.0
    assert result.alarms == []
    # the monitor did judge every camera, and none came near the alarm
    assert set(result.max_chi2) == set(scenario.site.cameras)
    assert max(result.max_chi2.values()) < 0.75 * health.alarm_chi2
