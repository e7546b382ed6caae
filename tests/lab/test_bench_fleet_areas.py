"""`smartedge bench fleet --split area`: the facility's site gets one area per router, each
backend serves its router's area, and the split is measured next to the unsplit peer."""

from __future__ import annotations

from pathlib import Path

import pytest

from backend_service.areas import AreaMap, parse_areas

pytest.importorskip("zenoh")


def test_the_fleet_site_has_one_area_per_router_with_the_cells_cameras(tmp_path: Path) -> None:
    from lab.bench.fleet import backend_areas_of, write_fleet_site

    site, layout = write_fleet_site(tmp_path / "site.yaml", 5, 20, 3)
    areas = parse_areas(site)
    assert sorted(areas) == ["a0", "a1", "a2"]
    for name, area in areas.items():
        k = int(name[1:])
        assert set(area.cameras) == {c for c, cell in layout.cell_of.items() if cell % 3 == k}
    # every robot's cell is in the area of its nearest camera
    amap = AreaMap(site)
    for i in range(5):
        x, y, _ = layout.robot_pose(i, 2.0)
        assert amap.area_of(x, y) == f"a{i % 3}"
    assert backend_areas_of(0, 3, 3) == ["a0"] and backend_areas_of(2, 3, 3) == ["a2"]
    assert backend_areas_of(0, 2, 3) == ["a0", "a2"] and backend_areas_of(1, 2, 3) == ["a1"]
    assert backend_areas_of(0, 1, 3) == ["a0", "a1", "a2"]
    assert backend_areas_of(3, 4, 3) == []  # more backends than areas: every camera
    plain, _ = write_fleet_site(tmp_path / "plain.yaml", 5, 20)
    assert parse_areas(plain) == {}


def test_in_process_each_area_backend_is_handed_only_its_areas_cameras(tmp_path: Path) -> None:
    from lab.bench.fleet import in_process_cpu

    res = in_process_cpu("area", 2, 2, 2, 8, 10.0, 10.0, 2.0, tmp_path)
    assert [(r.backend, r.areas, r.robots_run) for r in res] == [("b0", "a0", 1),
                                                                 ("b1", "a1", 1)]
    # 4 cameras each, 10 frames in the measured second
    assert [r.camera_messages for r in res] == [40, 40]
    assert all(r.cpu_s_per_s > 0 for r in res)
    whole = in_process_cpu("none", 1, 2, 2, 8, 10.0, 10.0, 2.0, tmp_path)
    assert whole[0].camera_messages == 80 and whole[0].areas == "all"


@pytest.mark.slow
def test_area_split_backends_receive_only_their_areas_cameras_and_never_publish_twice(
        tmp_path: Path) -> None:
    from lab.bench.fleet import FleetRow, run_row

    r = run_row(FleetRow(backends=2, routers=2, robots=2, cameras=6, rate_hz=10.0,
                         odom_rate_hz=10.0, seconds=3.0, warmup_s=3.0, split="area"),
                tmp_path, progress=False)
    print(r)
    assert r.areas == {"b0": "a0", "b1": "a1"}
    assert r.poses >= 0.8 * r.frame_sets and r.duplicates == 0 and r.silent == 0, r
    # each backend's synchronizer got its own three cameras' messages only (~3 x 10 Hz x 6 s)
    assert all(0 < n <= 3 * 10 * 6 + 10 for n in r.received.values()), r.received
    assert {r.owners["b0"], r.owners["b1"]} == {"robot00", "robot01"}
    assert r.owners["b0"] == "robot00"  # robot00's cell is in a0, b0's area
