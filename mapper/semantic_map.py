"""The semantic voxel map: Bayesian fusion of semantic point clouds (numpy only).

A sparse voxel grid in the world (map) frame, metres, with cubic voxels of edge
``voxel_size_m``. Voxel ``(i, j, k)`` covers ``[i, i + 1) * voxel_size_m`` on x (likewise y, z);
its centre is ``(i + 0.5) * voxel_size_m``. A voxel exists once a point (observed or from the
prior model) fell into it; free-space carving never creates voxels.

Per voxel the map keeps:

- class log-probabilities ``(C,)`` float32, normalised (log-sum-exp) after every update and
  bounded below by ``class_log_prob_clamp`` so that a confident voxel can still change its mind;
  uniform (``-log C``) until the first semantic observation (``has_semantics`` false);
- occupancy as counts per scan: ``hits`` (+1 per :meth:`SemanticVoxelMap.integrate` call that
  put at least one point in the voxel) and ``misses`` (+1 per call whose free-space rays crossed
  the voxel without a point of that call in it);
- geometry: point count, the sums of the points' offsets ``d = p - centre`` and of their outer
  products (offsets from the voxel centre keep the float64 sums well conditioned), from which
  the mean position and the normal (eigenvector of the smallest eigenvalue of the covariance)
  follow;
- whether it came from the prior geometric model (:meth:`SemanticVoxelMap.add_prior_geometry`,
  the paper's map of the empty room without semantics) and the sum of the prior normals given.

Storage: per-voxel arrays in insertion order (rows), grown by doubling; a sorted array of
int64-packed voxel keys with the row of each key finds existing voxels with ``np.searchsorted``.
Every query returns arrays in row order (the same order for every query of one map state).

Semantic fusion of one call (one scan): each point gives a likelihood over the C classes, either
the class probabilities of the segmentation (``class_probs``, floored at
``min_class_probability``) or a top-1 label with confidence c (``log c`` for the label,
``log((1 - c) / (C - 1))`` for the others, c clipped to ``[1/C + eps, 1 - eps]``). The points
of one voxel in one scan are summed (``evidence="sum"``, independent points) or averaged
(``evidence="mean"``, the default: the scan is one observation of the voxel, so the result does
not depend on point density and a majority of scans wins); the voxel's log-probabilities get that
added and are re-normalised. Everything is vectorised over points and voxels.

The map's state goes in and out as plain arrays (:meth:`SemanticVoxelMap.state_arrays`,
:meth:`SemanticVoxelMap.from_state_arrays`); files (the ``.npz`` snapshot, PLY export, prior
models) are :mod:`mapper.map_io`'s.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping
from typing import Final

import numpy as np

from protocol.errors import SmartedgeError
from protocol.semantic_classes import NUM_SEMANTIC_CLASSES

logger = logging.getLogger(__name__)

_AXIS_BITS: Final = 21
_AXIS_OFFSET: Final = 1 << (_AXIS_BITS - 1)  # voxel indices in [-2**20, 2**20)
_AXIS_MASK: Final = (1 << _AXIS_BITS) - 1
#: Ray samples processed at once while carving (bounds the temporary memory to ~100 MB).
_CARVE_CHUNK_SAMPLES: Final = 1 << 20
#: Largest dense grid of rows built for carving (4 bytes a cell); bigger ray boxes look up keys.
_CARVE_GRID_MAX_CELLS: Final = 1 << 24
_EVIDENCE_MODES: Final = ("mean", "sum")

#: The per-voxel state by public name (:meth:`SemanticVoxelMap.state_arrays`) → attribute.
_STATE_ATTRS: Final = {
    "keys": "_keys", "log_probs": "_log_probs", "hits": "_hits", "misses": "_misses",
    "point_count": "_count", "sum_d": "_sum_d", "sum_dd": "_sum_dd", "semantic": "_semantic",
    "prior": "_prior", "prior_normal_sum": "_prior_normal_sum",
}
#: Names of the per-voxel state arrays, in :meth:`SemanticVoxelMap.state_arrays` order.
STATE_FIELDS: Final = tuple(_STATE_ATTRS)


def _state_layout(num_classes: int) -> dict[str, tuple[tuple[int, ...], type]]:
    """Per state field: the trailing shape of its (K, ...) array and its dtype."""
    return {
        "keys": ((), np.int64), "log_probs": ((num_classes,), np.float32),
        "hits": ((), np.uint32), "misses": ((), np.uint32), "point_count": ((), np.int64),
        "sum_d": ((3,), np.float64), "sum_dd": ((6,), np.float64), "semantic": ((), np.bool_),
        "prior": ((), np.bool_), "prior_normal_sum": ((3,), np.float64),
    }


class MapError(SmartedgeError, ValueError):
    """Bad input to the semantic map or the cloud alignment (shape, values, configuration) or
    a bad map file; the message names the field or the file and what is wrong."""


@dataclasses.dataclass(frozen=True)
class SemanticMapConfig:
    """Parameters of :class:`SemanticVoxelMap`.

    ``voxel_size_m``: voxel edge, metres. ``num_classes``: C, the number of semantic classes
    (ids ``0 .. C-1``; default: the legend of :mod:`protocol.semantic_classes`).
    ``max_range_m``: points farther than this from the sensor origin are dropped (only when an
    origin is given). ``confidence_eps``: top-1 confidences are clipped to
    ``[1/C + eps, 1 - eps]``. ``min_class_probability``: floor of ``class_probs`` before the
    log. ``class_log_prob_clamp``: lower bound of a voxel's class log-probabilities (nats).
    ``evidence``: how the points of one voxel in one scan combine, ``"mean"`` or ``"sum"`` (see
    the module docstring). ``carve_free_space``: cast rays from the sensor origin and count
    misses (costly; see ``smartedge bench map``).
    """

    voxel_size_m: float = 0.05
    num_classes: int = NUM_SEMANTIC_CLASSES
    max_range_m: float = 8.0
    confidence_eps: float = 1e-3
    min_class_probability: float = 1e-4
    class_log_prob_clamp: float = -20.0
    evidence: str = "mean"
    carve_free_space: bool = False

    def __post_init__(self) -> None:
        def bad(field: str, reason: str) -> MapError:
            return MapError(f"semantic map config: {field}: {reason}")

        for name in ("voxel_size_m", "max_range_m", "confidence_eps", "min_class_probability",
                     "class_log_prob_clamp"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise bad(name, f"must be a number, got {value!r}")
        if isinstance(self.num_classes, bool) or not isinstance(self.num_classes, int):
            raise bad("num_classes", f"must be an integer, got {self.num_classes!r}")
        if not 2 <= self.num_classes <= 65536:
            raise bad("num_classes", f"must be in [2, 65536], got {self.num_classes}")
        if not (math.isfinite(self.voxel_size_m) and 1e-4 <= self.voxel_size_m <= 10.0):
            raise bad("voxel_size_m", f"must be in [1e-4, 10] m, got {self.voxel_size_m}")
        if not self.max_range_m > 0.0:  # inf allowed: no range limit
            raise bad("max_range_m", f"must be > 0 m, got {self.max_range_m}")
        eps_max = 0.5 * (1.0 - 1.0 / self.num_classes)
        if not 0.0 < self.confidence_eps < eps_max:
            raise bad("confidence_eps", f"must be in (0, {eps_max:.3g}), got "
                                        f"{self.confidence_eps}")
        if not 0.0 < self.min_class_probability <= 1.0 / self.num_classes:
            raise bad("min_class_probability",
                      f"must be in (0, 1/num_classes], got {self.min_class_probability}")
        uniform = -math.log(self.num_classes)
        if not (math.isfinite(self.class_log_prob_clamp) and self.class_log_prob_clamp < uniform):
            raise bad("class_log_prob_clamp",
                      f"must be finite and < -log(num_classes) = {uniform:.3f}, got "
                      f"{self.class_log_prob_clamp}")
        if self.evidence not in _EVIDENCE_MODES:
            raise bad("evidence", f"must be one of {_EVIDENCE_MODES}, got {self.evidence!r}")
        if not isinstance(self.carve_free_space, bool):
            raise bad("carve_free_space", f"must be true or false, got {self.carve_free_space!r}")


@dataclasses.dataclass(frozen=True)
class IntegrateReport:
    """What one :meth:`SemanticVoxelMap.integrate` call did.

    ``points_in``: points given; ``points_out_of_range``: dropped beyond ``max_range_m``;
    ``points_fused``: the rest; ``voxels_updated``: voxels that got points (``voxels_created``
    of them new); ``voxels_carved``: existing voxels whose misses went up;
    ``rays``/``ray_samples``: free-space rays cast (one per updated voxel) and samples taken.
    """

    points_in: int
    points_out_of_range: int
    points_fused: int
    voxels_updated: int
    voxels_created: int
    voxels_carved: int = 0
    rays: int = 0
    ray_samples: int = 0


# ----------------------------------------------------------------------------------------------
# voxel keys


def pack_voxel_keys(indices: np.ndarray) -> np.ndarray:
    """(N, 3) int64 voxel indices in ``[-2**20, 2**20)`` → (N,) int64 keys (21 bits per axis,
    x in the high bits), ordered like the index triples."""
    biased = indices + _AXIS_OFFSET
    return (biased[:, 0] << (2 * _AXIS_BITS)) | (biased[:, 1] << _AXIS_BITS) | biased[:, 2]


def unpack_voxel_keys(keys: np.ndarray) -> np.ndarray:
    """(N,) int64 keys → (N, 3) int64 voxel indices (inverse of :func:`pack_voxel_keys`)."""
    keys = np.asarray(keys, dtype=np.int64)
    out = np.empty((len(keys), 3), dtype=np.int64)
    out[:, 0] = (keys >> (2 * _AXIS_BITS)) & _AXIS_MASK
    out[:, 1] = (keys >> _AXIS_BITS) & _AXIS_MASK
    out[:, 2] = keys & _AXIS_MASK
    out -= _AXIS_OFFSET
    return out


# ----------------------------------------------------------------------------------------------
# input checks (all before any change of the map)


def _check_points(points: object, field: str) -> np.ndarray:
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise MapError(f"{field}: expected shape (N, 3), got {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise MapError(f"{field}: expected a float array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if not np.isfinite(arr).all():
        bad = int(np.count_nonzero(~np.isfinite(arr).all(axis=1)))
        raise MapError(f"{field}: {bad} of {len(arr)} points are not finite (NaN or inf)")
    return arr


def _check_vector3(value: object, field: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.shape != (3,) or arr.dtype.kind not in "fiu":
        raise MapError(f"{field}: expected a (3,) float array, got shape {arr.shape} "
                       f"dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise MapError(f"{field}: not finite: {arr.tolist()}")
    return arr


def _check_top1(class_ids: object, confidences: object, n: int,
                num_classes: int) -> tuple[np.ndarray, np.ndarray]:
    ids = np.asarray(class_ids)
    if ids.shape != (n,):
        raise MapError(f"class_ids: expected shape ({n},), got {ids.shape}")
    if ids.dtype.kind not in "iu":
        raise MapError(f"class_ids: expected an integer array, got dtype {ids.dtype}")
    if n:
        lo, hi = int(ids.min()), int(ids.max())
        if lo < 0 or hi >= num_classes:
            raise MapError(f"class_ids: ids must be in [0, {num_classes - 1}], got "
                           f"{lo if lo < 0 else hi}")
    conf = np.asarray(confidences)
    if conf.shape != (n,):
        raise MapError(f"confidences: expected shape ({n},), got {conf.shape}")
    if conf.dtype.kind not in "fiu":
        raise MapError(f"confidences: expected a float array, got dtype {conf.dtype}")
    conf = conf.astype(np.float64, copy=False)
    if n and not (np.isfinite(conf).all() and conf.min() >= 0.0 and conf.max() <= 1.0):
        raise MapError("confidences: must be finite and in [0, 1]")
    return ids.astype(np.intp, copy=False), conf


def _check_probs(class_probs: object, n: int, num_classes: int) -> np.ndarray:
    probs = np.asarray(class_probs)
    if probs.shape != (n, num_classes):
        raise MapError(f"class_probs: expected shape ({n}, {num_classes}), got {probs.shape}")
    if probs.dtype.kind != "f":
        raise MapError(f"class_probs: expected a float array, got dtype {probs.dtype}")
    if n:
        if not (np.isfinite(probs).all() and probs.min() >= 0.0 and probs.max() <= 1.0):
            raise MapError("class_probs: must be finite and in [0, 1]")
        sums = probs.sum(axis=1, dtype=np.float64)
        worst = float(np.max(np.abs(sums - 1.0)))
        if worst > 1e-2:
            raise MapError(f"class_probs: rows must sum to 1 (worst row sums to "
                           f"{1.0 + worst:.4f} or {1.0 - worst:.4f})")
    return probs


def _farthest_corner_m(points: np.ndarray, origin: np.ndarray) -> float:
    """Distance from ``origin`` to the farthest corner of the points' bounding box (an upper
    bound of the farthest point's distance)."""
    lo, hi = _column_bounds(points)
    return float(np.linalg.norm(np.maximum(np.abs(lo - origin), np.abs(hi - origin))))


def _column_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis (3,) minimum and maximum of (N, 3) points, N >= 1 (column by column: numpy
    reduces an (N, 3) array over axis 0 an order of magnitude slower)."""
    lo = np.array([points[:, a].min() for a in range(3)])
    hi = np.array([points[:, a].max() for a in range(3)])
    return lo, hi


# ----------------------------------------------------------------------------------------------
# the map


class SemanticVoxelMap:
    """Sparse semantic voxel map in the world (map) frame; see the module docstring.

    Not thread-safe: one owner (the mapper's worker) mutates it.
    """

    __hash__ = None  # type: ignore[assignment]  # mutable, compared by content

    # per-voxel storage, rows [0, len) in use, capacity rows allocated (see _allocate)
    _keys: np.ndarray  # (cap,) int64 packed voxel key
    _log_probs: np.ndarray  # (cap, C) float32
    _hits: np.ndarray  # (cap,) uint32
    _misses: np.ndarray  # (cap,) uint32
    _count: np.ndarray  # (cap,) int64 points
    _sum_d: np.ndarray  # (cap, 3) float64, m
    _sum_dd: np.ndarray  # (cap, 6) float64, m²
    _semantic: np.ndarray  # (cap,) bool
    _prior: np.ndarray  # (cap,) bool
    _prior_normal_sum: np.ndarray  # (cap, 3) float64

    def __init__(self, config: SemanticMapConfig | None = None, *, capacity: int = 1024) -> None:
        self.config = config if config is not None else SemanticMapConfig()
        if not isinstance(self.config, SemanticMapConfig):
            raise MapError(f"config: expected a SemanticMapConfig, got {type(config).__name__}")
        self._n = 0
        self._allocate(max(1, int(capacity)))
        self._index_keys = np.zeros(0, dtype=np.int64)  # sorted voxel keys
        self._index_rows = np.zeros(0, dtype=np.int64)  # row of each sorted key
        self._normals_cache: np.ndarray | None = None

    # -- storage -------------------------------------------------------------------------------

    def _allocate(self, capacity: int) -> None:
        c = self.config.num_classes
        old = self.__dict__.get("_keys")
        n = self._n if old is not None else 0
        for field, (tail, dtype) in _state_layout(c).items():
            name = _STATE_ATTRS[field]
            fill = -math.log(c) if field == "log_probs" else 0  # uniform classes, zero counts
            arr: np.ndarray = np.full((capacity, *tail), fill, dtype=dtype)
            if old is not None:
                arr[:n] = getattr(self, name)[:n]
            setattr(self, name, arr)
        self._capacity = capacity

    def _lookup(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows of the sorted, unique ``keys`` (V,) and whether each exists (V,) bool (row -1
        where not)."""
        if len(self._index_keys) == 0:
            return np.full(len(keys), -1, dtype=np.int64), np.zeros(len(keys), dtype=bool)
        pos = np.searchsorted(self._index_keys, keys)
        pos_c = np.minimum(pos, len(self._index_keys) - 1)
        found = self._index_keys[pos_c] == keys
        rows = np.where(found, self._index_rows[pos_c], -1)
        return rows, found

    def _rows_for(self, keys: np.ndarray) -> tuple[np.ndarray, int]:
        """Rows of the sorted, unique ``keys`` (V,), creating the missing voxels (uniform
        class log-probabilities, zero counts). Returns the rows and how many were created."""
        rows, found = self._lookup(keys)
        new_keys = keys[~found]
        m = len(new_keys)
        if m == 0:
            return rows, 0
        if self._n + m > self._capacity:
            self._allocate(max(2 * self._capacity, self._n + m))
        new_rows = np.arange(self._n, self._n + m, dtype=np.int64)
        self._keys[new_rows] = new_keys
        rows[~found] = new_rows
        # merge the new keys into the sorted index, O(K + m)
        k = len(self._index_keys)
        at = np.searchsorted(self._index_keys, new_keys) + np.arange(m)
        merged_keys = np.empty(k + m, dtype=np.int64)
        merged_rows = np.empty(k + m, dtype=np.int64)
        old_slots = np.ones(k + m, dtype=bool)
        old_slots[at] = False
        merged_keys[at], merged_rows[at] = new_keys, new_rows
        merged_keys[old_slots], merged_rows[old_slots] = self._index_keys, self._index_rows
        self._index_keys, self._index_rows = merged_keys, merged_rows
        self._n += m
        return rows, m

    def _voxel_indices_of(self, points: np.ndarray, field: str) -> np.ndarray:
        idx = np.floor(points * (1.0 / self.config.voxel_size_m)).astype(np.int64)
        if len(idx) and (idx.min() < -_AXIS_OFFSET or idx.max() >= _AXIS_OFFSET):
            limit = _AXIS_OFFSET * self.config.voxel_size_m
            raise MapError(f"{field}: coordinates beyond the map's extent of ±{limit:.0f} m")
        return idx

    def _accumulate_geometry(self, rows: np.ndarray, inv: np.ndarray, counts: np.ndarray,
                             offsets: np.ndarray) -> None:
        """Add the points' offsets from their voxel centres (N, 3), grouped by ``inv`` (N,)
        into the voxels ``rows`` (V,), to the geometry sums."""
        v = len(rows)
        d = np.ascontiguousarray(offsets.T)  # (3, N): contiguous columns for bincount
        sum_d = np.empty((v, 3))
        sum_dd = np.empty((v, 6))
        for a in range(3):
            sum_d[:, a] = np.bincount(inv, weights=d[a], minlength=v)
        for col, (a, b) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
            sum_dd[:, col] = np.bincount(inv, weights=d[a] * d[b], minlength=v)
        self._count[rows] += counts
        self._sum_d[rows] += sum_d
        self._sum_dd[rows] += sum_dd
        self._normals_cache = None

    # -- building ------------------------------------------------------------------------------

    @classmethod
    def from_prior_points(cls, points_world: np.ndarray, config: SemanticMapConfig | None = None,
                          normals: np.ndarray | None = None) -> SemanticVoxelMap:
        """A map initialised from a prior geometric model of the site (points sampled on its
        surfaces, (N, 3) world metres; optional (N, 3) surface normals): occupied voxels
        without semantics. See :meth:`add_prior_geometry`."""
        out = cls(config)
        out.add_prior_geometry(points_world, normals)
        return out

    def add_prior_geometry(self, points_world: np.ndarray,
                           normals: np.ndarray | None = None) -> int:
        """Mark the voxels of the prior model's points (N, 3) world metres as prior (occupied,
        no semantics) and add the points to their geometry; ``normals`` (N, 3), any length,
        orient the voxels' normals and stand in where a voxel has too few points for one.
        Returns the number of voxels created. Raises :class:`MapError` (map unchanged) on bad
        input."""
        pts = _check_points(points_world, "points_world")
        nrm = None
        if normals is not None:
            nrm = _check_points(normals, "normals")
            if len(nrm) != len(pts):
                raise MapError(f"normals: expected {len(pts)} rows, got {len(nrm)}")
        idx = self._voxel_indices_of(pts, "points_world")
        if len(pts) == 0:
            return 0
        keys = pack_voxel_keys(idx)
        ukeys, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
        rows, created = self._rows_for(ukeys)
        offsets = pts - (idx + 0.5) * self.config.voxel_size_m
        self._accumulate_geometry(rows, inv, counts, offsets)
        self._prior[rows] = True
        if nrm is not None:
            lengths = np.linalg.norm(nrm, axis=1, keepdims=True)
            unit = np.divide(nrm, lengths, out=np.zeros_like(nrm), where=lengths > 0)
            for a in range(3):
                self._prior_normal_sum[rows, a] += np.bincount(inv, weights=unit[:, a],
                                                               minlength=len(rows))
        logger.debug("prior geometry: %d points, %d voxels (%d new)", len(pts), len(rows),
                     created)
        return created

    def integrate(
        self,
        points_world: np.ndarray,
        class_ids: np.ndarray | None = None,
        confidences: np.ndarray | None = None,
        *,
        class_probs: np.ndarray | None = None,
        sensor_origin_world: np.ndarray | None = None,
    ) -> IntegrateReport:
        """Fuse one semantic scan.

        ``points_world`` (N, 3) float, world frame, metres; semantics either as ``class_ids``
        (N,) int in ``[0, C)`` with ``confidences`` (N,) in [0, 1] (top-1), or as
        ``class_probs`` (N, C) with rows summing to 1. ``sensor_origin_world`` (3,) metres: the
        sensor's position; with it, points beyond ``max_range_m`` are dropped and, when
        ``carve_free_space`` is set, free-space rays are cast.

        Raises :class:`MapError` and leaves the map unchanged on any bad input (shapes, NaN or
        inf, class ids out of range, confidences outside [0, 1]).
        """
        cfg = self.config
        pts = _check_points(points_world, "points_world")
        n_in = len(pts)
        probs = ids = conf = None
        if class_probs is not None:
            if class_ids is not None or confidences is not None:
                raise MapError("class_probs: give either class_probs or class_ids + "
                               "confidences, not both")
            probs = _check_probs(class_probs, n_in, cfg.num_classes)
        elif class_ids is None or confidences is None:
            raise MapError("class_ids: give class_ids and confidences (or class_probs)")
        else:
            ids, conf = _check_top1(class_ids, confidences, n_in, cfg.num_classes)
        origin = None
        if sensor_origin_world is not None:
            origin = _check_vector3(sensor_origin_world, "sensor_origin_world")
            if math.isfinite(cfg.max_range_m) and n_in and _farthest_corner_m(
                    pts, origin) > cfg.max_range_m:
                rel = pts - origin
                keep = np.einsum("ij,ij->i", rel, rel) <= cfg.max_range_m**2
                if not keep.all():
                    pts = pts[keep]
                    if probs is not None:
                        probs = probs[keep]
                    else:
                        ids, conf = ids[keep], conf[keep]  # type: ignore[index]
        idx = self._voxel_indices_of(pts, "points_world")
        n = len(pts)
        if n == 0:
            return IntegrateReport(n_in, n_in - n, 0, 0, 0)
        # -- validated; from here on the map changes --
        keys = pack_voxel_keys(idx)
        ukeys, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
        inv = inv.reshape(-1)
        v = len(ukeys)
        evidence = self._evidence(inv, counts, ids, conf, probs)
        offsets = pts - (idx + 0.5) * cfg.voxel_size_m

        carved = rays = samples = 0
        if cfg.carve_free_space and origin is not None and self._n:
            centers = (unpack_voxel_keys(ukeys) + 0.5) * cfg.voxel_size_m
            ends = centers + np.stack(
                [np.bincount(inv, weights=offsets[:, a], minlength=v) for a in range(3)], axis=1
            ) / counts[:, None]
            carved, samples = self._carve(origin, ends, ukeys)
            rays = v

        rows, created = self._rows_for(ukeys)
        self._accumulate_geometry(rows, inv, counts, offsets)
        self._hits[rows] += np.uint32(1)
        # (C, V): reductions over the classes run along the long axis
        lp = self._log_probs[rows].T + evidence
        lp -= lp.max(axis=0)
        lp -= np.log(np.exp(lp).sum(axis=0))
        np.maximum(lp, np.float32(cfg.class_log_prob_clamp), out=lp)
        self._log_probs[rows] = lp.T
        self._semantic[rows] = True
        report = IntegrateReport(n_in, n_in - n, n, v, created, carved, rays, samples)
        logger.debug("integrated %s", report)
        return report

    def _evidence(self, inv: np.ndarray, counts: np.ndarray, ids: np.ndarray | None,
                  conf: np.ndarray | None, probs: np.ndarray | None) -> np.ndarray:
        """(C, V) float32 log-likelihood of each class per voxel of this scan (up to a constant
        per voxel, which the normalisation removes), summed in float64."""
        cfg = self.config
        c = cfg.num_classes
        v = len(counts)
        out: np.ndarray
        if probs is None:
            assert ids is not None and conf is not None
            conf = np.clip(conf, 1.0 / c + cfg.confidence_eps, 1.0 - cfg.confidence_eps)
            log_label = np.log(conf)
            log_other = np.log((1.0 - conf) / (c - 1))
            out = np.bincount(ids * v + inv, weights=log_label - log_other,
                              minlength=v * c).reshape(c, v)
            out += np.bincount(inv, weights=log_other, minlength=v)
        else:
            log_p = np.log(np.clip(probs, cfg.min_class_probability, 1.0)).astype(np.float64)
            log_p = np.ascontiguousarray(log_p.T)
            out = np.empty((c, v))
            for k in range(c):
                out[k] = np.bincount(inv, weights=log_p[k], minlength=v)
        if cfg.evidence == "mean":
            out /= counts
        return out.astype(np.float32)

    def _carve(self, origin: np.ndarray, ends: np.ndarray,
               hit_keys: np.ndarray) -> tuple[int, int]:
        """Count a miss for every existing voxel crossed by a ray ``origin`` → ``ends`` (R, 3)
        world metres, sampled every half voxel and stopping one voxel before the end, except
        the voxels ``hit_keys`` of this scan. Returns (voxels carved, samples taken).

        The map's voxels inside the rays' bounding box go into a dense grid of rows (bounded
        by ``_CARVE_GRID_MAX_CELLS``; beyond it the samples are looked up by key), so a sample
        costs one array read."""
        vs = self.config.voxel_size_m
        base = np.floor(origin / vs)  # sensor voxel; samples are computed relative to it
        o = origin / vs - base
        vec = (ends - origin) / vs
        dist = np.sqrt(np.einsum("ij,ij->i", vec, vec))
        # samples at t = 0, 0.5, 1, ... voxels while t <= dist - 1 voxel
        n_samples = np.maximum(np.floor(2.0 * (dist - 1.0)).astype(np.int64) + 1, 0)
        total = int(n_samples.sum())
        if total == 0:
            return 0, 0
        ends_lo, ends_hi = _column_bounds(o + vec)
        lo = np.floor(np.minimum(o, ends_lo)).astype(np.int64) - 1
        hi = np.floor(np.maximum(o, ends_hi)).astype(np.int64) + 1
        shape = hi - lo + 1
        lo_abs = lo + base.astype(np.int64)  # absolute voxel index of the box's corner
        grid = None
        if int(np.prod(shape)) <= _CARVE_GRID_MAX_CELLS:
            grid = self._row_grid(lo_abs, shape)
            if grid is None:
                return 0, total  # no map voxel near the rays
        dirs = (vec / np.maximum(dist, 1e-12)[:, None]).astype(np.float32)
        o32 = o.astype(np.float32)
        order = np.argsort(-n_samples, kind="stable")  # long rays first: chunks of like length
        order = order[n_samples[order] > 0]
        missed = np.zeros(self._n, dtype=bool)
        first = 0
        while first < len(order):
            k_max = int(n_samples[order[first]])
            last = min(len(order), first + max(1, _CARVE_CHUNK_SAMPLES // k_max))
            rays = order[first:last]
            t = np.arange(k_max, dtype=np.float32) * np.float32(0.5)
            valid = np.arange(k_max)[None, :] < n_samples[rays, None]
            # int32 is exact here: a cell index is < _CARVE_GRID_MAX_CELLS or the box is small
            cell = [
                np.floor(o32[a] + dirs[rays, a, None] * t[None, :]).astype(np.int32)
                - np.int32(lo[a])
                for a in range(3)
            ]
            if grid is not None:
                flat = (cell[0] * np.int32(shape[1]) + cell[1]) * np.int32(shape[2]) + cell[2]
                rows = grid[flat[valid]]
                missed[rows[rows >= 0]] = True
            else:
                rel = np.stack([c[valid] for c in cell], axis=1).astype(np.int64)
                keys = pack_voxel_keys(rel + lo_abs)
                fresh = np.ones(len(keys), dtype=bool)  # consecutive samples share voxels
                fresh[1:] = keys[1:] != keys[:-1]
                rows, found = self._lookup(keys[fresh])
                missed[rows[found]] = True
            first = last
        hit_rows, hit_found = self._lookup(hit_keys)
        missed[hit_rows[hit_found]] = False
        self._misses[: self._n][missed] += np.uint32(1)
        return int(np.count_nonzero(missed)), total

    def _row_grid(self, lo: np.ndarray, shape: np.ndarray) -> np.ndarray | None:
        """Flat dense grid (prod(shape),) int32 of the rows of the voxels with indices in
        ``[lo, lo + shape)`` (-1 where none); None when there is none."""
        hi = lo + shape - 1
        # keys are ordered by x first: the voxels with x in [lo_x, hi_x] are one slice
        x_lo, x_hi = np.clip([lo[0], hi[0]], -_AXIS_OFFSET, _AXIS_OFFSET - 1)
        bounds = pack_voxel_keys(np.array([[x_lo, -_AXIS_OFFSET, -_AXIS_OFFSET],
                                           [x_hi, _AXIS_OFFSET - 1, _AXIS_OFFSET - 1]]))
        span = slice(int(np.searchsorted(self._index_keys, bounds[0], side="left")),
                     int(np.searchsorted(self._index_keys, bounds[1], side="right")))
        idx = unpack_voxel_keys(self._index_keys[span]) - lo
        inside = ((idx >= 0) & (idx < shape)).all(axis=1)
        if not inside.any():
            return None
        idx = idx[inside]
        grid = np.full(int(np.prod(shape)), -1, dtype=np.int32)
        grid[(idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2]] = (
            self._index_rows[span][inside])
        return grid

    # -- queries (arrays in row order) ---------------------------------------------------------

    def __len__(self) -> int:
        return self._n

    def keys(self) -> np.ndarray:
        """(K,) int64 packed voxel keys (see :func:`pack_voxel_keys`)."""
        return self._keys[: self._n].copy()

    def voxel_indices(self) -> np.ndarray:
        """(K, 3) int64 voxel indices."""
        return unpack_voxel_keys(self._keys[: self._n])

    def voxel_centers(self) -> np.ndarray:
        """(K, 3) float64 voxel centres, world frame, metres."""
        return (self.voxel_indices() + 0.5) * self.config.voxel_size_m

    def means(self) -> np.ndarray:
        """(K, 3) float64 mean position of the points in each voxel, world frame, metres."""
        n = self._n
        return self.voxel_centers() + self._sum_d[:n] / self._count[:n, None]

    def point_counts(self) -> np.ndarray:
        """(K,) int64 points (observed and prior) that fell into each voxel."""
        return self._count[: self._n].copy()

    def hits(self) -> np.ndarray:
        """(K,) uint32 scans that put points into each voxel."""
        return self._hits[: self._n].copy()

    def misses(self) -> np.ndarray:
        """(K,) uint32 scans whose free-space rays crossed each voxel."""
        return self._misses[: self._n].copy()

    def is_prior(self) -> np.ndarray:
        """(K,) bool: the voxel holds points of the prior model."""
        return self._prior[: self._n].copy()

    def has_semantics(self) -> np.ndarray:
        """(K,) bool: the voxel got at least one semantic observation."""
        return self._semantic[: self._n].copy()

    def occupied(self) -> np.ndarray:
        """(K,) bool: prior voxel, or more hits than misses."""
        n = self._n
        return self._prior[:n] | (self._hits[:n] > self._misses[:n])

    def log_probs(self) -> np.ndarray:
        """(K, C) float32 normalised class log-probabilities (uniform without semantics)."""
        return self._log_probs[: self._n].copy()

    def probabilities(self) -> np.ndarray:
        """(K, C) float32 class probabilities."""
        return np.exp(self._log_probs[: self._n])

    def labels(self) -> np.ndarray:
        """(K,) int64 most probable class id per voxel; -1 where the voxel has no semantics."""
        n = self._n
        out = np.argmax(self._log_probs[:n], axis=1).astype(np.int64)
        out[~self._semantic[:n]] = -1
        return out

    def confidence(self) -> np.ndarray:
        """(K,) float32 probability of the most probable class (1/C without semantics)."""
        return np.exp(self._log_probs[: self._n].max(axis=1))

    def coverage(self, surface_mask: np.ndarray | None = None) -> float:
        """Share of the surface voxels that have semantic information, in [0, 1] (NaN when
        there are none). Surface voxels: ``surface_mask`` (K,) bool, default the prior
        voxels."""
        n = self._n
        mask = self._prior[:n] if surface_mask is None else np.asarray(surface_mask)
        if mask.shape != (n,) or mask.dtype != np.bool_:
            raise MapError(f"surface_mask: expected a ({n},) bool array, got {mask.shape} "
                           f"{mask.dtype}")
        total = int(np.count_nonzero(mask))
        if total == 0:
            return float("nan")
        return int(np.count_nonzero(mask & self._semantic[:n])) / total

    def normals(self) -> np.ndarray:
        """(K, 3) float64 unit surface normals, world frame: the covariance's eigenvector of
        the smallest eigenvalue where the voxel has >= 3 points spread over a surface (second
        eigenvalue above (1e-3 voxel)²), else the prior normal, else NaN. Oriented along the
        prior normal where there is one (sign otherwise arbitrary). Cached until the next
        change."""
        if self._normals_cache is None:
            self._normals_cache = self._compute_normals()
        return self._normals_cache.copy()

    def geometry_in_box(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Means and normals ((V, 3) each, world metres / unit vectors; see :meth:`means` and
        :meth:`normals`) of the occupied voxels whose centres lie in the axis-aligned box
        ``[lo, hi]`` (3,) world metres. Costs O(K) for the selection and the normals only of
        the voxels in the box (the ICP gate's per-cloud query: a whole map's normals take
        ~0.5 s at 350k voxels)."""
        n = self._n
        centres = self.voxel_centers()
        inside = self.occupied()
        for a in range(3):
            inside &= (centres[:, a] >= lo[a]) & (centres[:, a] <= hi[a])
        rows = np.flatnonzero(inside)
        means = centres[rows] + self._sum_d[rows] / self._count[rows, None]
        if self._normals_cache is not None and len(self._normals_cache) == n:
            return means, self._normals_cache[rows].copy()
        return means, self._compute_normals(rows)

    def _compute_normals(self, rows: np.ndarray | None = None) -> np.ndarray:
        """Normals of all voxels, or of ``rows`` (in that order)."""
        sel = slice(0, self._n) if rows is None else rows
        count = self._count[sel].astype(np.float64)
        n = len(count)
        safe = np.maximum(count, 1.0)
        mean = self._sum_d[sel] / safe[:, None]
        s = self._sum_dd[sel] / safe[:, None]
        cov = np.empty((n, 3, 3))
        for col, (a, b) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
            cov[:, a, b] = cov[:, b, a] = s[:, col] - mean[:, a] * mean[:, b]
        out = np.full((n, 3), np.nan)
        if n == 0:
            return out
        eigval, eigvec = np.linalg.eigh(cov)
        ok = (count >= 3) & (eigval[:, 1] > (1e-3 * self.config.voxel_size_m) ** 2)
        out[ok] = eigvec[ok, :, 0]
        hint = self._prior_normal_sum[sel]
        hint_len = np.linalg.norm(hint, axis=1)
        has_hint = hint_len > 1e-9
        hint_unit = np.divide(hint, hint_len[:, None], out=np.zeros_like(hint),
                              where=has_hint[:, None])
        with np.errstate(invalid="ignore"):
            flip = ok & has_hint & (np.einsum("ij,ij->i", out, hint_unit) < 0)
        out[flip] *= -1.0
        use_hint = ~ok & has_hint
        out[use_hint] = hint_unit[use_hint]
        return out

    # -- identity ------------------------------------------------------------------------------

    _STATE: Final = tuple(_STATE_ATTRS.values())

    def copy(self) -> SemanticVoxelMap:
        """A deep copy."""
        out = SemanticVoxelMap(self.config, capacity=max(self._n, 1))
        for name in self._STATE:
            getattr(out, name)[: self._n] = getattr(self, name)[: self._n]
        out._n = self._n
        out._index_keys = self._index_keys.copy()
        out._index_rows = self._index_rows.copy()
        return out

    def subset(self, mask: np.ndarray) -> SemanticVoxelMap:
        """A new map with the voxels where ``mask`` (K,) bool is true (same configuration,
        their state copied, in row order)."""
        mask = np.asarray(mask)
        if mask.shape != (self._n,) or mask.dtype != np.bool_:
            raise MapError(f"mask: expected a ({self._n},) bool array, got {mask.shape} "
                           f"{mask.dtype}")
        rows = np.flatnonzero(mask)
        m = len(rows)
        out = SemanticVoxelMap(self.config, capacity=max(m, 1))
        for name in self._STATE:
            getattr(out, name)[:m] = getattr(self, name)[rows]
        out._n = m
        order = np.argsort(out._keys[:m], kind="stable")
        out._index_keys = out._keys[:m][order].copy()
        out._index_rows = order.astype(np.int64)
        return out

    def equals(self, other: SemanticVoxelMap) -> bool:
        """Exact equality: same configuration, same voxels in the same rows, bitwise equal
        per-voxel state."""
        if not isinstance(other, SemanticVoxelMap):
            return False
        if self.config != other.config or self._n != other._n:
            return False
        n = self._n
        return all(
            getattr(self, name)[:n].tobytes() == getattr(other, name)[:n].tobytes()
            for name in self._STATE
        )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SemanticVoxelMap):
            return NotImplemented
        return self.equals(other)

    def __repr__(self) -> str:
        return (f"SemanticVoxelMap({self._n} voxels, voxel {self.config.voxel_size_m} m, "
                f"{self.config.num_classes} classes)")

    # -- state (what a map file holds; see mapper.map_io) --------------------------------------

    def state_arrays(self) -> dict[str, np.ndarray]:
        """The per-voxel state, copies in row order (K voxels, C classes), by the names of
        :data:`STATE_FIELDS`: ``keys`` (K,) int64 packed voxel keys (:func:`pack_voxel_keys`),
        ``log_probs`` (K, C) float32, ``hits`` / ``misses`` (K,) uint32, ``point_count`` (K,)
        int64, ``sum_d`` (K, 3) float64 (sum of the points' offsets from the voxel centre, m),
        ``sum_dd`` (K, 6) float64 (sums of their products xx, xy, xz, yy, yz, zz, m²),
        ``semantic`` / ``prior`` (K,) bool, ``prior_normal_sum`` (K, 3) float64 (sum of the
        prior's unit normals). :meth:`from_state_arrays` rebuilds the same map from them."""
        n = self._n
        return {name: getattr(self, attr)[:n].copy() for name, attr in _STATE_ATTRS.items()}

    @classmethod
    def from_state_arrays(cls, config: SemanticMapConfig,
                          arrays: Mapping[str, np.ndarray]) -> SemanticVoxelMap:
        """The map of ``config`` holding ``arrays`` (as :meth:`state_arrays` returns them: every
        field of :data:`STATE_FIELDS`, exact dtypes, one row per voxel). Raises
        :class:`MapError` naming the field and what is wrong: missing fields, a dtype or shape
        that does not match, duplicate voxel keys, voxels without points."""
        if not isinstance(config, SemanticMapConfig):
            raise MapError(f"config: expected a SemanticMapConfig, got {type(config).__name__}")
        missing = [name for name in STATE_FIELDS if name not in arrays]
        if missing:
            raise MapError(f"missing arrays {missing}")
        n: int | None = None
        for name, (tail, dtype) in _state_layout(config.num_classes).items():
            arr = np.asarray(arrays[name])
            if n is None:
                n = len(arr) if arr.ndim else -1
            if arr.dtype != dtype or arr.shape != (n, *tail):
                raise MapError(f"{name}: expected {np.dtype(dtype)} of shape {(n, *tail)}, got "
                               f"{arr.dtype} {arr.shape}")
        assert n is not None
        keys = np.asarray(arrays["keys"])
        order = np.argsort(keys, kind="stable")
        if n > 1 and np.any(np.diff(keys[order]) == 0):
            raise MapError("keys: duplicate voxel keys")
        if n and np.any(np.asarray(arrays["point_count"]) < 1):
            raise MapError("point_count: voxels without points")
        out = cls(config, capacity=max(n, 1))
        for name, attr in _STATE_ATTRS.items():
            getattr(out, attr)[:n] = arrays[name]
        out._n = n
        out._index_keys = keys[order].astype(np.int64)
        out._index_rows = order.astype(np.int64)
        return out
