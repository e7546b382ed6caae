"""Map files: the .npz snapshot (exact round trip, broken files), the PLY export, PLY priors."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from mapper.map_io import (
    MAP_FILE_FORMAT,
    MAP_FILE_VERSION,
    load_map_npz,
    read_ply_points,
    save_map_npz,
    write_map_ply,
)
from mapper.semantic_map import MapError, SemanticMapConfig, SemanticVoxelMap
from protocol.semantic_classes import SEMANTIC_CLASS_COLORS, SEMANTIC_CLASS_ID
from tests.mapper.scenes import busy_map, plane_points

TABLE = SEMANTIC_CLASS_ID["table"]

XYZ_HEADER = "ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n" \
             "property float z\n"


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


# ----------------------------------------------------------------------------------------------
# .npz snapshot


def test_save_and_load_round_trip_exactly(tmp_path: Path) -> None:
    m = busy_map()
    path = tmp_path / "map.npz"
    save_map_npz(m, path)
    assert not (tmp_path / "map.npz.tmp").exists()  # written aside, renamed into place
    loaded = load_map_npz(path)
    assert loaded == m and loaded.config == m.config
    for name in ("keys", "log_probs", "hits", "misses", "point_counts", "means", "normals"):
        a, b = getattr(m, name)(), getattr(loaded, name)()
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
    # the loaded map goes on exactly like the original
    rng = np.random.default_rng(8)
    pts = plane_points(rng, 500, size_m=3.0)
    for target in (m, loaded):
        target.integrate(pts, np.full(500, TABLE), np.full(500, 0.6),
                         sensor_origin_world=np.array([0.0, 0.0, 1.0]))
    assert loaded == m
    compressed = tmp_path / "small.npz"
    save_map_npz(m, compressed, compress=True)
    assert load_map_npz(compressed) == m
    assert compressed.stat().st_size < path.stat().st_size
    # the file's fields, as documented
    arrays = _arrays(path)
    assert str(arrays["format"][()]) == MAP_FILE_FORMAT
    assert int(arrays["version"][()]) == MAP_FILE_VERSION
    assert set(arrays) == {"format", "version", "config", *m.state_arrays()}


def test_empty_map_and_another_configuration_round_trip(tmp_path: Path) -> None:
    config = SemanticMapConfig(voxel_size_m=0.2, num_classes=5, evidence="sum")
    empty = SemanticVoxelMap(config)
    save_map_npz(empty, tmp_path / "empty.npz")
    loaded = load_map_npz(tmp_path / "empty.npz")
    assert len(loaded) == 0 and loaded.config == config and loaded == empty


def test_broken_files_raise_map_error_naming_the_file(tmp_path: Path) -> None:
    m = busy_map()
    good = tmp_path / "map.npz"
    save_map_npz(m, good)
    data = good.read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(MapError, match=re.escape(str(truncated))):
        load_map_npz(truncated)
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, keys=np.arange(3))
    with pytest.raises(MapError, match=re.escape(f"{foreign}: not a semantic map")):
        load_map_npz(foreign)
    text = tmp_path / "notes.npz"
    text.write_text("hello")
    with pytest.raises(MapError, match=re.escape(str(text))):
        load_map_npz(text)
    with pytest.raises(MapError, match=re.escape(f"{tmp_path / 'missing.npz'}: no such map")):
        load_map_npz(tmp_path / "missing.npz")
    # a damaged byte in the middle of an array (zip CRC) or in a header
    corrupt = tmp_path / "corrupt.npz"
    flipped = bytearray(data)
    flipped[len(data) // 3] ^= 0xFF
    corrupt.write_bytes(bytes(flipped))
    with pytest.raises(MapError, match=re.escape(str(corrupt))):
        load_map_npz(corrupt)
    # a single array, not an archive
    single = tmp_path / "single.npy"
    np.save(single, np.arange(3))
    with pytest.raises(MapError, match=re.escape(str(single))):
        load_map_npz(single)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"hits": lambda a: a[:-1]}, "hits: expected uint32"),
        ({"version": lambda a: np.array(MAP_FILE_VERSION + 1)}, "map file version 2"),
        ({"config": lambda a: np.array('{"voxel_size_m": 0.1, "colour": 1}')},
         r"config: unknown keys \['colour'\]"),
        ({"config": lambda a: np.array('{"voxel_size_m": -1}')}, "config: voxel_size_m"),
        ({"config": lambda a: np.array("not json")}, "config: not a valid JSON object"),
        ({"prior": None}, r"missing arrays \['prior'\]"),
        ({"point_count": lambda a: np.zeros_like(a)}, "point_count: voxels without points"),
    ],
)
def test_a_map_file_with_bad_fields_is_refused_naming_file_and_field(
        tmp_path: Path, change: dict, match: str) -> None:
    good = tmp_path / "map.npz"
    save_map_npz(busy_map(), good)
    arrays = _arrays(good)
    for name, edit in change.items():
        if edit is None:
            del arrays[name]
        else:
            arrays[name] = edit(arrays[name])
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(MapError, match=re.escape(f"{bad}: ") + ".*" + match):
        load_map_npz(bad)


# ----------------------------------------------------------------------------------------------
# PLY export


def test_ply_export_reads_back_with_open3d(tmp_path: Path) -> None:
    import open3d as o3d

    m = busy_map()
    table = plane_points(np.random.default_rng(9), 500, size_m=0.5, z=0.75)
    m.integrate(table, np.full(500, TABLE), np.full(500, 0.9))
    path = tmp_path / "map.ply"
    write_map_ply(m, path)
    cloud = o3d.io.read_point_cloud(str(path))
    assert len(cloud.points) == len(m)
    np.testing.assert_allclose(np.asarray(cloud.points), m.means(), atol=1e-5)
    assert cloud.has_normals() and cloud.has_colors()
    labels = m.labels()
    colors = np.round(np.asarray(cloud.colors) * 255).astype(np.uint8)
    np.testing.assert_array_equal(colors[labels == TABLE][0], SEMANTIC_CLASS_COLORS[TABLE])
    np.testing.assert_array_equal(colors[labels == -1][0], (128, 128, 128))
    # the scalar properties, read by hand
    raw = path.read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    assert b"property int label" in header and b"property float confidence" in header
    dtype = np.dtype([("xyz", "<f4", 3), ("n", "<f4", 3), ("rgb", "u1", 3), ("label", "<i4"),
                      ("confidence", "<f4")])
    rows = np.frombuffer(body, dtype=dtype)
    np.testing.assert_array_equal(rows["label"], labels)
    np.testing.assert_array_equal(rows["confidence"], m.confidence())


def test_ply_export_at_voxel_centres_and_bad_positions(tmp_path: Path) -> None:
    m = busy_map()
    path = tmp_path / "centres.ply"
    write_map_ply(m, path, positions="center")
    points, normals = read_ply_points(path)
    np.testing.assert_allclose(points, m.voxel_centers(), atol=1e-5)
    assert normals is not None and normals.shape == points.shape
    with pytest.raises(MapError, match="positions"):
        write_map_ply(m, tmp_path / "bad.ply", positions="corner")
    assert not (tmp_path / "bad.ply").exists()


# ----------------------------------------------------------------------------------------------
# PLY prior models


def test_ply_prior_round_trip_and_errors(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    points = plane_points(rng, 20_000, size_m=2.0)
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    m = SemanticVoxelMap.from_prior_points(points, SemanticMapConfig(), normals)
    path = tmp_path / "room.ply"
    write_map_ply(m, path)
    got, got_normals = read_ply_points(path)
    np.testing.assert_allclose(got, m.means(), atol=1e-5)
    assert got_normals is not None and got_normals.shape == got.shape
    # a map exported this way is another map's prior
    again = SemanticVoxelMap.from_prior_points(got, SemanticMapConfig(), got_normals)
    assert len(again) == len(m) and again.is_prior().all()
    ascii_path = tmp_path / "ascii.ply"
    ascii_path.write_text(XYZ_HEADER.format(fmt="ascii", n=2) + "end_header\n1 2 3\n4 5 6\n")
    got, got_normals = read_ply_points(ascii_path)
    np.testing.assert_array_equal(got, [[1, 2, 3], [4, 5, 6]])
    assert got_normals is None
    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(MapError, match=r"truncated\.ply.*truncated"):
        read_ply_points(truncated)
    with pytest.raises(MapError, match="no such PLY"):
        read_ply_points(tmp_path / "missing.ply")
    no_z = tmp_path / "no_z.ply"
    no_z.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                    "property float y\nend_header\n1 2\n")
    with pytest.raises(MapError, match=r"\['z'\] missing"):
        read_ply_points(no_z)


def test_ply_big_endian_with_faces_after_the_vertices(tmp_path: Path) -> None:
    """A CAD export: big-endian doubles, normals with a NaN, a face element that is ignored."""
    vertex = np.array([(0.0, 1.0, 2.0, 0.0, 0.0, 1.0), (3.0, 4.0, 5.0, np.nan, 0.0, 1.0)],
                      dtype=[(n, ">f8") for n in ("x", "y", "z", "nx", "ny", "nz")])
    header = ("ply\nformat binary_big_endian 1.0\ncomment from CAD\nelement vertex 2\n"
              + "".join(f"property double {n}\n" for n in ("x", "y", "z", "nx", "ny", "nz"))
              + "element face 1\nproperty list uchar int vertex_indices\nend_header\n")
    path = tmp_path / "cad.ply"
    path.write_bytes(header.encode("ascii") + vertex.tobytes() + b"\x03\x00\x00\x00\x00")
    points, normals = read_ply_points(path)
    np.testing.assert_array_equal(points, [[0, 1, 2], [3, 4, 5]])
    assert points.dtype == np.float64
    np.testing.assert_array_equal(normals, [[0, 0, 1], [0, 0, 1]])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("solid cube\n", "not a PLY file"),
        ("ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
         "element vertex 1\nproperty float x\nend_header\n3 0 1 2\n1\n",
         "'vertex' element must come first"),
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\nend_header\n",
         "unsupported vertex property"),
        ("ply\nformat binary_middle_endian 1.0\nelement vertex 0\nproperty float x\n"
         "property float y\nproperty float z\nend_header\n", "unsupported PLY format"),
        (XYZ_HEADER.format(fmt="ascii", n=-1) + "end_header\n", "vertex count -1"),
        (XYZ_HEADER.format(fmt="ascii", n=1) + "end_header\nnan 0 0\n", "NaN or inf"),
        (XYZ_HEADER.format(fmt="ascii", n=1) + "end_header\n1 2 three\n",
         "not a readable PLY point cloud"),
    ],
)
def test_bad_ply_files_raise_map_error_naming_the_file(tmp_path: Path, text: str,
                                                       match: str) -> None:
    path = tmp_path / "prior.ply"
    path.write_text(text)
    with pytest.raises(MapError, match=re.escape(str(path)) + ".*" + match):
        read_ply_points(path)
