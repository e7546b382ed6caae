"""Load a saved semantic map: how many voxels of each class, and where the map lies.

The mapper (``smartedge mapper``) keeps its map in an ``.npz`` snapshot (the site file's
``map.snapshot_path``; ``smartedge demo`` writes ``runs/demo/semantic_map.npz``). Each voxel is a
cube of ``voxel_size_m`` in the world (map) frame with class probabilities and the mean of the
points that fell into it.

    .venv/bin/python examples/load_map.py runs/demo/semantic_map.npz
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mapper.map_io import load_map_npz
from mapper.semantic_map import MapError
from protocol.semantic_classes import SEMANTIC_CLASSES


def main(path: Path) -> None:
    voxel_map = load_map_npz(path)
    voxel_size_m = voxel_map.config.voxel_size_m
    labels = voxel_map.labels()  # (K,) most probable class id; -1: never seen with semantics
    confidence = voxel_map.confidence()  # (K,) probability of that class

    print(f"{path}: {len(voxel_map)} voxels of {voxel_size_m:g} m, "
          f"{int((labels >= 0).sum())} with semantics")
    voxels_per_class = np.bincount(labels[labels >= 0], minlength=voxel_map.config.num_classes)
    for class_id in np.flatnonzero(voxels_per_class):
        # class ids are positions in the legend (a map may have been built with more classes)
        name = SEMANTIC_CLASSES[class_id] if class_id < len(SEMANTIC_CLASSES) else str(class_id)
        mean_confidence = float(confidence[labels == class_id].mean())
        print(f"  {name:12s} {voxels_per_class[class_id]:8d} voxels  "
              f"mean confidence {mean_confidence:.2f}")
    if len(voxel_map) == 0:
        return
    # the voxels' outer faces, world frame: centres -/+ half a voxel
    centers_m = voxel_map.voxel_centers()  # (K, 3)
    x_lo_m, y_lo_m, z_lo_m = centers_m.min(axis=0) - voxel_size_m / 2
    x_hi_m, y_hi_m, z_hi_m = centers_m.max(axis=0) + voxel_size_m / 2
    print(f"bounding box (world frame): x [{x_lo_m:.2f}, {x_hi_m:.2f}] m  "
          f"y [{y_lo_m:.2f}, {y_hi_m:.2f}] m  z [{z_lo_m:.2f}, {z_hi_m:.2f}] m")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map", type=Path, help="a map file (.npz) the mapper saved")
    args = parser.parse_args()
    try:
        main(args.map)
    except MapError as exc:  # missing, truncated or not a map: the message names the file
        raise SystemExit(f"error: {exc}") from None
