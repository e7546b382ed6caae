"""``smartedge demo --robots 3``: two identical HSR-like robots and a box base on crossing
routes, live over Zenoh on loopback: four edge agents reporting every robot unnamed (typed),
the backend assigning the detections, one robot bridge per robot. Every robot gets fused poses
on the bus, near its own true pose, and no correction goes to the wrong robot."""

from __future__ import annotations

from pathlib import Path

import pytest

from lab.demo import FLEET_SITE_FILE, run_demo, wrong_robot_corrections

pytestmark = pytest.mark.slow

ROBOTS = ("hsr_a", "hsr_b", "box_c")


def test_fleet_demo_every_robot_localized_no_wrong_corrections(tmp_path: Path) -> None:
    # 22 s: the robots pass within 0.5 m of each other at 6.5-8 s and stop at their second
    # waypoint (corrections while static) by about 16 s
    result = run_demo(["--robots", "3", "--duration", "22", "--rerun", "none",
                       "--out", str(tmp_path), "--progress-s", "10"])
    seen = result.seen
    assert result.exit_codes == [0] * 8, result.exit_codes  # backend, 4 edges, 3 bridges
    assert {"backend/main", *(f"robot-bridge/{r}" for r in ROBOTS)} <= set(seen.status)
    site_text = (tmp_path / FLEET_SITE_FILE).read_text()
    assert all(f"namespace: {r}" in site_text for r in ROBOTS)
    live = result.live
    assert live.robot_ids == ROBOTS
    assert dict(live.site.robots) == {"hsr_a": "hsr", "hsr_b": "hsr", "box_c": "box_base"}
    for rid in ROBOTS:
        fused = [e for e in seen.fused if e.robot_id == rid]
        camera = [e for e in seen.camera if e.robot_id == rid]
        assert len(fused) > 100 and len(camera) > 50, (rid, len(fused), len(camera))
        assert result.figures[f"{rid} fused"] < 0.05, rid
        assert result.figures[f"{rid} cameras"] < 0.05, rid
    # corrections: on each robot's own key, for that robot, placing it where it is
    assert len(seen.corrections) >= 3
    assert {c.robot_id for c in seen.corrections} <= set(ROBOTS)
    assert seen.correction_keys == [c.robot_id for c in seen.corrections]
    assert wrong_robot_corrections(seen, live) == 0
    assert result.figures["wrong_corrections"] == 0
    # the backend assigned the unnamed detections (counted in its status)
    assert result.figures["detections_assigned"] > 1000
    assert result.figures["detections_unknown_model"] == 0
    assert (tmp_path / "tum" / "hsr_b" / "fused.tum").exists()
