"""``smartedge bench map``: semantic map fusion throughput and ICP alignment latency.

Builds a synthetic room (floor, four walls, a table, a box and a cabinet, each a labelled plane
set), samples robot-like semantic clouds from it (a 1 m high sensor with a 90 x 60 deg view,
range-limited, surfaces facing the sensor, 5 mm noise), and measures:

- fusion: ``--clouds`` clouds of ``--points`` points integrated into a ``--voxel`` map
  initialised from the room's prior geometry, without and with free-space carving, as fused
  points per second (median over ``--repeats`` runs of the whole sequence);
- alignment: :func:`mapper.alignment.align_to_map` of one such cloud, displaced
  by 10 cm / 5 deg, against the fused map's voxel means and normals (coarse-to-fine
  point-to-plane ICP, the robot cloud downsampled per level), median latency over the repeats
  and the residual error.

The room and its views come from :mod:`simulation.synthetic_room` (the mapper tests use the
same generators).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from collections.abc import Sequence
from typing import Final

import numpy as np

from simulation.synthetic_room import (
    pose_matrix,
    robot_view,
    sample_room,
    synthetic_room,
    transform_points,
)

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
    from mapper.alignment import AlignmentConfig, align_to_map
    from mapper.semantic_map import SemanticMapConfig, SemanticVoxelMap

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
