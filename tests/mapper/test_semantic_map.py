"""The semantic voxel map: Bayesian fusion, input checks, carving, prior, state arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest

import mapper.semantic_map as semantic_map
from mapper.semantic_map import (
    STATE_FIELDS,
    MapError,
    SemanticMapConfig,
    SemanticVoxelMap,
    pack_voxel_keys,
    unpack_voxel_keys,
)
from protocol.semantic_classes import (
    SEMANTIC_CLASS_COLORS,
    SEMANTIC_CLASS_ID,
    SEMANTIC_CLASSES,
)
from tests.mapper.scenes import busy_map, noisy_labels, plane_points

FLOOR = SEMANTIC_CLASS_ID["floor"]
TABLE = SEMANTIC_CLASS_ID["table"]
BOX = SEMANTIC_CLASS_ID["box"]
C = len(SEMANTIC_CLASSES)


def test_two_noisy_views_raise_confidence() -> None:
    rng = np.random.default_rng(0)
    m = SemanticVoxelMap(SemanticMapConfig(voxel_size_m=0.1))
    n = 20_000
    m.integrate(plane_points(rng, n, z=0.05), *noisy_labels(rng, n, FLOOR, 0.2, 0.7))
    assert np.all(m.has_semantics())
    first = dict(zip(m.keys().tolist(), m.confidence().tolist(), strict=True))
    assert np.mean(m.labels() == FLOOR) > 0.95
    m.integrate(plane_points(rng, n, z=0.05), *noisy_labels(rng, n, FLOOR, 0.2, 0.7))
    second = dict(zip(m.keys().tolist(), m.confidence().tolist(), strict=True))
    common = sorted(set(first) & set(second))
    assert len(common) > 50
    gain = np.array([second[k] - first[k] for k in common])
    assert np.mean(gain > 0) > 0.95
    well_seen = m.point_counts() >= 50  # edge voxels with a handful of points may be wrong
    assert well_seen.sum() > 50
    assert np.all(m.labels()[well_seen] == FLOOR)
    assert np.all(m.hits() == 2)
    probs = m.probabilities().astype(np.float64)
    np.testing.assert_allclose(probs.sum(axis=1), 1.0, atol=1e-5)


def test_one_scan_of_a_voxel_gives_the_detector_confidence() -> None:
    m = SemanticVoxelMap()
    pts = np.full((7, 3), 0.012)
    m.integrate(pts, np.full(7, TABLE), np.full(7, 0.8))
    assert len(m) == 1
    assert m.labels()[0] == TABLE
    assert m.confidence()[0] == pytest.approx(0.8, abs=1e-5)


@pytest.mark.parametrize("evidence", ["mean", "sum"])
def test_contradictory_labels_within_one_scan_follow_the_majority(evidence: str) -> None:
    rng = np.random.default_rng(1)
    m = SemanticVoxelMap(SemanticMapConfig(voxel_size_m=0.25, evidence=evidence))
    n = 4000
    ids = np.where(rng.random(n) < 0.65, TABLE, BOX)
    m.integrate(plane_points(rng, n, z=0.1), ids, np.full(n, 0.8))
    assert np.all(m.labels() == TABLE)


def test_contradictory_scans_resolve_to_the_majority_whatever_the_order() -> None:
    rng = np.random.default_rng(2)
    for order in ([TABLE, TABLE, TABLE, BOX, BOX], [BOX, BOX, TABLE, TABLE, TABLE],
                  [TABLE, BOX, TABLE, BOX, TABLE]):
        m = SemanticVoxelMap(SemanticMapConfig(voxel_size_m=0.1))
        for label in order:
            n = 5000
            m.integrate(plane_points(rng, n, z=0.05), np.full(n, label), np.full(n, 0.75))
        assert np.all(m.labels() == TABLE), order
        # a single scan's evidence (log 0.75 - log(0.25 / 13)) is below the clamp: not saturated
        assert float(m.log_probs().min()) > m.config.class_log_prob_clamp


def test_class_probabilities_input() -> None:
    rng = np.random.default_rng(3)
    n = 3000
    probs = np.full((n, C), 0.2 / (C - 1), dtype=np.float32)
    probs[:, TABLE] = 0.8
    m = SemanticVoxelMap(SemanticMapConfig(voxel_size_m=0.2))
    m.integrate(plane_points(rng, n), class_probs=probs)
    top1 = SemanticVoxelMap(SemanticMapConfig(voxel_size_m=0.2))
    top1.integrate(plane_points(np.random.default_rng(3), n), np.full(n, TABLE), np.full(n, 0.8))
    assert np.all(m.labels() == TABLE)
    np.testing.assert_allclose(m.log_probs(), top1.log_probs(), atol=1e-5)


def _bad_inputs() -> list[tuple[str, dict, str]]:
    n = 10
    pts = np.linspace(0, 1, 3 * n).reshape(n, 3)
    ids = np.full(n, FLOOR)
    conf = np.full(n, 0.9)
    nan_pts = pts.copy()
    nan_pts[3, 1] = np.nan
    inf_pts = pts.copy()
    inf_pts[0, 2] = np.inf
    bad_ids = ids.copy()
    bad_ids[5] = C
    neg_ids = ids.copy()
    neg_ids[0] = -1
    bad_conf = conf.copy()
    bad_conf[2] = 1.5
    probs = np.full((n, C), 1.0 / C)
    return [
        ("unknown class id", dict(points_world=pts, class_ids=bad_ids, confidences=conf),
         "class_ids"),
        ("negative class id", dict(points_world=pts, class_ids=neg_ids, confidences=conf),
         "class_ids"),
        ("float class ids", dict(points_world=pts, class_ids=ids * 1.0, confidences=conf),
         "class_ids"),
        ("NaN point", dict(points_world=nan_pts, class_ids=ids, confidences=conf),
         "points_world"),
        ("inf point", dict(points_world=inf_pts, class_ids=ids, confidences=conf),
         "points_world"),
        ("confidence > 1", dict(points_world=pts, class_ids=ids, confidences=bad_conf),
         "confidences"),
        ("points (N, 2)", dict(points_world=pts[:, :2], class_ids=ids, confidences=conf),
         "points_world"),
        ("short ids", dict(points_world=pts, class_ids=ids[:-1], confidences=conf),
         "class_ids"),
        ("no semantics", dict(points_world=pts), "class_ids"),
        ("probs and ids", dict(points_world=pts, class_ids=ids, confidences=conf,
                               class_probs=probs), "class_probs"),
        ("probs rows", dict(points_world=pts, class_probs=probs * 2), "class_probs"),
        ("probs columns", dict(points_world=pts, class_probs=probs[:, :-1]), "class_probs"),
        ("far away", dict(points_world=pts + 1e6, class_ids=ids, confidences=conf),
         "points_world"),
        ("NaN origin", dict(points_world=pts, class_ids=ids, confidences=conf,
                            sensor_origin_world=np.array([0.0, np.nan, 0.0])),
         "sensor_origin_world"),
    ]


@pytest.mark.parametrize(("case", "kwargs", "field"), _bad_inputs(),
                         ids=[c[0] for c in _bad_inputs()])
def test_bad_input_is_rejected_and_leaves_the_map_unchanged(case: str, kwargs: dict,
                                                            field: str) -> None:
    rng = np.random.default_rng(4)
    m = SemanticVoxelMap.from_prior_points(plane_points(rng, 2000))
    m.integrate(plane_points(rng, 2000), np.full(2000, FLOOR), np.full(2000, 0.9))
    before = m.copy()
    assert m == before
    with pytest.raises(MapError, match=field):
        m.integrate(**kwargs)
    assert m == before, case


def test_config_is_validated_naming_the_field() -> None:
    with pytest.raises(MapError, match="voxel_size_m"):
        SemanticMapConfig(voxel_size_m=0.0)
    with pytest.raises(MapError, match="num_classes"):
        SemanticMapConfig(num_classes=1)
    with pytest.raises(MapError, match="class_log_prob_clamp"):
        SemanticMapConfig(class_log_prob_clamp=0.0)
    with pytest.raises(MapError, match="evidence"):
        SemanticMapConfig(evidence="max")
    with pytest.raises(MapError, match="carve_free_space"):
        SemanticMapConfig(carve_free_space="yes")  # type: ignore[arg-type]


def test_range_limit_drops_far_points() -> None:
    m = SemanticVoxelMap(SemanticMapConfig(max_range_m=2.0))
    pts = np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 1.9, 0.0]])
    report = m.integrate(pts, np.full(3, FLOOR), np.full(3, 0.9),
                         sensor_origin_world=np.zeros(3))
    assert (report.points_in, report.points_out_of_range, report.points_fused) == (3, 1, 2)
    assert len(m) == 2


def test_keys_pack_and_unpack() -> None:
    idx = np.array([[0, 0, 0], [-1, 2, -3], [2**20 - 1, -(2**20), 5]], dtype=np.int64)
    keys = pack_voxel_keys(idx)
    np.testing.assert_array_equal(unpack_voxel_keys(keys), idx)
    order = np.lexsort((idx[:, 2], idx[:, 1], idx[:, 0]))
    np.testing.assert_array_equal(np.argsort(keys), order)


def _corridor() -> tuple[SemanticVoxelMap, np.ndarray]:
    """A map with a wall at x = 3 m and a 'ghost' object at x = 1.5 m (seen before), both on
    the line of sight of a sensor at the origin; returns the map and the wall points."""
    rng = np.random.default_rng(5)
    m = SemanticVoxelMap(SemanticMapConfig(voxel_size_m=0.1, carve_free_space=True))
    ghost = np.column_stack([np.full(400, 1.55), rng.uniform(-0.2, 0.2, (400, 2))])
    m.integrate(ghost, np.full(400, BOX), np.full(400, 0.9))  # no origin: no carving
    off_ray = np.column_stack([np.full(200, 1.55), rng.uniform(2.0, 2.3, 200),
                               rng.uniform(-0.2, 0.2, 200)])
    m.integrate(off_ray, np.full(200, BOX), np.full(200, 0.9))
    wall = np.column_stack([np.full(3000, 3.05), rng.uniform(-0.5, 0.5, (3000, 2))])
    return m, wall


def test_carving_counts_misses_between_sensor_and_surface_and_creates_no_voxels() -> None:
    m, wall = _corridor()
    before = m.copy()
    ghost_keys = before.keys()
    report = m.integrate(wall, np.full(len(wall), SEMANTIC_CLASS_ID["wall"]),
                         np.full(len(wall), 0.9), sensor_origin_world=np.zeros(3))
    assert report.rays == report.voxels_updated and report.ray_samples > 0
    # only the wall's voxels are new
    wall_keys = np.unique(pack_voxel_keys(np.floor(wall / 0.1).astype(np.int64)))
    assert len(m) == len(before) + len(wall_keys)
    assert set(m.keys().tolist()) == set(ghost_keys.tolist()) | set(wall_keys.tolist())
    # voxels on the rays (|y|, |z| < 0.2 at x = 1.5, inside the wall's view cone) were crossed
    old = m.misses()[: len(before)]
    centers = before.voxel_centers()
    on_rays = (np.abs(centers[:, 1]) < 0.2) & (np.abs(centers[:, 2]) < 0.2)
    off_rays = centers[:, 1] > 1.5
    assert on_rays.any() and off_rays.any()
    assert np.all(old[on_rays] == 1)
    assert np.all(old[off_rays] == 0)
    assert report.voxels_carved == int(np.count_nonzero(old))
    assert np.all(m.misses()[len(before):] == 0)  # the wall itself is hit, not missed
    assert np.all(m.hits()[len(before):] == 1)
    # one hit, one miss: no longer occupied (hits > misses fails)
    assert not m.occupied()[: len(before)][on_rays].any()


def test_carving_by_key_lookup_matches_the_dense_grid(monkeypatch: pytest.MonkeyPatch) -> None:
    m_grid, wall = _corridor()
    m_keys = m_grid.copy()
    args = (wall, np.full(len(wall), 2), np.full(len(wall), 0.9))
    r_grid = m_grid.integrate(*args, sensor_origin_world=np.array([0.01, 0.02, 0.03]))
    monkeypatch.setattr(semantic_map, "_CARVE_GRID_MAX_CELLS", 0)
    r_keys = m_keys.integrate(*args, sensor_origin_world=np.array([0.01, 0.02, 0.03]))
    assert r_grid == r_keys
    assert m_grid == m_keys


def test_no_carving_by_default_nor_without_a_sensor_origin() -> None:
    carving, wall = _corridor()
    plain = SemanticVoxelMap(SemanticMapConfig(voxel_size_m=0.1))
    ghost = carving.means()
    plain.integrate(ghost, np.full(len(ghost), BOX), np.full(len(ghost), 0.9))
    args = (wall, np.full(len(wall), 2), np.full(len(wall), 0.9))
    report = plain.integrate(*args, sensor_origin_world=np.zeros(3))
    assert report.voxels_carved == 0 and report.ray_samples == 0
    assert np.all(plain.misses() == 0)
    report = carving.integrate(*args)  # carving on, but no origin
    assert report.voxels_carved == 0 and report.ray_samples == 0
    assert np.all(carving.misses() == 0)


def test_prior_voxels_have_no_semantics_and_coverage_counts_them() -> None:
    rng = np.random.default_rng(6)
    prior = plane_points(rng, 40_000, size_m=2.0, noise_m=0.0)
    m = SemanticVoxelMap.from_prior_points(prior, SemanticMapConfig(voxel_size_m=0.1),
                                           normals=np.tile([0.0, 0.0, 1.0], (len(prior), 1)))
    assert len(m) > 300
    assert m.is_prior().all() and m.occupied().all()
    assert not m.has_semantics().any()
    assert np.all(m.labels() == -1)
    np.testing.assert_allclose(m.confidence(), 1.0 / C, rtol=1e-5)
    assert m.coverage() == 0.0
    assert np.all(m.hits() == 0)
    # floor voxels: normals along +z (oriented by the prior normals)
    np.testing.assert_allclose(m.normals(), np.tile([0.0, 0.0, 1.0], (len(m), 1)), atol=1e-6)

    # observe the half x < 1 m and a table above the floor (not in the prior)
    seen = prior[prior[:, 0] < 0.95]
    m.integrate(seen, np.full(len(seen), FLOOR), np.full(len(seen), 0.9))
    table = plane_points(rng, 2000, size_m=0.5, z=0.75)
    m.integrate(table, np.full(len(table), TABLE), np.full(len(table), 0.9))
    prior_mask = m.is_prior()
    seen_keys = set(pack_voxel_keys(np.floor(seen / 0.1).astype(np.int64)).tolist())
    expected = sum(k in seen_keys for k in m.keys()[prior_mask].tolist()) / prior_mask.sum()
    assert m.coverage() == pytest.approx(expected)
    assert 0.4 < m.coverage() < 0.6
    assert m.coverage(np.ones(len(m), dtype=bool)) > m.coverage()
    assert math.isnan(SemanticVoxelMap().coverage())
    with pytest.raises(MapError, match="surface_mask"):
        m.coverage(np.ones(3, dtype=bool))


def test_state_arrays_rebuild_the_same_map() -> None:
    m = busy_map()
    arrays = m.state_arrays()
    assert tuple(arrays) == STATE_FIELDS
    assert all(len(a) == len(m) for a in arrays.values())
    assert arrays["log_probs"].shape == (len(m), C) and arrays["sum_dd"].shape == (len(m), 6)
    rebuilt = SemanticVoxelMap.from_state_arrays(m.config, arrays)
    assert rebuilt == m and rebuilt.config == m.config
    hits = m.hits()
    arrays["hits"] += np.uint32(7)  # copies: the map keeps its own state
    assert rebuilt == m and np.array_equal(m.hits(), hits)
    # the rebuilt map finds its voxels by key and goes on exactly like the original
    rng = np.random.default_rng(8)
    pts = plane_points(rng, 500, size_m=3.0)
    for target in (m, rebuilt):
        target.integrate(pts, np.full(500, TABLE), np.full(500, 0.6),
                         sensor_origin_world=np.array([0.0, 0.0, 1.0]))
    assert rebuilt == m
    empty = SemanticVoxelMap()
    assert SemanticVoxelMap.from_state_arrays(empty.config, empty.state_arrays()) == empty


def test_state_arrays_are_checked_naming_the_field() -> None:
    m = busy_map()
    good = m.state_arrays()

    def broken(**changes: object) -> dict:
        out = dict(good)
        out.update(changes)
        return {k: v for k, v in out.items() if v is not None}

    cases = [
        (broken(sum_dd=None), r"missing arrays \['sum_dd'\]"),
        (broken(hits=good["hits"].astype(np.int64)), "hits: expected uint32"),
        (broken(misses=good["misses"][:-1]), "misses: expected uint32 of shape"),
        (broken(log_probs=good["log_probs"][:, :-1]), "log_probs: expected float32"),
        (broken(keys=np.concatenate([good["keys"][:-1], good["keys"][:1]])),
         "keys: duplicate voxel keys"),
        (broken(point_count=np.zeros(len(m), dtype=np.int64)),
         "point_count: voxels without points"),
    ]
    for arrays, match in cases:
        with pytest.raises(MapError, match=match):
            SemanticVoxelMap.from_state_arrays(m.config, arrays)
    with pytest.raises(MapError, match="config: expected a SemanticMapConfig"):
        SemanticVoxelMap.from_state_arrays({"voxel_size_m": 0.1}, good)  # type: ignore[arg-type]


def test_copy_is_independent() -> None:
    m = busy_map()
    c = m.copy()
    assert c == m and c is not m
    c.integrate(np.array([[5.0, 5.0, 5.0]]), np.array([TABLE]), np.array([0.9]))
    assert c != m and len(c) == len(m) + 1


def test_class_legend_matches_the_simulation() -> None:
    from simulation.mesh import CLASSES

    assert tuple(CLASSES) == SEMANTIC_CLASSES
    assert SEMANTIC_CLASS_COLORS.shape == (len(SEMANTIC_CLASSES), 3)
    assert SemanticMapConfig().num_classes == len(SEMANTIC_CLASSES)


def test_geometry_in_a_box_is_the_whole_maps_geometry_there() -> None:
    """The ICP gate's per-cloud query: the same means and normals as the whole map's, for the
    occupied voxels with centres in the box (computed without the rest of the map)."""
    m = busy_map()
    lo, hi = np.array([0.2, 0.1, -0.1]), np.array([0.7, 0.8, 0.3])
    means, normals = m.geometry_in_box(lo, hi)
    c = m.voxel_centers()
    inside = m.occupied() & np.all((c >= lo) & (c <= hi), axis=1)
    assert 0 < inside.sum() < len(m)
    np.testing.assert_array_equal(means, m.means()[inside])
    np.testing.assert_allclose(normals, m.normals()[inside], equal_nan=True)
    cached_means, cached_normals = m.geometry_in_box(lo, hi)  # now from the normals cache
    np.testing.assert_array_equal(cached_means, means)
    np.testing.assert_allclose(cached_normals, normals, equal_nan=True)
