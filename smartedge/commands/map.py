"""``smartedge map``: look into and convert the semantic map files the mapper keeps.

- ``smartedge map info MAP.npz``: voxel size, voxel counts, the share with semantics, the
  class histogram of the labelled voxels;
- ``smartedge map export MAP.npz OUT.ply [--positions mean|center] [--semantic-only]``: a binary
  PLY point cloud with ``x y z nx ny nz red green blue label confidence`` per voxel, which
  CloudCompare, Open3D and MeshLab open (colour = class colour of the legend, grey without
  semantics).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import numpy as np

from protocol.semantic_classes import SEMANTIC_CLASSES


def _load(path: str):
    from mapper.map_io import load_map_npz

    return load_map_npz(path)


def info(path: str) -> int:
    m = _load(path)
    labels = m.labels()
    sem = labels >= 0
    n = len(m)
    print(f"{path}: {n} voxels of {m.config.voxel_size_m} m, {int(m.is_prior().sum())} from the "
          f"prior model, {int(sem.sum())} with semantics "
          f"({100.0 * sem.sum() / max(n, 1):.1f} %), {m.config.num_classes} classes")
    if sem.any():
        counts = np.bincount(labels[sem], minlength=m.config.num_classes)
        conf = m.confidence()
        for cid in np.argsort(-counts):
            if counts[cid] == 0:
                continue
            name = SEMANTIC_CLASSES[cid] if cid < len(SEMANTIC_CLASSES) else f"class {cid}"
            mean_conf = float(conf[sem & (labels == cid)].mean())
            print(f"  {name:12s} {int(counts[cid]):8d} voxels  mean confidence {mean_conf:.2f}")
    return 0


def export(path: str, out: str, positions: str, semantic_only: bool) -> int:
    m = _load(path)
    if semantic_only:
        m = m.subset(m.has_semantics())
    from mapper.map_io import write_map_ply

    write_map_ply(m, out, positions=positions)
    print(f"wrote {out}: {len(m)} voxels")
    return 0


def main(argv: Sequence[str]) -> int:
    from mapper.semantic_map import MapError

    parser = argparse.ArgumentParser(prog="smartedge map", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    p_info = sub.add_parser("info", help="what a map file holds")
    p_info.add_argument("map", help="map file (.npz, as the mapper keeps it)")
    p_exp = sub.add_parser("export", help="export a map file to PLY")
    p_exp.add_argument("map", help="map file (.npz)")
    p_exp.add_argument("out", help="output .ply")
    p_exp.add_argument("--positions", choices=("mean", "center"), default="mean",
                       help="voxel means (default) or voxel centres")
    p_exp.add_argument("--semantic-only", action="store_true",
                       help="only the voxels with semantic information")
    args = parser.parse_args(list(argv))
    try:
        if args.what == "info":
            return info(args.map)
        return export(args.map, args.out, args.positions, args.semantic_only)
    except MapError as exc:
        print(f"smartedge map: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"smartedge map: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
