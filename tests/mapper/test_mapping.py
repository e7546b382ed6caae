"""Semantic mapping (transport-free) and the mapper service node: placing clouds, the ICP gate,
bad input, persistence."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from core.geometry import rotation_z
from core.history import StampedHistory
from core.runtime import ScriptedRunner
from core.site import load_site
from mapper.map_io import save_map_npz, write_map_ply
from mapper.mapping import MappingConfig, SemanticMapping, interpolate_pose
from mapper.semantic_map import SemanticMapConfig, SemanticVoxelMap
from mapper.service import MapperNode, load_or_start_map
from protocol import encode, keys
from protocol.messages import PoseEstimate, SemanticCloud
from protocol.semantic_classes import SEMANTIC_CLASS_ID
from simulation.synthetic_room import robot_view, sample_room, synthetic_room
from tests.conftest import EXAMPLE_SITE

ROBOT = "hsr"
CAMERA = "cam_sw"
T0 = 1_700_000_000_000_000_000
#: the robot in the synthetic room: base pose and the head sensor 1 m above the base
TRUE_POSE = (1.2, 1.0, math.radians(35.0))
HEAD_Z_M = 1.0
COV = np.diag([1e-4, 1e-4, 1e-4])


@pytest.fixture(scope="module")
def site():
    return load_site(EXAMPLE_SITE)


@pytest.fixture(scope="module")
def room() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return sample_room(synthetic_room(), 300_000, np.random.default_rng(0))


def fresh_mapping(site, room, **config) -> SemanticMapping:
    points, normals, _ = room
    return SemanticMapping(site, MappingConfig(**config), prior_points_world=points,
                           prior_normals_world=normals)


def robot_cloud(stamp_ns: int, seed: int = 1, n: int = 30_000) -> tuple[SemanticCloud, np.ndarray]:
    """The head sensor's view from TRUE_POSE in the robot's base frame, true labels; and the
    same points in the world frame."""
    x, y, th = TRUE_POSE
    pts_world, cls = robot_view(synthetic_room(), (x, y, HEAD_Z_M), th, n,
                                np.random.default_rng(seed))
    pts_base = (pts_world - [x, y, 0.0]) @ rotation_z(th)  # R^T (p - t), row vectors
    T_base_sensor = np.eye(4)
    T_base_sensor[2, 3] = HEAD_Z_M
    msg = SemanticCloud(ROBOT, stamp_ns, 0, "base_link", pts_base.astype(np.float32),
                        cls.astype(np.uint8), np.full(len(cls), 0.9, np.float32), T_base_sensor)
    return msg, pts_world


def world_cloud(points_world: np.ndarray, class_id: int, stamp_ns: int = T0,
                frame_id: str = "map") -> SemanticCloud:
    n = len(points_world)
    return SemanticCloud(CAMERA, stamp_ns, 0, frame_id, points_world.astype(np.float32),
                         np.full(n, class_id, np.uint8), np.full(n, 0.8, np.float32))


def fused(x: float, y: float, th: float, stamp_ns: int) -> PoseEstimate:
    return PoseEstimate(ROBOT, stamp_ns, 0, x, y, th, COV, "fused")


def floor_patch(n: int = 2000, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    # 1 cm above the floor plane: inside the floor voxels, not on their faces
    return np.column_stack([rng.uniform(2.0, 3.0, n), rng.uniform(2.0, 3.0, n),
                            np.full(n, 0.01)])


# -- static sensors ------------------------------------------------------------------------------


def test_edge_cloud_in_the_world_frame_is_fused(site, room) -> None:
    mapping = fresh_mapping(site, room)
    before = mapping.map.coverage()
    out = mapping.on_cloud(world_cloud(floor_patch(), SEMANTIC_CLASS_ID["floor"]), "edge",
                           CAMERA, T0)
    assert out.accepted, out.reason
    assert out.points_fused == 2000
    assert mapping.map.coverage() > before
    labels = mapping.map.labels()
    assert set(np.unique(labels[labels >= 0])) == {SEMANTIC_CLASS_ID["floor"]}
    assert mapping.counter_snapshot()["map.fused.edge"] == 1


def test_edge_cloud_in_the_camera_frame_is_placed_with_the_calibration(site, room) -> None:
    """The same points sent in the camera's optical frame land on the same voxels."""
    pts = floor_patch()
    T_cam_world = site.camera(CAMERA).T_cam_world
    in_cam = pts @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    a, b = fresh_mapping(site, room), fresh_mapping(site, room)
    assert a.on_cloud(world_cloud(pts, 1), "edge", CAMERA, T0).accepted
    assert b.on_cloud(world_cloud(in_cam, 1, frame_id=CAMERA), "edge", CAMERA, T0).accepted
    # float32 on the wire: a point within a micrometre of a voxel face may change sides
    ka = set(a.map.keys()[a.map.has_semantics()].tolist())
    kb = set(b.map.keys()[b.map.has_semantics()].tolist())
    assert len(ka ^ kb) <= 0.01 * len(ka), (len(ka), len(ka ^ kb))


@pytest.mark.parametrize(("case", "token"), [
    ("unknown camera", "unknown_sensor"),
    ("unknown class id", "bad_cloud"),
    ("NaN points", "bad_cloud"),
    ("wrong frame", "wrong_frame"),
    ("future stamp", "future_stamp"),
    ("stale", "stale"),
    ("empty", "empty"),
    ("robot without a pose", "no_pose"),
])
def test_bad_clouds_are_rejected_counted_and_change_nothing(site, room, case: str,
                                                           token: str) -> None:
    mapping = fresh_mapping(site, room)
    reference = mapping.map.copy()
    pts = floor_patch(200)
    scope, sensor, now = "edge", CAMERA, T0
    if case == "unknown camera":
        msg, sensor = world_cloud(pts, 1), "cam_nowhere"
    elif case == "unknown class id":
        msg = world_cloud(pts, 200)
    elif case == "NaN points":
        # decode() already refuses such a message; the mapping does not rely on it
        msg = world_cloud(pts, 1)
        bad = msg.points_xyz.copy()
        bad[5, 1] = np.nan
        object.__setattr__(msg, "points_xyz", bad)
    elif case == "wrong frame":
        msg = world_cloud(pts, 1, frame_id="odom")
    elif case == "future stamp":
        msg, now = world_cloud(pts, 1, stamp_ns=T0 + 2_000_000_000), T0
    elif case == "stale":
        msg, now = world_cloud(pts, 1), T0 + 60_000_000_000
    elif case == "empty":
        msg = world_cloud(pts[:0], 1)
    else:
        msg, _ = robot_cloud(T0, n=2000)
        scope, sensor = "robot", ROBOT
    out = mapping.on_cloud(msg, scope, sensor, now)
    assert not out.accepted
    assert out.reason.startswith(token), out.reason
    counters = mapping.counter_snapshot()
    assert counters["map.rejected"] == 1 and counters[f"map.rejected.{token}"] == 1
    assert mapping.map.equals(reference)


# -- robot clouds: placed with the fused pose, aligned by ICP ------------------------------------


def test_robot_cloud_is_aligned_to_the_map_and_the_offset_reported(site, room) -> None:
    """The fused pose is 10 cm / 5 deg off: with ``placement: icp`` ICP moves the cloud back
    onto the room, reports the offset, and the labels land on the room's own voxels."""
    mapping = fresh_mapping(site, room, placement="icp")
    x, y, th = TRUE_POSE
    err = (0.08, -0.06, math.radians(5.0))
    for k in range(-3, 4):  # fused poses around the cloud's stamp, 20 ms apart
        mapping.on_pose(fused(x + err[0], y + err[1], th + err[2], T0 + k * 20_000_000))
    msg, _ = robot_cloud(T0)
    out = mapping.on_cloud(msg, "robot", ROBOT, T0)
    assert out.accepted, out.reason
    assert out.alignment is not None and out.alignment.fitness > 0.9
    report = mapping.alignments[ROBOT]
    # the sensor (above the base origin) was placed err[:2] off; the correction moves it back
    assert math.hypot(report.dx_m + err[0], report.dy_m + err[1]) < 0.01
    assert report.dyaw_deg == pytest.approx(-5.0, abs=0.3)
    assert out.T_world_sensor is not None
    np.testing.assert_allclose(out.T_world_sensor[:2, 3], [x, y], atol=0.01)
    # the labels land where the true pose would have put them; without ICP they would not
    def labelled(m: SemanticMapping) -> set[int]:
        return set(m.map.keys()[m.map.has_semantics()].tolist())

    truth = fresh_mapping(site, room, align_robot_clouds=False)
    truth.on_pose(fused(x, y, th, T0))
    assert truth.on_cloud(msg, "robot", ROBOT, T0).accepted
    unaligned = fresh_mapping(site, room, align_robot_clouds=False)
    unaligned.on_pose(fused(x + err[0], y + err[1], th + err[2], T0))
    assert unaligned.on_cloud(msg, "robot", ROBOT, T0).accepted

    def jaccard(a: set[int], b: set[int]) -> float:
        return len(a & b) / len(a | b)

    aligned_overlap = jaccard(labelled(mapping), labelled(truth))
    unaligned_overlap = jaccard(labelled(unaligned), labelled(truth))
    assert aligned_overlap > 0.8 and unaligned_overlap < 0.4, (aligned_overlap,
                                                                unaligned_overlap)


def test_default_placement_fuses_where_the_fused_pose_puts_it_and_reports_the_offset(
        site, room) -> None:
    """``placement: fused`` (the default): ICP gates the cloud and measures the offset, the
    cloud is fused as the fused pose places it."""
    mapping = fresh_mapping(site, room)
    x, y, th = TRUE_POSE
    for k in range(-3, 4):
        mapping.on_pose(fused(x + 0.05, y, th, T0 + k * 20_000_000))
    msg, _ = robot_cloud(T0)
    out = mapping.on_cloud(msg, "robot", ROBOT, T0)
    assert out.accepted, out.reason
    assert out.T_world_sensor is not None and out.T_world_sensor[0, 3] == pytest.approx(x + 0.05)
    assert mapping.alignments[ROBOT].dx_m == pytest.approx(-0.05, abs=0.01)


@pytest.mark.parametrize(("placement", "std_m", "fused_ok"), [
    ("fused", 0.01, True), ("fused", 0.3, False), ("icp", 0.01, False)])
def test_a_cloud_the_map_cannot_check_is_fused_only_on_a_confident_pose(
        site, room, placement: str, std_m: float, fused_ok: bool) -> None:
    """Floor only: ICP cannot verify x, y, yaw (degenerate). With the default placement it is
    fused when the fused pose is confident, never with ``placement: icp``."""
    mapping = fresh_mapping(site, room, placement=placement)
    mapping.on_pose(PoseEstimate(ROBOT, T0, 0, 2.5, 2.5, 0.0, np.diag([std_m**2 / 2] * 2 + [1e-4]),
                                 "fused"))
    rng = np.random.default_rng(5)
    floor_base = np.column_stack([rng.uniform(0.5, 2.0, 3000), rng.uniform(-0.7, 0.7, 3000),
                                  np.full(3000, 0.01)])
    msg = SemanticCloud(ROBOT, T0, 0, "base_link", floor_base.astype(np.float32),
                        np.full(3000, 1, np.uint8), np.full(3000, 0.9, np.float32))
    out = mapping.on_cloud(msg, "robot", ROBOT, T0)
    assert out.accepted == fused_ok, out.reason
    if not fused_ok:
        assert "degenerate" in out.reason
    else:
        assert mapping.counter_snapshot()["map.fused.robot_unverified"] == 1


def test_robot_cloud_from_the_wrong_place_is_rejected_and_not_fused(site, room) -> None:
    mapping = fresh_mapping(site, room)
    reference = mapping.map.copy()
    x, y, th = TRUE_POSE
    for k in range(-3, 4):
        mapping.on_pose(fused(x + 1.5, y + 0.5, th + 0.6, T0 + k * 20_000_000))
    msg, _ = robot_cloud(T0)
    out = mapping.on_cloud(msg, "robot", ROBOT, T0)
    assert not out.accepted and out.reason.startswith("alignment"), out.reason
    assert mapping.map.equals(reference)
    assert mapping.counter_snapshot()["map.rejected.alignment"] == 1
    assert not mapping.alignments[ROBOT].accepted


def test_without_alignment_the_cloud_is_fused_where_the_pose_puts_it(site, room) -> None:
    mapping = fresh_mapping(site, room, align_robot_clouds=False)
    x, y, th = TRUE_POSE
    mapping.on_pose(fused(x + 0.3, y, th, T0))
    msg, _ = robot_cloud(T0)
    out = mapping.on_cloud(msg, "robot", ROBOT, T0)
    assert out.accepted and out.alignment is None
    assert out.T_world_sensor is not None
    assert out.T_world_sensor[0, 3] == pytest.approx(x + 0.3)


def test_only_fused_poses_of_known_robots_are_used(site, room) -> None:
    mapping = fresh_mapping(site, room)
    mapping.on_pose(PoseEstimate(ROBOT, T0, 0, 1.0, 1.0, 0.0, COV, "cameras"))
    mapping.on_pose(PoseEstimate("ghost", T0, 0, 1.0, 1.0, 0.0, COV, "fused"))
    c = mapping.counter_snapshot()
    assert c["map.pose_wrong_source"] == 1 and c["map.pose_unknown_robot"] == 1
    msg, _ = robot_cloud(T0, n=2000)
    assert mapping.on_cloud(msg, "robot", ROBOT, T0).reason.startswith("no_pose")


def test_interpolate_pose() -> None:
    poses: StampedHistory[PoseEstimate] = StampedHistory(out_of_order="insert")
    for p in (fused(0.0, 0.0, math.pi - 0.1, T0), fused(1.0, 2.0, -math.pi + 0.1, T0 + 100)):
        poses.insert(p.stamp_ns, p)
    x, y, th = interpolate_pose(poses, T0 + 50, max_gap_ns=200)
    assert (x, y) == pytest.approx((0.5, 1.0))
    assert abs(abs(th) - math.pi) < 1e-9  # along the shorter arc, through +-pi
    assert interpolate_pose(poses, T0 + 50, max_gap_ns=50) is None  # the two are too far apart
    assert interpolate_pose(poses, T0 - 20, max_gap_ns=50) == pytest.approx(
        (0.0, 0.0, math.pi - 0.1))
    assert interpolate_pose(poses, T0 - 40, max_gap_ns=50) is None
    assert interpolate_pose(StampedHistory(), T0, max_gap_ns=50) is None


# -- configuration ------------------------------------------------------------------------------


def _site_with_map(tmp_path: Path, section: str):
    text = EXAMPLE_SITE.read_text() + "\nmap:\n" + section
    path = tmp_path / "site.yaml"
    path.write_text(text)
    return load_site(path)


def test_map_section_is_read_and_checked_naming_the_key(tmp_path: Path) -> None:
    from protocol.errors import SiteConfigError

    site = _site_with_map(tmp_path, "  voxel_size_m: 0.1\n  min_fitness: 0.6\n"
                                    "  snapshot_path: maps/lab.npz\n")
    cfg = MappingConfig.from_site(site)
    assert cfg.map.voxel_size_m == 0.1 and cfg.alignment.min_fitness == 0.6
    assert cfg.snapshot_path == "maps/lab.npz"
    with pytest.raises(SiteConfigError, match=r"map.*voxel_sise_m"):
        MappingConfig.from_site(_site_with_map(tmp_path, "  voxel_sise_m: 0.1\n"))
    with pytest.raises(SiteConfigError, match="map"):
        MappingConfig.from_site(_site_with_map(tmp_path, "  voxel_size_m: -1\n"))


# -- the service node, persistence ---------------------------------------------------------------


def test_mapper_node_fuses_publishes_and_keeps_the_map(site, room, tmp_path: Path) -> None:
    points, normals, _ = room
    snapshot = tmp_path / "map.npz"
    config = MappingConfig(publish_period_s=0.0, snapshot_period_s=0.0)
    mapping = SemanticMapping(site, config, prior_points_world=points,
                              prior_normals_world=normals)
    node = MapperNode(site, mapping=mapping, snapshot_path=snapshot)
    runner = ScriptedRunner(node)
    runner.feed(keys.edge_cloud_key(site.name, CAMERA),
                encode(world_cloud(floor_patch(), SEMANTIC_CLASS_ID["floor"])), T0)
    runner.feed(keys.edge_cloud_key(site.name, CAMERA), b"\x93garbage", T0)
    x, y, th = TRUE_POSE
    for k in range(-3, 4):
        runner.feed(keys.pose_key(site.name, ROBOT),
                    encode(fused(x, y, th, T0 + k * 20_000_000)), T0)
    msg, _ = robot_cloud(T0)
    runner.feed(keys.robot_cloud_key(site.name, ROBOT), encode(msg), T0)
    counters = node.counters()
    assert counters["invalid"] == 1
    assert counters["map.fused.edge"] == 1 and counters["map.fused.robot"] == 1
    assert "hsr icp ok" in node.state()[1]
    node.config = dataclasses.replace(config, publish_period_s=1e-9)
    out = runner.tick(T0)
    voxels = [o.message for o in out if o.key == keys.map_voxels_key(site.name, "main")]
    assert len(voxels) == 1
    assert len(voxels[0].points_xyz) == int(mapping.map.has_semantics().sum())
    assert snapshot.exists() and node.counters()["snapshots"] == 1
    node.close()
    restarted, how = load_or_start_map(site, config, snapshot)
    assert "snapshot" in how and restarted.map.equals(mapping.map)


def test_unreadable_snapshot_is_moved_aside_and_the_map_starts_from_the_prior(
        site, room, tmp_path: Path) -> None:
    points, normals, _ = room
    prior = tmp_path / "room.ply"
    write_map_ply(SemanticVoxelMap.from_prior_points(points, SemanticMapConfig(), normals),
                  prior)
    snapshot = tmp_path / "map.npz"
    save_map_npz(fresh_mapping(site, room).map, snapshot)
    snapshot.write_bytes(snapshot.read_bytes()[:1000])  # truncated
    config = MappingConfig(prior_model=str(prior))
    mapping, how = load_or_start_map(site, config, snapshot)
    assert how.startswith("prior model")
    assert not snapshot.exists()
    assert len(list(tmp_path.glob("map.npz.unreadable-*"))) == 1
    assert mapping.map.is_prior().all() and len(mapping.map) > 1000


def test_command_line_paths_are_relative_to_the_working_directory(
        room, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--snapshot`` / ``--prior-model`` given on the command line are the user's paths (the
    working directory), not relative to the site file; a bad prior model is a config error."""
    from mapper.service import build_node, build_parser
    from protocol.errors import SmartedgeError

    points, normals, _ = room
    monkeypatch.chdir(tmp_path)
    write_map_ply(SemanticVoxelMap.from_prior_points(points, SemanticMapConfig(), normals),
                  tmp_path / "room.ply")
    args = build_parser().parse_args(["--site", str(EXAMPLE_SITE), "--prior-model", "room.ply",
                                      "--snapshot", "maps/lab.npz"])
    node = build_node(args)
    assert node.snapshot_path == tmp_path / "maps" / "lab.npz"
    assert node.started_from.startswith("prior model room.ply")
    assert node.save_snapshot() and (tmp_path / "maps" / "lab.npz").exists()
    bad = build_parser().parse_args(["--site", str(EXAMPLE_SITE), "--prior-model", "none.ply"])
    with pytest.raises(SmartedgeError, match=r"none\.ply"):
        build_node(bad)
