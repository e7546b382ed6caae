"""``smartedge bench map``: semantic map fusion throughput and ICP alignment latency.

Builds a synthetic room (floor, four walls, a table, a box and a cabinet, each a labelled plane
set), samples robot-like semantic clouds from it (a 1 m high sensor with a 90 x 60 deg view,
range-limited, surfaces facing the sensor, 5 mm noise), and measures:

- fusion: ``--clouds`` clouds of ``--points`` points integrated into a ``--voxel`` map
  initialised from the room's prior geometry, without and with free-space carving, as fused
  points per second (median over ``--repeats`` runs of the whole sequence);
- alignment: :func:`backend_service.cloud_alignment.align_to_map` of one such cloud, displaced
  by 10 cm / 5 deg, against the fused map's voxel means and normals (coarse-to-fine
  point-to-plane ICP, the robot cloud downsampled per level), median latency over the repeats
  and the residual error.

The room and view generators (:func:`synthetic_room`, :func:`sample_room`, :func:`robot_view`)
are numpy-only and deterministic for a given generator; the map and alignment tests use them.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import platform
import sys
import time
from collections.abc import Sequence
from typing import Final

import numpy as np

from protocol.semantic_classes import SEMANTIC_CLASS_ID

_ROOM_SIZE_M: Final = (6.0, 5.0, 2.5)


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
    w, d, h = _ROOM_SIZE_M
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


#: Robot poses (x, y, heading) of the benchmark's views.
_VIEW_POSES: Final = tuple(
    (1.0 + 4.0 * ((k * 0.37) % 1.0), 0.8 + 3.4 * ((k * 0.61) % 1.0), k * 2.4) for k in range(64)
)


def _views(n_clouds: int, n_points: int, seed: int) -> list[tuple[np.ndarray, np.ndarray,
                                                                   np.ndarray, np.ndarray]]:
    """(points, class ids, confidences, sensor origin) per view; 10 % of the labels wrong."""
    rng = np.random.default_rng(seed)
    room = synthetic_room()
    out = []
    for k in range(n_clouds):
        x, y, th = _VIEW_POSES[k % len(_VIEW_POSES)]
        origin = np.array([x, y, 1.0])
        pts, cls = robot_view(room, origin, th, n_points, rng)
        wrong = rng.random(len(cls)) < 0.1
        cls = np.where(wrong, rng.integers(0, 14, len(cls)), cls)
        conf = rng.uniform(0.5, 0.99, len(cls))
        out.append((pts.astype(np.float32), cls.astype(np.uint8), conf.astype(np.float32),
                    origin))
    return out


def main(argv: Sequence[str]) -> int:
    from backend_service.cloud_alignment import AlignmentConfig, align_to_map
    from backend_service.semantic_map import SemanticMapConfig, SemanticVoxelMap

    parser = argparse.ArgumentParser(prog="smartedge bench map", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clouds", type=int, default=20, help="clouds per run (20)")
    parser.add_argument("--points", type=int, default=50_000, help="points per cloud (50000)")
    parser.add_argument("--voxel", type=float, default=0.05, help="voxel size, m (0.05)")
    parser.add_argument("--repeats", type=int, default=5, help="runs; medians reported (5)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(list(argv))
    if args.clouds < 1 or args.points < 100 or args.voxel <= 0 or args.repeats < 1:
        parser.error("--clouds >= 1, --points >= 100, --voxel > 0, --repeats >= 1")

    print(f"machine: {platform.machine()}, {os.cpu_count()} CPUs (load average "
          f"{os.getloadavg()[0]:.1f}), python {platform.python_version()}, numpy "
          f"{np.__version__}")
    t0 = time.perf_counter()
    views = _views(args.clouds, args.points, args.seed)
    prior, prior_normals, _ = sample_room(synthetic_room(), 400_000,
                                          np.random.default_rng(args.seed + 1))
    n_fused = sum(len(v[0]) for v in views)
    print(f"{args.clouds} clouds x {args.points} points (synthetic 6 x 5 m room, robot views), "
          f"prior 400k points; generated in {time.perf_counter() - t0:.1f} s")

    fused_map = None
    for carve in (False, True):
        config = SemanticMapConfig(voxel_size_m=args.voxel, carve_free_space=carve)
        rates = []
        for _ in range(args.repeats):
            m = SemanticVoxelMap.from_prior_points(prior, config, prior_normals)
            t = time.perf_counter()
            for pts, cls, conf, origin in views:
                m.integrate(pts, cls, conf, sensor_origin_world=origin)
            rates.append(n_fused / (time.perf_counter() - t))
            if not carve:
                fused_map = m
        label = "with carving   " if carve else "without carving"
        print(f"fusion {label}: {np.median(rates) / 1e6:6.2f} M points/s (median of "
              f"{args.repeats}; min {min(rates) / 1e6:.2f}, max {max(rates) / 1e6:.2f}); "
              f"{len(m)} voxels")
    assert fused_map is not None

    t = time.perf_counter()
    map_points, map_normals = fused_map.means(), fused_map.normals()
    print(f"map geometry for ICP (means + normals of {len(fused_map)} voxels): "
          f"{(time.perf_counter() - t) * 1e3:.1f} ms (cached until the next change)")
    align_config = AlignmentConfig()
    robot_pts = views[0][0].astype(np.float64)
    pivot = views[0][3]
    T_err = pose_matrix(math.radians(5.0), (0.08, -0.06, 0.0), pivot)
    cloud = transform_points(T_err, robot_pts)
    latencies, results = [], []
    for _ in range(max(args.repeats, 7)):
        t = time.perf_counter()
        res = align_to_map(cloud, map_points, map_normals, align_config)
        latencies.append(time.perf_counter() - t)
        results.append(res)
    res = results[-1]
    residual = res.T_correction @ T_err
    err_m = float(np.linalg.norm(transform_points(residual, pivot[None])[0] - pivot))
    err_deg = math.degrees(math.acos(np.clip((np.trace(residual[:3, :3]) - 1) / 2, -1, 1)))
    print(f"ICP ({len(cloud)}-point cloud, levels {align_config.voxel_sizes_m} m): median "
          f"{np.median(latencies) * 1e3:.1f} ms (min {min(latencies) * 1e3:.1f}, max "
          f"{max(latencies) * 1e3:.1f}); accepted {res.accepted}, fitness {res.fitness:.3f}, "
          f"inlier RMSE {res.inlier_rmse_m * 100:.2f} cm, residual {err_m * 100:.2f} cm / "
          f"{err_deg:.3f} deg after a 10 cm / 5 deg offset")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
