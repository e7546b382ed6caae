"""Map files: the semantic voxel map's ``.npz`` snapshot, its PLY export, and PLY prior models.

- :func:`save_map_npz` / :func:`load_map_npz`: the map exactly (every voxel's state, the
  configuration), as the mapper service keeps it across restarts and ``smartedge map`` reads it.
  An ``.npz`` zip of ``.npy`` arrays (no pickles), named by :data:`MAP_FILE_FORMAT` and
  :data:`MAP_FILE_VERSION`; written to a temporary file and renamed into place.
- :func:`write_map_ply`: the voxels as a binary PLY point cloud for CloudCompare, Open3D or
  MeshLab (positions, normals, class colour, label, confidence); one way, nothing reads the
  semantics back.
- :func:`read_ply_points`: points and normals of a PLY point cloud, how a prior geometric model
  of the site (the empty room, world frame, metres) is read.

Numpy only. Every reader raises :class:`~mapper.semantic_map.MapError` naming the file and what
is wrong for a missing, truncated, corrupt or foreign file.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import zipfile
import zlib
from pathlib import Path
from typing import Final

import numpy as np

from mapper.semantic_map import STATE_FIELDS, MapError, SemanticMapConfig, SemanticVoxelMap
from protocol.semantic_classes import NO_SEMANTICS_COLOR, class_colors

logger = logging.getLogger(__name__)

#: Name and version written into every map file (``format`` / ``version`` fields).
MAP_FILE_FORMAT: Final = "smartedge.semantic_voxel_map"
MAP_FILE_VERSION: Final = 1

_PLY_TYPES: Final = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
#: Largest header read (bytes) and vertex count accepted from a PLY file.
_PLY_MAX_HEADER: Final = 64 * 1024
_PLY_MAX_VERTICES: Final = 50_000_000


# ----------------------------------------------------------------------------------------------
# the map snapshot (.npz)


def save_map_npz(voxel_map: SemanticVoxelMap, path: str | os.PathLike[str], *,
                 compress: bool = False) -> None:
    """Write ``voxel_map`` to ``path`` (an ``.npz`` zip of ``.npy`` arrays, written to
    ``<path>.tmp`` and renamed into place, so a reader never sees half a file).

    Fields: ``format`` (str, :data:`MAP_FILE_FORMAT`), ``version`` (int64,
    :data:`MAP_FILE_VERSION`), ``config`` (str: JSON of :class:`SemanticMapConfig`), and the
    per-voxel state of :meth:`SemanticVoxelMap.state_arrays`, in row order (K voxels, C
    classes): ``keys`` (K,) int64 packed voxel keys, ``log_probs`` (K, C) float32, ``hits`` /
    ``misses`` (K,) uint32, ``point_count`` (K,) int64, ``sum_d`` (K, 3) float64 (sum of point
    offsets from the voxel centre, m), ``sum_dd`` (K, 6) float64 (sums of their products xx, xy,
    xz, yy, yz, zz, m²), ``semantic`` / ``prior`` (K,) bool, ``prior_normal_sum`` (K, 3) float64.
    ``compress``: deflate the arrays (smaller, slower).
    """
    path = Path(path)
    arrays = voxel_map.state_arrays()
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        (np.savez_compressed if compress else np.savez)(
            f,
            format=np.array(MAP_FILE_FORMAT),
            version=np.array(MAP_FILE_VERSION, dtype=np.int64),
            config=np.array(json.dumps(dataclasses.asdict(voxel_map.config), sort_keys=True)),
            **arrays,
        )
    os.replace(tmp, path)
    logger.debug("map saved to %s: %d voxels", path, len(voxel_map))


def load_map_npz(path: str | os.PathLike[str]) -> SemanticVoxelMap:
    """Read a map written by :func:`save_map_npz`. Raises :class:`MapError` naming the file and
    what is wrong for a missing, truncated, corrupt or foreign file, another file version, or
    arrays that do not make a map."""
    try:
        with np.load(path, allow_pickle=False) as data:
            out = _map_from_npz(data, str(path))
    except MapError:
        raise
    except FileNotFoundError as exc:
        raise MapError(f"{path}: no such map file") from exc
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error,
            AttributeError, TypeError) as exc:
        raise MapError(f"{path}: not a readable semantic map file "
                       f"({type(exc).__name__}: {exc})") from exc
    logger.debug("map loaded from %s: %d voxels", path, len(out))
    return out


def _map_from_npz(data: object, where: str) -> SemanticVoxelMap:
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
            raise MapError(f"config: unknown keys {sorted(unknown)}")
        config = SemanticMapConfig(**raw)
    except MapError as exc:
        raise MapError(f"{where}: {exc}") from exc
    except (json.JSONDecodeError, TypeError, AttributeError) as exc:
        raise MapError(f"{where}: config: not a valid JSON object ({exc})") from exc
    missing = sorted(set(STATE_FIELDS) - names)
    if missing:
        raise MapError(f"{where}: missing arrays {missing}")
    try:
        return SemanticVoxelMap.from_state_arrays(config, {n: data[n] for n in STATE_FIELDS})
    except MapError as exc:
        raise MapError(f"{where}: {exc}") from exc


# ----------------------------------------------------------------------------------------------
# PLY export


def write_map_ply(voxel_map: SemanticVoxelMap, path: str | os.PathLike[str], *,
                  positions: str = "mean") -> None:
    """Write the voxels of ``voxel_map`` as a binary little-endian PLY point cloud (CloudCompare,
    Open3D, MeshLab read it), one vertex per voxel in row order: ``x y z`` float32 (world frame,
    metres: voxel means, or centres with ``positions="center"``), ``nx ny nz`` float32 (unit
    normals, 0 where undefined), ``red green blue`` uchar (class colour of the label, grey
    without semantics), ``label`` int32 (-1 without semantics), ``confidence`` float32 (the
    label's probability). :func:`read_ply_points` reads its points and normals back (a map
    exported this way can be another map's prior model)."""
    if positions not in ("mean", "center"):
        raise MapError(f"positions: 'mean' or 'center', got {positions!r}")
    n = len(voxel_map)
    xyz = voxel_map.means() if positions == "mean" else voxel_map.voxel_centers()
    normals = np.nan_to_num(voxel_map.normals(), nan=0.0)
    labels = voxel_map.labels()
    colors = np.empty((n, 3), dtype=np.uint8)
    colors[:] = NO_SEMANTICS_COLOR
    sem = labels >= 0
    colors[sem] = class_colors(voxel_map.config.num_classes)[labels[sem]]
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
    vertex["confidence"] = voxel_map.confidence()
    props = "".join(
        f"property {kind} {name}\n" for name, kind in (
            ("x", "float"), ("y", "float"), ("z", "float"), ("nx", "float"),
            ("ny", "float"), ("nz", "float"), ("red", "uchar"), ("green", "uchar"),
            ("blue", "uchar"), ("label", "int"), ("confidence", "float"))
    )
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"comment smartedge semantic voxel map, voxel_size_m {voxel_map.config.voxel_size_m}\n"
        f"element vertex {n}\n{props}end_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertex.tobytes())
    logger.debug("map exported to %s: %d voxels", path, n)


# ----------------------------------------------------------------------------------------------
# prior models (PLY point clouds)


def read_ply_points(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (N, 3) float64 and, when the file has ``nx ny nz``, normals (N, 3) float64 (non-
    finite components set to 0) of a PLY point cloud (``ascii`` or ``binary_little_endian`` /
    ``binary_big_endian``; the ``vertex`` element must come first; other elements such as faces
    are ignored), in the file's frame and unit (for a prior model: world frame, metres). This
    is how a prior geometric model of the site is read (e.g. exported from CAD or CloudCompare,
    or written by :func:`write_map_ply`). Raises :class:`MapError` naming the file and what is
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
    logger.debug("PLY %s: %d points%s", where, len(points),
                 " with normals" if normals is not None else "")
    return points, normals


def _parse_ply_header(lines: list[str], where: str) -> tuple[str, int, list[tuple[str, str]]]:
    """Format, vertex count and vertex properties (name, numpy kind) of a PLY header's
    ``lines`` (the ``ply`` magic first)."""
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
