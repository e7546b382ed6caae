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
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import zipfile
import zlib
from pathlib import Path
from typing import Final

import numpy as np

from protocol.errors import SmartedgeError
from protocol.semantic_classes import (
    NO_SEMANTICS_COLOR,
    NUM_SEMANTIC_CLASSES,
    class_colors,
)

logger = logging.getLogger(__name__)

#: Name and version written into every map file (``format`` / ``version`` fields).
MAP_FILE_FORMAT: Final = "smartedge.semantic_voxel_map"
MAP_FILE_VERSION: Final = 1

_AXIS_BITS: Final = 21
_AXIS_OFFSET: Final = 1 << (_AXIS_BITS - 1)  # voxel indices in [-2**20, 2**20)
_AXIS_MASK: Final = (1 << _AXIS_BITS) - 1
#: Ray samples processed at once while carving (bounds the temporary memory to ~100 MB).
_CARVE_CHUNK_SAMPLES: Final = 1 << 20
#: Largest dense grid of rows built for carving (4 bytes a cell); bigger ray boxes look up keys.
_CARVE_GRID_MAX_CELLS: Final = 1 << 24
_EVIDENCE_MODES: Final = ("mean", "sum")


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

    Not thread-safe: one owner (the backend's map worker) mutates it.
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
        fields = {
            "_keys": ((), np.int64, 0),
            "_log_probs": ((c,), np.float32, -math.log(c)),
            "_hits": ((), np.uint32, 0),
            "_misses": ((), np.uint32, 0),
            "_count": ((), np.int64, 0),
            "_sum_d": ((3,), np.float64, 0.0),
            "_sum_dd": ((6,), np.float64, 0.0),
            "_semantic": ((), np.bool_, False),
            "_prior": ((), np.bool_, False),
            "_prior_normal_sum": ((3,), np.float64, 0.0),
        }
        for name, (tail, dtype, fill) in fields.items():
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

    _STATE: Final = ("_keys", "_log_probs", "_hits", "_misses", "_count", "_sum_d", "_sum_dd",
                     "_semantic", "_prior", "_prior_normal_sum")

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

    # -- files ---------------------------------------------------------------------------------

    def save_npz(self, path: str | os.PathLike[str], *, compress: bool = False) -> None:
        """Write the map to ``path`` (an ``.npz`` zip of ``.npy`` arrays, written to a temporary
        file and renamed into place).

        Fields: ``format`` (str, :data:`MAP_FILE_FORMAT`), ``version`` (int64,
        :data:`MAP_FILE_VERSION`), ``config`` (str: JSON of :class:`SemanticMapConfig`), and
        per voxel, in row order: ``keys`` (K,) int64 packed voxel keys, ``log_probs`` (K, C)
        float32, ``hits`` / ``misses`` (K,) uint32, ``point_count`` (K,) int64, ``sum_d`` (K, 3)
        float64 (sum of point offsets from the voxel centre, m), ``sum_dd`` (K, 6) float64 (sums
        of their products xx, xy, xz, yy, yz, zz, m²), ``semantic`` / ``prior`` (K,) bool,
        ``prior_normal_sum`` (K, 3) float64.
        """
        path = Path(path)
        n = self._n
        arrays = {name.lstrip("_"): getattr(self, name)[:n] for name in self._STATE}
        arrays["point_count"] = arrays.pop("count")
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            (np.savez_compressed if compress else np.savez)(
                f,
                format=np.array(MAP_FILE_FORMAT),
                version=np.array(MAP_FILE_VERSION, dtype=np.int64),
                config=np.array(json.dumps(dataclasses.asdict(self.config), sort_keys=True)),
                **arrays,
            )
        os.replace(tmp, path)

    @classmethod
    def load_npz(cls, path: str | os.PathLike[str]) -> SemanticVoxelMap:
        """Read a map written by :meth:`save_npz`. Raises :class:`MapError` naming the file and
        what is wrong for a missing, truncated, corrupt or foreign file."""
        try:
            with np.load(path, allow_pickle=False) as data:
                return cls._from_npz(data, str(path))
        except MapError:
            raise
        except FileNotFoundError as exc:
            raise MapError(f"{path}: no such map file") from exc
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error,
                AttributeError, TypeError) as exc:
            raise MapError(f"{path}: not a readable semantic map file "
                           f"({type(exc).__name__}: {exc})") from exc

    @classmethod
    def _from_npz(cls, data: object, where: str) -> SemanticVoxelMap:
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise MapError(f"{where}: not an .npz archive (a single array)")
        names = set(data.files)
        if "format" not in names or str(data["format"][()]) != MAP_FILE_FORMAT:
            raise MapError(f"{where}: not a semantic map file (format field missing or not "
                           f"{MAP_FILE_FORMAT!r})")
        version = int(data["version"][()]) if "version" in names else None
        if version != MAP_FILE_VERSION:
            raise MapError(f"{where}: map file version {version}, this build reads "
                           f"{MAP_FILE_VERSION}")
        try:
            raw = json.loads(str(data["config"][()]))
            fields = {f.name for f in dataclasses.fields(SemanticMapConfig)}
            unknown = set(raw) - fields
            if unknown:
                raise MapError(f"{where}: config: unknown keys {sorted(unknown)}")
            config = SemanticMapConfig(**raw)
        except MapError as exc:
            if str(exc).startswith(where):
                raise
            raise MapError(f"{where}: {exc}") from exc
        except (json.JSONDecodeError, TypeError, AttributeError) as exc:
            raise MapError(f"{where}: config: not a valid JSON object ({exc})") from exc
        c = config.num_classes
        expected = {
            "keys": ((), np.int64), "log_probs": ((c,), np.float32), "hits": ((), np.uint32),
            "misses": ((), np.uint32), "point_count": ((), np.int64), "sum_d": ((3,), np.float64),
            "sum_dd": ((6,), np.float64), "semantic": ((), np.bool_), "prior": ((), np.bool_),
            "prior_normal_sum": ((3,), np.float64),
        }
        missing = sorted(set(expected) - names)
        if missing:
            raise MapError(f"{where}: missing arrays {missing}")
        arrays = {}
        n = None
        for name, (tail, dtype) in expected.items():
            arr = data[name]
            if n is None:
                n = len(arr) if arr.ndim else -1
            if arr.dtype != dtype or arr.shape != (n, *tail):
                raise MapError(f"{where}: {name}: expected {np.dtype(dtype)} of shape "
                               f"{(n, *tail)}, got {arr.dtype} {arr.shape}")
            arrays[name] = arr
        assert n is not None
        keys = arrays["keys"]
        order = np.argsort(keys, kind="stable")
        if n > 1 and np.any(np.diff(keys[order]) == 0):
            raise MapError(f"{where}: keys: duplicate voxel keys")
        if n and np.any(arrays["point_count"] < 1):
            raise MapError(f"{where}: point_count: voxels without points")
        out = cls(config, capacity=max(n, 1))
        for name in cls._STATE:
            getattr(out, name)[:n] = arrays["point_count" if name == "_count" else name[1:]]
        out._n = n
        out._index_keys = keys[order].astype(np.int64)
        out._index_rows = order.astype(np.int64)
        return out

    def to_ply(self, path: str | os.PathLike[str], *, positions: str = "mean") -> None:
        """Write the voxels as a binary little-endian PLY point cloud (CloudCompare, Open3D,
        MeshLab read it): ``x y z`` float32 (voxel means, or centres with
        ``positions="center"``), ``nx ny nz`` float32 (0 where undefined), ``red green blue``
        uchar (class colour of the label, grey without semantics), ``label`` int32 (-1 without
        semantics), ``confidence`` float32."""
        if positions not in ("mean", "center"):
            raise MapError(f"positions: 'mean' or 'center', got {positions!r}")
        n = self._n
        xyz = self.means() if positions == "mean" else self.voxel_centers()
        normals = np.nan_to_num(self.normals(), nan=0.0)
        labels = self.labels()
        colors = np.empty((n, 3), dtype=np.uint8)
        colors[:] = NO_SEMANTICS_COLOR
        sem = labels >= 0
        colors[sem] = class_colors(self.config.num_classes)[labels[sem]]
        vertex = np.empty(n, dtype=[
            ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"),
            ("nz", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("label", "<i4"),
            ("confidence", "<f4"),
        ])
        for a, name in enumerate("xyz"):
            vertex[name] = xyz[:, a]
            vertex["n" + name] = normals[:, a]
        for a, name in enumerate(("red", "green", "blue")):
            vertex[name] = colors[:, a]
        vertex["label"] = labels
        vertex["confidence"] = self.confidence()
        props = "".join(
            f"property {kind} {name}\n" for name, kind in (
                ("x", "float"), ("y", "float"), ("z", "float"), ("nx", "float"),
                ("ny", "float"), ("nz", "float"), ("red", "uchar"), ("green", "uchar"),
                ("blue", "uchar"), ("label", "int"), ("confidence", "float"))
        )
        header = (
            "ply\nformat binary_little_endian 1.0\n"
            f"comment smartedge semantic voxel map, voxel_size_m {self.config.voxel_size_m}\n"
            f"element vertex {n}\n{props}end_header\n"
        )
        with open(path, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(vertex.tobytes())


# ----------------------------------------------------------------------------------------------
# prior models


_PLY_TYPES: Final = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
#: Largest header read (bytes) and vertex count accepted from a PLY file.
_PLY_MAX_HEADER: Final = 64 * 1024
_PLY_MAX_VERTICES: Final = 50_000_000


def read_ply_points(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) float64 and, when the file has ``nx ny nz``, normals (N, 3) of a PLY
    point cloud (``ascii`` or ``binary_little_endian``/``binary_big_endian``; the ``vertex``
    element must come first; other elements such as faces are ignored). This is how a prior
    geometric model of the site is read (e.g. exported from CAD or CloudCompare, or written
    by :meth:`SemanticVoxelMap.to_ply`). Raises :class:`MapError` naming the file and what is
    wrong."""
    where = str(path)
    try:
        with open(path, "rb") as f:
            head = f.read(_PLY_MAX_HEADER)
            end = head.find(b"end_header")
            if not head.startswith(b"ply") or end < 0:
                raise MapError(f"{where}: not a PLY file (no 'ply' magic or no end_header in "
                               f"the first {_PLY_MAX_HEADER} bytes)")
            nl = head.find(b"\n", end)
            if nl < 0:
                raise MapError(f"{where}: truncated after end_header")
            header = head[:nl].decode("ascii", errors="replace").splitlines()
            fmt, count, props = _parse_ply_header(header, where)
            f.seek(nl + 1)
            if fmt == "ascii":
                rows = [f.readline().split() for _ in range(count)]
                if any(len(r) < len(props) for r in rows):
                    raise MapError(f"{where}: truncated: fewer than {count} vertex rows")
                table = np.array([r[:len(props)] for r in rows], dtype=np.float64).reshape(
                    count, len(props))
                column = {name: table[:, i] for i, (name, _) in enumerate(props)}
            else:
                order = "<" if fmt == "binary_little_endian" else ">"
                dtype = np.dtype([(name, order + kind) for name, kind in props])
                raw = f.read(dtype.itemsize * count)
                if len(raw) < dtype.itemsize * count:
                    raise MapError(f"{where}: truncated: {len(raw)} bytes of vertex data, "
                                   f"expected {dtype.itemsize * count}")
                data = np.frombuffer(raw, dtype=dtype, count=count)
                column = {name: data[name].astype(np.float64) for name, _ in props}
    except FileNotFoundError as exc:
        raise MapError(f"{where}: no such PLY file") from exc
    except (OSError, ValueError) as exc:
        if isinstance(exc, MapError):
            raise
        raise MapError(f"{where}: not a readable PLY point cloud ({exc})") from exc
    points = np.stack([column["x"], column["y"], column["z"]], axis=1)
    if not np.isfinite(points).all():
        raise MapError(f"{where}: vertices with NaN or inf coordinates")
    normals = None
    if {"nx", "ny", "nz"} <= set(column):
        normals = np.stack([column["nx"], column["ny"], column["nz"]], axis=1)
        normals = np.where(np.isfinite(normals), normals, 0.0)
    return points, normals


def _parse_ply_header(lines: list[str], where: str) -> tuple[str, int, list[tuple[str, str]]]:
    fmt = ""
    element = None
    count = -1
    props: list[tuple[str, str]] = []
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else ""
        elif words[0] == "element":
            if element == "vertex":
                break  # the vertex element is complete
            element = words[1] if len(words) > 1 else ""
            if element != "vertex":
                raise MapError(f"{where}: the 'vertex' element must come first, found "
                               f"{element!r}")
            try:
                count = int(words[2])
            except (IndexError, ValueError):
                raise MapError(f"{where}: bad element line {line!r}") from None
        elif words[0] == "property" and element == "vertex":
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                raise MapError(f"{where}: unsupported vertex property {line!r} (scalar "
                               "properties only)")
            props.append((words[2], _PLY_TYPES[words[1]]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MapError(f"{where}: unsupported PLY format {fmt!r}")
    if not 0 <= count <= _PLY_MAX_VERTICES:
        raise MapError(f"{where}: vertex count {count} missing or above {_PLY_MAX_VERTICES}")
    names = [n for n, _ in props]
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        raise MapError(f"{where}: vertex properties {missing} missing")
    return fmt, count, props
