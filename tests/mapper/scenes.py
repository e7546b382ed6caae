"""Test scenes of the semantic map: planar point patches, noisy labels, a map with some history.

World frame, metres; class ids of :mod:`protocol.semantic_classes`.
"""

from __future__ import annotations

import numpy as np

from mapper.semantic_map import SemanticMapConfig, SemanticVoxelMap
from protocol.semantic_classes import SEMANTIC_CLASS_ID, SEMANTIC_CLASSES

FLOOR = SEMANTIC_CLASS_ID["floor"]
C = len(SEMANTIC_CLASSES)


def plane_points(rng: np.random.Generator, n: int, *, size_m: float = 1.0, z: float = 0.0,
                 noise_m: float = 0.005) -> np.ndarray:
    """(n, 3) points on the square [0.02, size - 0.02]² at height z, with noise (the margin
    keeps the noise from making sparse voxels past the square's edges)."""
    xy = rng.uniform(0.02, size_m - 0.02, (n, 2))
    pts = np.column_stack([xy, np.full(n, z)])
    return pts + rng.normal(0.0, noise_m, pts.shape)


def noisy_labels(rng: np.random.Generator, n: int, label: int, wrong: float,
                 confidence: float) -> tuple[np.ndarray, np.ndarray]:
    """Top-1 labels (n,) uint8 of ``label`` with a share ``wrong`` replaced by random classes,
    and confidences (n,) float32 all ``confidence``."""
    ids = np.where(rng.random(n) < wrong, rng.integers(0, C, n), label).astype(np.uint8)
    return ids, np.full(n, confidence, dtype=np.float32)


def busy_map() -> SemanticVoxelMap:
    """A 2 x 2 m floor (0.1 m voxels, free-space carving on): the prior (points, no normals)
    plus three noisy top-1 floor scans from a sensor 1.5 m above its centre."""
    rng = np.random.default_rng(7)
    m = SemanticVoxelMap.from_prior_points(
        plane_points(rng, 5000, size_m=2.0), SemanticMapConfig(voxel_size_m=0.1,
                                                               carve_free_space=True))
    for k in range(3):
        pts = plane_points(rng, 3000, size_m=2.0, z=0.02 * k)
        m.integrate(pts, *noisy_labels(rng, 3000, FLOOR, 0.3, 0.8),
                    sensor_origin_world=np.array([1.0, 1.0, 1.5]))
    return m
