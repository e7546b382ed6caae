"""The robot bridge's map output (``robot_bridge.map_output``): conversion time of a semantic map
into a ``sensor_msgs/PointCloud2`` and an obstacle ``nav_msgs/OccupancyGrid`` (checks, class
colours, the grid, both CDR encodings) and the bytes of each message, for synthetic rooms of
20 000 to 200 000 voxels and for the simulated demo lab with every static surface observed.

    .venv/bin/python scripts/map_output_figures.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from protocol.codec import encode
from protocol.messages import SemanticCloud
from robot_bridge.map_output import MapOutputConfig, map_snapshot

STAMP_NS = 1_700_000_000_000_000_000
VOXEL_M = 0.05


def synthetic_room(n: int, rng: np.random.Generator) -> SemanticCloud:
    """A 6 x 5 m room: a floor of 5 cm voxels, the rest random voxels of random classes up to
    2.5 m."""
    fx, fy = np.meshgrid(np.arange(0.025, 6.0, VOXEL_M), np.arange(0.025, 5.0, VOXEL_M))
    floor = np.stack([fx.ravel(), fy.ravel(), np.full(fx.size, 0.025)], axis=1)[:n]
    k = n - len(floor)
    rest = np.stack([rng.uniform(0, 6, k), rng.uniform(0, 5, k), rng.uniform(0.05, 2.5, k)],
                    axis=1)
    labels = np.concatenate([np.full(len(floor), 1), rng.integers(2, 14, k)])
    return SemanticCloud("map", STAMP_NS, 0, "map",
                         np.concatenate([floor, rest]).astype(np.float32),
                         labels.astype(np.uint16), rng.uniform(0.3, 1.0, n).astype(np.float32))


def demo_lab() -> SemanticCloud:
    """The simulated site's static surfaces (sampled at 2 cm) as 5 cm voxels with their true
    classes: the map the demo's mapper would publish with every surface observed."""
    from simulation.scenario import load_scenario
    from simulation.scenes import site_geometry, surface_samples

    scenario = load_scenario()
    points, _, classes = surface_samples(site_geometry(scenario).objects, 0.02, seed=2)
    keys = np.floor(points / VOXEL_M).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    means = np.zeros((len(first), 3))
    np.add.at(means, inverse, points)
    means /= np.bincount(inverse)[:, None]
    return SemanticCloud("map", STAMP_NS, 0, scenario.site.world_frame,
                         means.astype(np.float32), classes[first].astype(np.uint16),
                         np.full(len(first), 0.9, np.float32))


def measure(name: str, cloud: SemanticCloud, repeats: int) -> None:
    config = MapOutputConfig()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        snap = map_snapshot(cloud, config, cloud.frame_id)
        cloud_bytes = snap.cloud_payload()
        grid_bytes = snap.grid_payload()
        times.append(time.perf_counter() - t0)
    assert cloud_bytes is not None and grid_bytes is not None and snap.grid is not None
    grid = snap.grid
    print(f"| {name} ({len(snap)} voxels) | {1e3 * float(np.median(times)):.1f} ms | "
          f"{len(cloud_bytes):,} B | {len(grid_bytes):,} B ({grid.width} x {grid.height}; "
          f"{int((grid.cells == 100).sum())} occupied) | {len(encode(cloud)):,} B |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7, help="runs per map (median)")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print("| map | conversion (median) | PointCloud2 | OccupancyGrid | msgpack map message |")
    print("|---|---:|---:|---:|---:|")
    for n in (20_000, 69_663, 100_000, 200_000):
        measure("synthetic room", synthetic_room(n, rng), args.repeats)
    print("building the demo lab's map ...", flush=True)
    measure("demo lab, every static surface", demo_lab(), args.repeats)


if __name__ == "__main__":
    main()
