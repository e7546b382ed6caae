"""A synthetic room for the semantic map: labelled planar surfaces (floor, four walls, a table,
a box, a cabinet), points sampled uniformly over them, and robot-like views of them.

Numpy only and deterministic for a given generator. Used by ``smartedge bench map`` and the
mapper tests. Frames: world (= map), z up, metres; class ids of
:mod:`protocol.semantic_classes`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Final

import numpy as np

from protocol.semantic_classes import SEMANTIC_CLASS_ID

#: the room's extent (x, y, z) in metres, corner at the origin, floor at z = 0
ROOM_SIZE_M: Final = (6.0, 5.0, 2.5)


@dataclasses.dataclass(frozen=True)
class Surface:
    """A labelled rectangle ``origin + a u + b v`` (a, b in [0, 1]) with unit ``normal``
    pointing to the free side; world frame, metres."""

    origin: tuple[float, float, float]
    u: tuple[float, float, float]
    v: tuple[float, float, float]
    normal: tuple[float, float, float]
    class_id: int

    @property
    def area_m2(self) -> float:
        return float(np.linalg.norm(np.cross(self.u, self.v)))


def _box(lo: Sequence[float], hi: Sequence[float], class_id: int,
         bottom: bool = False) -> list[Surface]:
    """The faces of an axis-aligned box (outward normals; the bottom face only if asked)."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    faces = [
        Surface((x0, y0, z1), (dx, 0, 0), (0, dy, 0), (0, 0, 1), class_id),
        Surface((x0, y0, z0), (dx, 0, 0), (0, 0, dz), (0, -1, 0), class_id),
        Surface((x0, y1, z0), (dx, 0, 0), (0, 0, dz), (0, 1, 0), class_id),
        Surface((x0, y0, z0), (0, dy, 0), (0, 0, dz), (-1, 0, 0), class_id),
        Surface((x1, y0, z0), (0, dy, 0), (0, 0, dz), (1, 0, 0), class_id),
    ]
    if bottom:
        faces.append(Surface((x0, y0, z0), (dx, 0, 0), (0, dy, 0), (0, 0, -1), class_id))
    return faces


def synthetic_room() -> tuple[Surface, ...]:
    """A 6 x 5 x 2.5 m room (x, y, z; floor at z = 0, corner at the origin): floor, four
    walls (normals inward), a table (0.75 m high top slab with four legs), a 0.5 m box on the
    floor and a cabinet against the x = 6 m wall."""
    w, d, h = ROOM_SIZE_M
    ids = SEMANTIC_CLASS_ID
    out = [
        Surface((0, 0, 0), (w, 0, 0), (0, d, 0), (0, 0, 1), ids["floor"]),
        Surface((0, 0, 0), (w, 0, 0), (0, 0, h), (0, 1, 0), ids["wall"]),
        Surface((0, d, 0), (w, 0, 0), (0, 0, h), (0, -1, 0), ids["wall"]),
        Surface((0, 0, 0), (0, d, 0), (0, 0, h), (1, 0, 0), ids["wall"]),
        Surface((w, 0, 0), (0, d, 0), (0, 0, h), (-1, 0, 0), ids["wall"]),
    ]
    out += _box((2.8, 1.8, 0.71), (4.2, 2.6, 0.75), ids["table"], bottom=True)
    for x, y in ((2.85, 1.85), (4.1, 1.85), (2.85, 2.5), (4.1, 2.5)):
        out += _box((x, y, 0.0), (x + 0.05, y + 0.05, 0.71), ids["table"])
    out += _box((1.0, 3.4, 0.0), (1.5, 3.9, 0.5), ids["box"])
    out += _box((5.55, 0.8, 0.0), (6.0, 2.0, 1.8), ids["cabinet"])
    return tuple(out)


def sample_room(surfaces: Sequence[Surface], n_points: int,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n_points`` points uniform over the surfaces' total area: (N, 3) float64 world
    metres, (N, 3) unit normals, (N,) int64 class ids."""
    areas = np.array([s.area_m2 for s in surfaces])
    which = rng.choice(len(surfaces), size=n_points, p=areas / areas.sum())
    origin = np.array([s.origin for s in surfaces], dtype=np.float64)[which]
    u = np.array([s.u for s in surfaces], dtype=np.float64)[which]
    v = np.array([s.v for s in surfaces], dtype=np.float64)[which]
    ab = rng.random((n_points, 2))
    points = origin + ab[:, :1] * u + ab[:, 1:] * v
    normals = np.array([s.normal for s in surfaces], dtype=np.float64)[which]
    class_ids = np.array([s.class_id for s in surfaces], dtype=np.int64)[which]
    return points, normals, class_ids


def robot_view(
    surfaces: Sequence[Surface],
    sensor_xyz: Sequence[float] | np.ndarray,
    heading_rad: float,
    n_points: int,
    rng: np.random.Generator,
    *,
    h_fov_deg: float = 90.0,
    v_fov_deg: float = 60.0,
    max_range_m: float = 5.0,
    noise_m: float = 0.005,
) -> tuple[np.ndarray, np.ndarray]:
    """A robot-like view: ``n_points`` points of the surfaces inside the sensor's field of
    view (centred on ``heading_rad``, level), within ``max_range_m``, on faces turned to the
    sensor (no occlusion test), with Gaussian noise ``noise_m`` per axis.

    Returns (N, 3) float64 points (world frame, metres) and (N,) int64 true class ids.
    """
    sensor = np.asarray(sensor_xyz, dtype=np.float64)
    out_p: list[np.ndarray] = []
    out_c: list[np.ndarray] = []
    have = 0
    for _ in range(100):
        p, nrm, cls = sample_room(surfaces, 4 * n_points, rng)
        rel = p - sensor
        dist = np.linalg.norm(rel, axis=1)
        yaw = np.arctan2(rel[:, 1], rel[:, 0]) - heading_rad
        yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
        pitch = np.arcsin(np.clip(rel[:, 2] / np.maximum(dist, 1e-9), -1, 1))
        keep = (
            (np.abs(yaw) <= math.radians(h_fov_deg) / 2)
            & (np.abs(pitch) <= math.radians(v_fov_deg) / 2)
            & (dist <= max_range_m) & (dist > 0.2)
            & (np.einsum("ij,ij->i", nrm, -rel) > 0)
        )
        out_p.append(p[keep])
        out_c.append(cls[keep])
        have += int(keep.sum())
        if have >= n_points:
            break
    points = np.concatenate(out_p)[:n_points]
    classes = np.concatenate(out_c)[:n_points]
    return points + rng.normal(0.0, noise_m, points.shape), classes


def pose_matrix(yaw_rad: float, translation: Sequence[float] | np.ndarray,
                pivot: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) transform: rotation by ``yaw_rad`` about the vertical axis through ``pivot``,
    then ``translation`` (metres)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    pivot_v = np.asarray(pivot, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = pivot_v - R @ pivot_v + np.asarray(translation, dtype=np.float64)
    return T


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) points moved by the (4, 4) transform ``T``."""
    return points @ T[:3, :3].T + T[:3, 3]


__all__ = [
    "ROOM_SIZE_M",
    "Surface",
    "pose_matrix",
    "robot_view",
    "sample_room",
    "synthetic_room",
    "transform_points",
]
