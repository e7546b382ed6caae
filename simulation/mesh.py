"""Triangle meshes and scenes for rendering (numpy only; the GL code is in :mod:`.render_gl`).

A :class:`Mesh` lives in its own frame (metres, z up); a :class:`SceneObject` places it in the
world (``T_world_object``) with an instance id (0: no instance; robots and other counted things
get 1, 2, ...) and a semantic class (:data:`CLASSES`). A :class:`Scene` is what one render pass
draws: objects, a light and a background colour. :func:`closed_outward_faces` finds the closed,
outward-oriented parts of a mesh (the renderer culls their back faces).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Final

import numpy as np

from protocol.semantic_classes import SEMANTIC_CLASSES

#: Semantic classes of the per-pixel class image, in id order (0 = nothing rendered): the
#: semantic-mapping legend of :mod:`protocol.semantic_classes`, one numbering for rendered
#: labels, the segmentation network, the edge's clouds and the map.
CLASSES: Final = SEMANTIC_CLASSES
CLASS_ID: Final = {name: i for i, name in enumerate(CLASSES)}


@dataclasses.dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in its own frame.

    ``vertices`` (N, 3) float32 metres; ``faces`` (M, 3) uint32 vertex indices, counter-clockwise
    seen from outside; ``colors`` (N, 3) float32 albedo in [0, 1]; ``normals`` (N, 3) float32 unit
    vertex normals (computed from the faces when not given); optional ``uv`` (N, 2) float32 with a
    ``texture`` (H, W, 3) uint8 image that multiplies the albedo.
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    normals: np.ndarray | None = None
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None

    def __post_init__(self) -> None:
        v = np.ascontiguousarray(self.vertices, dtype=np.float32)
        f = np.ascontiguousarray(self.faces, dtype=np.uint32)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"mesh: vertices {v.shape} / faces {f.shape}, expected (N,3)/(M,3)")
        if len(f) and int(f.max()) >= len(v):
            raise ValueError(f"mesh: face index {int(f.max())} >= {len(v)} vertices")
        if not np.all(np.isfinite(v)):
            raise ValueError("mesh: non-finite vertex coordinates")
        c = np.asarray(self.colors, dtype=np.float32)
        if c.shape == (3,):
            c = np.tile(c, (len(v), 1))
        if c.shape != v.shape:
            raise ValueError(f"mesh: colors {c.shape}, expected {v.shape} or (3,)")
        n = vertex_normals(v, f) if self.normals is None else np.asarray(self.normals, np.float32)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)
        object.__setattr__(self, "colors", np.ascontiguousarray(c))
        object.__setattr__(self, "normals", np.ascontiguousarray(n, dtype=np.float32))
        if (self.uv is None) != (self.texture is None):
            raise ValueError("mesh: uv and texture go together")
        if self.uv is not None:
            object.__setattr__(self, "uv", np.ascontiguousarray(self.uv, dtype=np.float32))
            object.__setattr__(self, "texture", np.ascontiguousarray(self.texture, np.uint8))

    @property
    def num_triangles(self) -> int:
        return len(self.faces)

    def transformed(self, T: np.ndarray) -> Mesh:
        """This mesh moved by the (4, 4) transform ``T`` (normals rotated)."""
        T = np.asarray(T, dtype=np.float64)
        v = self.vertices @ T[:3, :3].T + T[:3, 3]
        n = self.normals @ T[:3, :3].T  # type: ignore[operator]
        return dataclasses.replace(self, vertices=v, normals=n)

    def recolored(self, color: Sequence[float] | np.ndarray) -> Mesh:
        return dataclasses.replace(self, colors=np.asarray(color, dtype=np.float32))

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min (3,), max (3,)) of the vertices."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) area-weighted unit vertex normals of a triangle mesh."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n = np.zeros_like(v)
    if len(f):
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        for k in range(3):
            np.add.at(n, f[:, k], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.where(norm > 0, norm, 1.0)).astype(np.float32)


def concatenate(meshes: Sequence[Mesh]) -> Mesh:
    """One mesh of several (textures are dropped: only untextured meshes may be merged)."""
    if not meshes:
        raise ValueError("concatenate: no meshes")
    if any(m.texture is not None for m in meshes):
        raise ValueError("concatenate: textured meshes cannot be merged")
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(
        np.vstack([m.vertices for m in meshes]),
        np.vstack([m.faces + o for m, o in zip(meshes, offsets, strict=True)]),
        np.vstack([m.colors for m in meshes]),
        np.vstack([m.normals for m in meshes]),  # type: ignore[misc]
    )


def closed_outward_faces(mesh: Mesh, weld_m: float = 1e-6) -> np.ndarray:
    """(M,) bool: the faces of ``mesh`` that belong to a closed surface whose faces are all
    counter-clockwise seen from outside.

    Vertices closer than ``weld_m`` are merged first (flat-shaded meshes repeat them per face)
    and faces that collapse are left out (False). Per connected part, every directed edge must
    occur exactly once and its reverse exactly once, and the enclosed signed volume must be
    positive. Seen from outside its bounding box, such a part shows only front faces, so its
    back faces may be culled without changing the image; open parts (single-sided panels) and
    inside-out parts are drawn two-sided.
    """
    return closed_outward_faces_many([mesh], weld_m)[0]


def closed_outward_faces_many(meshes: Sequence[Mesh], weld_m: float = 1e-6
                              ) -> list[np.ndarray]:
    """:func:`closed_outward_faces` of each mesh, computed in one pass over all of them (the
    small meshes of a randomized scene cost numpy call overhead, not arithmetic). Vertices of
    different meshes are never welded together, so each result is the single-mesh one."""
    results = [np.zeros(len(m.faces), bool) for m in meshes]
    todo = [k for k, m in enumerate(meshes) if len(m.faces) >= 4]
    if not todo:
        return results
    verts = [meshes[k].vertices.astype(np.float64) for k in todo]
    counts = np.array([len(v) for v in verts])
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    face_counts = np.array([len(meshes[k].faces) for k in todo])
    v = np.concatenate(verts)
    faces = np.concatenate([meshes[k].faces.astype(np.int64) + o
                            for k, o in zip(todo, offsets, strict=True)])
    face_mesh = np.repeat(np.arange(len(todo)), face_counts)
    # weld within each mesh only: the mesh index is part of the key
    keys = np.empty((len(v), 4), np.int64)
    keys[:, :3] = np.round(v / weld_m)
    keys[:, 3] = np.repeat(np.arange(len(todo)), counts)
    _, welded = np.unique(keys, axis=0, return_inverse=True)
    f = welded.reshape(-1)[faces]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    # a mesh with fewer than 4 faces left cannot enclose anything (and was all-open before)
    kept_per_mesh = np.bincount(face_mesh[keep], minlength=len(todo))
    keep &= kept_per_mesh[face_mesh] >= 4
    keep = np.flatnonzero(keep)
    if len(keep) == 0:
        return results
    f = f[keep]
    n = int(f.max()) + 1
    a, b = f.ravel(), f[:, [1, 2, 0]].ravel()  # directed edges, three per face in face order

    # Connected parts: hook each root onto the smallest root it shares an edge with, then
    # compress paths fully; a few rounds suffice.
    parent = np.arange(n)
    while True:
        ra, rb = parent[a], parent[b]
        differ = ra != rb
        if not differ.any():
            break
        np.minimum.at(parent, np.maximum(ra, rb)[differ], np.minimum(ra, rb)[differ])
        while True:
            jumped = parent[parent]
            if np.array_equal(jumped, parent):
                break
            parent = jumped
    _, part = np.unique(parent[f[:, 0]], return_inverse=True)

    # An edge is paired when it occurs once and its reverse occurs exactly once.
    directed = a * n + b
    order = np.argsort(directed)
    ds = directed[order]
    same_next = ds[1:] == ds[:-1]
    repeated = np.zeros(len(ds), bool)
    repeated[1:] |= same_next
    repeated[:-1] |= same_next
    pos = np.minimum(np.searchsorted(ds, b * n + a), len(ds) - 1)
    paired = (ds[pos] == b * n + a) & ~repeated[pos]
    paired[order] &= ~repeated
    open_faces = ~paired.reshape(-1, 3).all(axis=1)
    num_parts = int(part.max()) + 1
    part_open = np.bincount(part, weights=open_faces, minlength=num_parts) > 0
    fv = faces[keep]
    volume6 = np.einsum("ij,ij->i", v[fv[:, 0]], np.cross(v[fv[:, 1]], v[fv[:, 2]]))
    part_volume = np.bincount(part, weights=volume6, minlength=num_parts)
    closed = np.zeros(len(faces), bool)
    closed[keep] = (~part_open & (part_volume > 0.0))[part]
    for k, piece in zip(todo, np.split(closed, np.cumsum(face_counts)[:-1]), strict=True):
        results[k] = piece
    return results


@dataclasses.dataclass(frozen=True, eq=False)
class SceneObject:
    """A mesh placed in the world: ``T_world_object`` (4, 4), ``instance_id`` (0: none),
    ``class_id`` (index into :data:`CLASSES`)."""

    mesh: Mesh
    T_world_object: np.ndarray
    instance_id: int = 0
    class_id: int = 0

    def __post_init__(self) -> None:
        T = np.asarray(self.T_world_object, dtype=np.float64)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"scene object: T_world_object must be a finite (4, 4), got {T.shape}")
        object.__setattr__(self, "T_world_object", T)
        if not 0 <= self.class_id < len(CLASSES):
            raise ValueError(f"scene object: class_id {self.class_id} not in 0..{len(CLASSES) - 1}")
        if not 0 <= self.instance_id < 2**24:
            raise ValueError(f"scene object: instance_id {self.instance_id} out of range")


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """What one render draws. ``light_dir_world`` (3,): direction the light comes *from*;
    ``ambient`` in [0, 1]; ``background_rgb`` (3,) in [0, 1] where nothing is drawn.
    ``light_rgb`` (3,): the key light's colour; ``fill_dir_world`` / ``fill_rgb``: a second
    light (black: none); ``specular`` >= 0 and ``shininess``: a Blinn-Phong highlight of the
    key light (0: matte). Shading per vertex: albedo x (ambient + (1 - ambient) x (key + fill))
    + highlight (the defaults give the plain one-light Lambert image).

    ``static_objects``: the first that many ``objects`` are the same :class:`SceneObject`
    instances from frame to frame (the site's floor, walls and furniture): a renderer may keep
    their render per camera and draw only the remaining objects on top of it, which gives the
    same image (they are drawn first either way). 0: nothing is kept.
    """

    objects: tuple[SceneObject, ...]
    light_dir_world: tuple[float, float, float] = (0.3, 0.2, 1.0)
    ambient: float = 0.45
    background_rgb: tuple[float, float, float] = (0.0, 0.0, 0.0)
    static_objects: int = 0
    light_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)
    fill_dir_world: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fill_rgb: tuple[float, float, float] = (0.0, 0.0, 0.0)
    specular: float = 0.0
    shininess: float = 16.0

    def __post_init__(self) -> None:
        if not 0 <= self.static_objects <= len(self.objects):
            raise ValueError(f"scene: static_objects {self.static_objects} not in "
                             f"0..{len(self.objects)}")
