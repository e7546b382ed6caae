"""The semantic map as ROS messages (robot_bridge.map_output): the PointCloud2 and the obstacle
OccupancyGrid decoded with rosbags (its own typestore, not the bridge's) match the map; the
rate limit, latest-only and bad-map counting of :class:`MapOutput`; the ``map_output`` section."""

from __future__ import annotations

import dataclasses
import math
import struct

import numpy as np
import pytest

from protocol.messages import SemanticCloud
from protocol.semantic_classes import SEMANTIC_CLASS_COLORS, SEMANTIC_CLASS_ID
from robot_bridge import map_output as mo

pytest.importorskip("rosbags")

S = 1_000_000_000
T0 = 1_700_000_123 * S + 456


def _store(ros1: bool = False):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def lab_map(frame: str = "map") -> SemanticCloud:
    """A 2 m x 1 m floor (5 cm voxels, class floor, z 0.02), a box standing on it at
    x 1.00-1.20, y 0.40-0.60 (z 0.1-0.5), a wall segment only above the band (x 0.3, z 2.2),
    a ceiling voxel (x 0.5, y 0.5, z 2.6), a low-confidence chair at (0.2, 0.2, 0.4), a table
    beyond the floor (x 2.5, y 0.5, z 0.75)."""
    fx, fy = np.meshgrid(np.arange(0.025, 2.0, 0.05), np.arange(0.025, 1.0, 0.05))
    floor = np.stack([fx.ravel(), fy.ravel(), np.full(fx.size, 0.02)], axis=1)
    bx, by, bz = np.meshgrid(np.arange(1.025, 1.2, 0.05), np.arange(0.425, 0.6, 0.05),
                             np.arange(0.125, 0.5, 0.05))
    box = np.stack([bx.ravel(), by.ravel(), bz.ravel()], axis=1)
    others = np.array([[0.325, 0.825, 2.2], [0.525, 0.525, 2.6], [0.225, 0.225, 0.4],
                       [2.525, 0.525, 0.75]])
    pts = np.concatenate([floor, box, others]).astype(np.float32)
    cid = SEMANTIC_CLASS_ID
    labels = np.concatenate([
        np.full(len(floor), cid["floor"]), np.full(len(box), cid["box"]),
        [cid["wall"], cid["ceiling"], cid["chair"], cid["table"]]]).astype(np.uint16)
    conf = np.concatenate([np.full(len(floor), 0.9), np.linspace(0.5, 1.0, len(box)),
                           [0.8, 0.7, 0.2, 0.95]]).astype(np.float32)
    return SemanticCloud("mapper_main", T0, 3, frame, pts, labels, conf)


def _stamp_ns(header) -> int:
    return header.stamp.sec * S + header.stamp.nanosec


@pytest.mark.parametrize("ros1", [False, True])
def test_point_cloud_decodes_with_rosbags_and_matches_the_map(ros1) -> None:
    cloud = lab_map()
    snap = mo.map_snapshot(cloud, mo.MapOutputConfig(), "map")
    payload = snap.cloud_payload(ros1=ros1, seq=5)
    ts = _store(ros1)
    if ros1:
        msg = ts.deserialize_ros1(payload, "sensor_msgs/msg/PointCloud2")
        assert msg.header.seq == 5
    else:
        assert payload[:4] == b"\x00\x01\x00\x00"  # CDR little endian
        msg = ts.deserialize_cdr(payload, "sensor_msgs/msg/PointCloud2")
    n = len(cloud.points_xyz)
    assert msg.header.frame_id == "map" and _stamp_ns(msg.header) == T0
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, n, 24, 24 * n)
    assert not msg.is_bigendian and msg.is_dense
    fields = {f.name: (f.offset, f.datatype, f.count) for f in msg.fields}
    assert fields == {"x": (0, 7, 1), "y": (4, 7, 1), "z": (8, 7, 1), "rgb": (12, 7, 1),
                      "confidence": (16, 7, 1), "label": (20, 4, 1)}
    data = bytes(msg.data)
    assert len(data) == 24 * n
    # read every point with struct, from the offsets the message states
    for i in (0, n // 2, n - 4, n - 1):
        base = i * 24
        x, y, z = struct.unpack_from("<3f", data, base + fields["x"][0])
        assert (x, y, z) == tuple(float(v) for v in cloud.points_xyz[i])
        # rgb: a float32 whose bits are 0x00RRGGBB, as RViz's RGB8 colour transformer reads it
        (rgb_bits,) = struct.unpack_from("<I", data, base + fields["rgb"][0])
        label = struct.unpack_from("<H", data, base + fields["label"][0])[0]
        assert label == cloud.class_ids[i]
        r, g, b = (rgb_bits >> 16) & 255, (rgb_bits >> 8) & 255, rgb_bits & 255
        assert (r, g, b) == tuple(int(c) for c in SEMANTIC_CLASS_COLORS[label])
        assert rgb_bits >> 24 == 0
        (conf,) = struct.unpack_from("<f", data, base + fields["confidence"][0])
        assert conf == pytest.approx(float(cloud.confidences[i]))
    cols = mo.decode_cloud_data(msg.data, msg.fields, msg.point_step)
    np.testing.assert_array_equal(cols["label"], cloud.class_ids)
    np.testing.assert_array_equal(np.stack([cols["x"], cols["y"], cols["z"]], 1),
                                  cloud.points_xyz)


def test_occupancy_grid_marks_the_right_cells() -> None:
    cloud = lab_map()
    config = mo.MapOutputConfig(resolution_m=0.1, min_confidence=0.3)
    snap = mo.map_snapshot(cloud, config, "map")
    msg = _store().deserialize_cdr(snap.grid_payload(), "nav_msgs/msg/OccupancyGrid")
    info = msg.info
    assert msg.header.frame_id == "map" and _stamp_ns(msg.header) == T0
    assert info.resolution == pytest.approx(0.1)
    # the extent: x 0.025..2.525 and y 0.025..0.975 at 10 cm
    assert (info.origin.position.x, info.origin.position.y) == pytest.approx((0.0, 0.0))
    assert (info.width, info.height) == (26, 10)
    q = info.origin.orientation
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
    grid = np.asarray(msg.data, dtype=np.int8).reshape(info.height, info.width)

    def cell(x: float, y: float) -> int:
        i = math.floor((x - info.origin.position.x) / info.resolution)
        j = math.floor((y - info.origin.position.y) / info.resolution)
        return int(grid[j, i])

    assert cell(1.05, 0.45) == 100 and cell(1.15, 0.55) == 100  # the box
    assert cell(0.05, 0.05) == 0 and cell(1.95, 0.95) == 0  # floor only
    assert cell(0.35, 0.85) == 0  # a wall voxel above the band leaves the floor free
    assert cell(0.55, 0.55) == 0  # the ceiling is no obstacle
    assert cell(0.25, 0.25) == 0  # the chair is less certain than min_confidence
    assert cell(2.55, 0.55) == 100  # the table, off the floor
    assert cell(2.25, 0.55) == -1  # nothing seen there
    occupied = {(int(j), int(i)) for j, i in zip(*np.nonzero(grid == 100), strict=True)}
    assert occupied == {(4, 10), (4, 11), (5, 10), (5, 11), (5, 25)}
    assert (grid == -1).sum() == 26 * 10 - 20 * 10 - 1
    # without the confidence floor the chair occupies its cell
    snap2 = mo.map_snapshot(cloud, dataclasses.replace(config, min_confidence=0.0), "map")
    assert snap2.grid is not None
    assert snap2.grid.cells[snap2.grid.cell_of(0.25, 0.25)] == 100


def test_grid_band_follows_the_floor_height_and_classes() -> None:
    cloud = lab_map()
    # the floor 0.3 m up: the box's voxels below 0.35 m are under the band, the rest in it
    high = mo.MapOutputConfig(resolution_m=0.1, floor_z_m=0.3, band_min_m=0.05, band_max_m=0.1)
    grid = mo.map_snapshot(cloud, high, "map").grid
    assert grid is not None and grid.origin_z_m == 0.3
    assert grid.cells[grid.cell_of(1.05, 0.45)] == 100  # box voxels at z 0.375
    only_walls = mo.MapOutputConfig(resolution_m=0.1, obstacle_classes="wall", band_max_m=3.0)
    grid = mo.map_snapshot(cloud, only_walls, "map").grid
    assert grid is not None
    assert int((grid.cells == 100).sum()) == 1
    assert grid.cells[grid.cell_of(0.35, 0.85)] == 100
    snap = mo.map_snapshot(cloud, mo.MapOutputConfig(grid=False), "map")
    assert snap.grid is None and snap.grid_payload() is None
    assert mo.map_snapshot(cloud, mo.MapOutputConfig(cloud=False), "map").cloud_payload() is None


def _bad(cloud: SemanticCloud, **fields) -> SemanticCloud:
    """``cloud`` with fields the message constructor would refuse (what a peer that skips the
    checks could send)."""
    bad = dataclasses.replace(cloud)
    for name, value in fields.items():
        object.__setattr__(bad, name, value)
    return bad


def test_map_output_rate_limit_latest_only_and_bad_maps() -> None:
    out = mo.MapOutput(mo.MapOutputConfig(rate_hz=1.0), world_frame="map")
    good = lab_map()
    assert out.due(T0) is None  # nothing yet
    assert out.on_map(good)
    first = out.due(T0)
    assert first is not None and len(first) == len(good.points_xyz)
    assert out.due(T0 + 1) is None  # nothing new
    newer = dataclasses.replace(good, seq=4, stamp_ns=T0 + S // 2)
    newest = dataclasses.replace(good, seq=5, stamp_ns=T0 + S)
    assert out.on_map(newer) and out.on_map(newest)
    assert out.due(T0 + S // 2) is None  # within the period
    got = out.due(T0 + S)
    assert got is not None and got.stamp_ns == T0 + S  # the newest, the older one replaced
    assert out.due(T0 + 3 * S) is None
    pts = np.array(good.points_xyz)
    pts[7, 2] = np.nan
    assert not out.on_map(_bad(good, points_xyz=pts))
    assert not out.on_map(_bad(good, points_xyz=pts[:, :2]))
    assert not out.on_map(_bad(good, confidences=np.array(good.confidences)[:-1]))
    assert not out.on_map(dataclasses.replace(good, frame_id="odom"))
    assert not out.on_map("not a map")
    assert out.due(T0 + 5 * S) is None  # no bad map went through
    assert out.counters == {"received": 8, "replaced": 1, "converted": 2, "invalid": 5}
    assert out.last_conversion_s > 0.0
    # off
    off = mo.MapOutput(mo.MapOutputConfig(rate_hz=0.0))
    off.on_map(good)
    assert off.due(T0) is None


def test_grid_extent_limit_is_an_error_not_an_allocation() -> None:
    good = lab_map()
    far = np.array(good.points_xyz)
    far[0] = (5000.0, 5000.0, 0.02)
    out = mo.MapOutput(mo.MapOutputConfig(resolution_m=0.01), world_frame="map")
    assert out.on_map(_bad(good, points_xyz=far))
    assert out.due(T0) is None
    assert out.counters["conversion_failed"] == 1


def test_config_checks_and_the_site_section(tmp_path, example_site_path) -> None:
    for bad in ({"rate_hz": 2.0}, {"resolution_m": 0.0}, {"band_min_m": 1.0, "band_max_m": 0.5},
                {"obstacle_classes": "wall,sofa"}, {"free_classes": "floor,wall"},
                {"min_confidence": 1.5}, {"map_id": " "}):
        with pytest.raises(ValueError):
            mo.MapOutputConfig(**bad)
    import yaml

    from core.site import load_site

    doc = yaml.safe_load(example_site_path.read_text())
    doc["map_output"] = {"rate_hz": 0.5, "resolution_m": 0.1, "obstacle_classes": "box,wall"}
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(doc))
    config = mo.MapOutputConfig.from_site(load_site(path))
    assert (config.rate_hz, config.resolution_m) == (0.5, 0.1)
    assert list(config.class_ids(config.obstacle_classes)) == [2, 9]
    doc["map_output"] = {"rate_hz": 3}
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(Exception, match="map_output"):
        mo.MapOutputConfig.from_site(load_site(path))


def test_rviz_config_shows_the_topics_the_bridge_publishes(example_site) -> None:
    """deploy/rviz/smartedge.rviz: the map cloud coloured by its packed rgb, the obstacle grid,
    the pose outputs, on the default topics of the ``ros`` section, in the site's world frame."""
    from pathlib import Path

    import yaml

    from robot_bridge.adapters.ros2 import RosConfig

    path = Path(__file__).resolve().parents[2] / "deploy" / "rviz" / "smartedge.rviz"
    doc = yaml.safe_load(path.read_text())
    manager = doc["Visualization Manager"]
    assert manager["Global Options"]["Fixed Frame"] == example_site.world_frame
    displays = {d["Class"].split("/")[-1]: d for d in manager["Displays"]}
    ros = RosConfig()
    cloud = displays["PointCloud2"]
    assert cloud["Topic"]["Value"] == "/" + ros.map_cloud_topic
    assert cloud["Color Transformer"] == "RGB8" and cloud["Position Transformer"] == "XYZ"
    assert cloud["Size (m)"] == pytest.approx(mo.MapOutputConfig().resolution_m)
    assert displays["Map"]["Topic"]["Value"] == "/" + ros.obstacles_topic
    # the rmw_zenoh publishers are volatile: a transient-local subscription would not match
    for d in (cloud, displays["Map"]):
        assert d["Topic"]["Durability Policy"] == "Volatile"
    poses = {d["Topic"]["Value"] for d in manager["Displays"]
             if d["Class"].endswith("PoseWithCovariance")}
    assert poses == {"/" + ros.pose_topic, "/" + ros.camera_pose_topic}
    assert "TF" in displays


def test_bridge_subscribes_to_the_map_only_with_an_adapter_that_publishes_it(
        example_site, zenoh_pair) -> None:
    from protocol import keys
    from robot_bridge.adapters.base import RobotAdapter
    from robot_bridge.adapters.ros2 import RosConfig, RosZenohAdapter
    from robot_bridge.service import RobotBridgeNode

    class NoRos(RobotAdapter):
        def read_odometry(self):
            return []

        def read_localization(self):
            return None

        def apply_correction(self, correction) -> bool:
            return False

    robot_id = next(iter(example_site.robots))
    map_key = keys.map_voxels_key(example_site.name, "*")

    def map_keys(node) -> list[str]:
        return [s.key_expr for s in node.subscriptions() if s.key_expr == map_key]

    plain = RobotBridgeNode(example_site, robot_id, lambda session: NoRos())
    plain.attach(None)
    assert map_keys(plain) == []
    topics = RosConfig(profile="nav2").topics()
    ros = RobotBridgeNode(example_site, robot_id,
                          lambda session: RosZenohAdapter(session, topics))
    ros.attach(zenoh_pair[0])
    try:
        assert map_keys(ros) == [map_key]
    finally:
        ros.close()
