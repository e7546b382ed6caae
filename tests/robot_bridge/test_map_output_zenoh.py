"""The semantic map reaches ROS end to end over real Zenoh on loopback: a mapper-style map
message on ``.../map/<id>/voxels`` → the robot bridge (its service node on a ZenohRunner, the
rmw_zenoh adapter) → ``PointCloud2`` and ``OccupancyGrid`` samples with the rmw_zenoh
attachment that the robot side decodes with rosbags. Bad map messages are counted and the
bridge keeps publishing; at most one map a second goes out."""

from __future__ import annotations

import dataclasses
import struct
import threading
import time

import numpy as np
import pytest

from core.runtime import ZenohRunner
from core.session import loopback_config
from protocol import keys
from protocol.codec import encode
from robot_bridge.adapters import rmw_zenoh as rz
from robot_bridge.adapters import rmw_zenoh_wire as wire
from robot_bridge.adapters import ros2
from robot_bridge.service import RobotBridgeNode
from tests.conftest import free_port, wait_until
from tests.robot_bridge.test_map_output import T0, lab_map

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("rosbags")

CLOUD = "sensor_msgs/msg/PointCloud2"
GRID = "nav_msgs/msg/OccupancyGrid"


class Taker:
    """A robot-side rmw_zenoh subscription: keeps (sequence number, payload) of samples with a
    valid 33-byte attachment and counts the others."""

    def __init__(self, session, key: str) -> None:
        self.got: list[tuple[int, bytes]] = []
        self.dropped = 0
        self._lock = threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        att = sample.attachment
        raw = att.to_bytes() if att is not None else b""
        with self._lock:
            if len(raw) != 33 or raw[16] != 16:
                self.dropped += 1
                return
            self.got.append((struct.unpack_from("<q", raw)[0], sample.payload.to_bytes()))

    def samples(self) -> list[tuple[int, bytes]]:
        with self._lock:
            return list(self.got)


def _bad(cloud, **fields):
    bad = dataclasses.replace(cloud)
    for name, value in fields.items():
        object.__setattr__(bad, name, value)
    return bad


def test_map_reaches_ros_over_rmw_zenoh_and_bad_maps_are_counted(example_site) -> None:
    from rosbags.typesys import Stores, get_typestore

    site = example_site
    robot_id = next(iter(site.robots))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    topics = ros2.RosConfig(profile="nav2").topics(map_frame=site.world_frame)
    node = RobotBridgeNode(
        site, robot_id, lambda session: rz.RmwZenohAdapter(session, topics, domain_id=4))
    runner = ZenohRunner(node, loopback_config(listen=[endpoint]), status=False)
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    ts = get_typestore(Stores.ROS2_HUMBLE)
    map_key = keys.map_voxels_key(site.name, "mapper_main")
    try:
        assert runner.started.wait(10)
        with zenoh.open(loopback_config(connect=[endpoint])) as robot:
            clouds = Taker(robot, wire.topic_key(4, "/smartedge/semantic_map", CLOUD))
            grids = Taker(robot, wire.topic_key(4, "/smartedge/obstacles", GRID))
            pub = robot.declare_publisher(map_key, congestion_control=zenoh.CongestionControl.BLOCK)
            good = lab_map(site.world_frame)
            pts = np.array(good.points_xyz)
            pts[3, 0] = np.inf
            # refused by the decoder (counted "invalid"), or by the map output's checks
            # ("map_output.invalid"); one at a time (the bridge queues only the newest two)
            for junk, counter in ((encode(_bad(good, points_xyz=pts)), "invalid"),
                                  (encode(_bad(good, points_xyz=pts[:, :2])), "invalid"),
                                  (b"\x00garbage", "invalid"),
                                  (encode(dataclasses.replace(good, frame_id="odom")),
                                   "map_output.invalid")):
                before = node.counters().get(counter, 0)
                assert wait_until(
                    lambda junk=junk, counter=counter, before=before:
                        pub.put(junk) or node.counters().get(counter, 0) > before,
                    timeout_s=10, step_s=0.2), counter
            assert not clouds.samples()  # none of them reached the robot
            # the first good maps may go out before the bridge's subscription is known
            seq = 0

            def put_good() -> bool:
                nonlocal seq
                seq += 1
                pub.put(encode(dataclasses.replace(good, seq=seq, stamp_ns=T0 + seq)))
                return bool(clouds.samples()) and bool(grids.samples())

            assert wait_until(put_good, timeout_s=10, step_s=0.1)
            # 2.5 s more of maps at 10 Hz: at most one a second reaches the robot
            start = len(clouds.samples())
            t_end = time.monotonic() + 2.5
            while time.monotonic() < t_end:
                put_good()
                time.sleep(0.1)
            time.sleep(0.3)
            sent = len(clouds.samples()) - start
            assert 2 <= sent <= 3, sent
            assert clouds.dropped == 0 and grids.dropped == 0
            seqs = [s for s, _ in clouds.samples()]
            assert seqs == list(range(1, len(seqs) + 1))  # rmw_zenoh sequence from 1

            msg = ts.deserialize_cdr(clouds.samples()[-1][1], CLOUD)
            assert msg.header.frame_id == site.world_frame
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            assert T0 < stamp <= T0 + seq  # a recent map, not the first
            n = len(good.points_xyz)
            assert (msg.width, msg.point_step) == (n, 24)
            data = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(n, 24)
            xyz = data[:, 0:12].copy().view("<f4")
            labels = data[:, 20:22].copy().view("<u2").ravel()
            np.testing.assert_array_equal(xyz, good.points_xyz)
            np.testing.assert_array_equal(labels, good.class_ids)

            grid = ts.deserialize_cdr(grids.samples()[-1][1], GRID)
            assert grid.header.frame_id == site.world_frame
            cells = np.asarray(grid.data, np.int8).reshape(grid.info.height, grid.info.width)
            res = grid.info.resolution
            col = int((1.1 - grid.info.origin.position.x) // res)
            row = int((0.5 - grid.info.origin.position.y) // res)
            assert cells[row, col] == 100  # the box
            assert cells[0, 0] == 0  # floor

        counters = node.counters()
        assert counters["invalid"] >= 3  # NaN/inf, wrong shape, garbage: refused on decode
        assert counters["map_output.invalid"] >= 1  # the map in another frame
        assert counters["map_output.replaced"] >= 5  # 10 Hz in, 1 Hz out
        assert counters["map_output_published"] >= 3
        assert counters["adapter.map_cloud_published"] == counters["map_output_published"]
        assert counters["adapter.map_grid_published"] == counters["map_output_published"]
        assert counters.get("handler_errors", 0) == 0
        assert thread.is_alive()  # the bridge kept running
    finally:
        runner.stop()
        thread.join(10)
    assert not thread.is_alive()


@pytest.mark.parametrize("namespace", ["", "robot1"])
def test_map_over_zenoh_bridge_ros2dds_keys(zenoh_pair, namespace) -> None:
    """The ros2 adapter (zenoh-bridge-ros2dds on the robot) puts the map on ``[ns/]smartedge/
    semantic_map`` and ``[ns/]smartedge/obstacles``: plain CDR, as the DDS bridge forwards it."""
    from rosbags.typesys import Stores, get_typestore

    from robot_bridge.map_output import MapOutputConfig, map_snapshot

    bridge_side, robot_side, _ = zenoh_pair
    topics = ros2.RosConfig(profile="nav2", namespace=namespace).topics()
    adapter = ros2.RosZenohAdapter(bridge_side, topics)
    prefix = f"{namespace}/" if namespace else ""
    got: dict[str, list[bytes]] = {"cloud": [], "grid": []}
    robot_side.declare_subscriber(f"{prefix}smartedge/semantic_map",
                                  lambda s: got["cloud"].append(s.payload.to_bytes()))
    robot_side.declare_subscriber(f"{prefix}smartedge/obstacles",
                                  lambda s: got["grid"].append(s.payload.to_bytes()))
    snap = map_snapshot(lab_map(), MapOutputConfig(resolution_m=0.1), "map")
    try:
        assert wait_until(lambda: adapter.publish_map(snap) and bool(got["cloud"])
                          and bool(got["grid"]), timeout_s=10, step_s=0.1)
    finally:
        adapter.close()
    ts = get_typestore(Stores.ROS2_HUMBLE)
    cloud = ts.deserialize_cdr(got["cloud"][-1], CLOUD)
    grid = ts.deserialize_cdr(got["grid"][-1], GRID)
    assert cloud.width == len(snap) and cloud.header.frame_id == "map"
    assert (grid.info.width, grid.info.height) == (26, 10)
    assert int((np.asarray(grid.data) == 100).sum()) == int((snap.grid.cells == 100).sum())
    assert adapter.counters["map_cloud_published"] >= 1
    assert not adapter.publish_map(snap)  # closed


def test_map_over_zenoh_plugin_ros1(zenoh_pair) -> None:
    """``--adapter ros1``: ROS 1 serialization on ``<hex(type)>/<md5>/smartedge/...`` keys."""
    from rosbags.typesys import Stores, get_typestore

    from robot_bridge.map_output import MapOutputConfig, map_snapshot

    bridge_side, robot_side, _ = zenoh_pair
    topics = ros2.RosConfig(profile="nav2").topics(ros1=True)
    adapter = ros2.RosZenohAdapter(bridge_side, topics)
    got: dict[str, list[tuple[str, bytes]]] = {"cloud": [], "grid": []}
    for what, topic in (("cloud", "smartedge/semantic_map"), ("grid", "smartedge/obstacles")):
        robot_side.declare_subscriber(
            f"*/*/{topic}", lambda s, what=what: got[what].append(
                (str(s.key_expr), s.payload.to_bytes())))
    snap = map_snapshot(lab_map(), MapOutputConfig(resolution_m=0.1), "map")
    try:
        assert wait_until(lambda: adapter.publish_map(snap) and bool(got["cloud"])
                          and bool(got["grid"]), timeout_s=10, step_s=0.1)
    finally:
        adapter.close()
    ts = get_typestore(Stores.ROS1_NOETIC)
    key, payload = got["cloud"][-1]
    assert key.split("/")[0] == b"sensor_msgs/PointCloud2".hex()
    cloud = ts.deserialize_ros1(payload, CLOUD)
    assert cloud.width == len(snap) and cloud.header.frame_id == "map"
    key, payload = got["grid"][-1]
    assert key.split("/")[0] == b"nav_msgs/OccupancyGrid".hex()
    grid = ts.deserialize_ros1(payload, GRID)
    assert (grid.info.width, grid.info.height) == (26, 10)
