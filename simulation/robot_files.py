"""Loading a user's own robot for rendering: a mesh file (OBJ, STL, PLY, GLB/glTF, through
``trimesh``, the ``sim`` extra, imported lazily), a URDF (its visual geometry with every joint at
0) and a keypoint file (keypoints on the URDF's links, moved to the base frame).

The meshes are :class:`simulation.mesh.Mesh` in the robot's base frame, as in
:mod:`simulation.robot_mesh`. Every error raised on purpose is a :class:`RobotMeshError` naming
the file and what is wrong.
"""

from __future__ import annotations

import logging
import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from core.config_file import ConfigReader, join_key, read_yaml_file
from core.geometry import rotation_from_rpy
from protocol.errors import ConfigFileError
from simulation.mesh import Mesh, concatenate
from simulation.robot_mesh import DEFAULT_COLOR, Color, albedo, box, cylinder, sphere, transform

logger = logging.getLogger(__name__)


class RobotMeshError(ConfigFileError, ValueError):
    """A robot mesh, URDF or keypoint file is missing, unreadable or invalid; the message names
    the file, the key or element (``link[wheel].visual[0]``, ``keypoints[2].link``) and why."""


def _existing_file(path: str | Path, what: str) -> Path:
    p = Path(path)
    if not p.is_file():
        raise RobotMeshError(str(p), "", f"{what} not found" if not p.exists()
                             else f"{what} is not a regular file")
    return p


def _trimesh_to_mesh(geom: Any, T: np.ndarray, default_color: Color, keep_texture: bool,
                     where: str) -> tuple[Mesh, bool]:
    """One trimesh.Trimesh moved by ``T`` (4, 4) → (:class:`Mesh`, whether the file gave it
    colours): smooth-shaded with edges sharper than 30 degrees kept; the file's colours, else
    ``default_color``."""
    import trimesh

    geom = trimesh.graph.smooth_shade(geom, angle=math.radians(30.0))
    visual = geom.visual
    uv = texture = None
    own_colors = visual.kind is not None
    if visual.kind == "texture":
        mat = visual.material
        if hasattr(mat, "to_simple"):
            mat = mat.to_simple()
        image = getattr(mat, "image", None)
        if keep_texture and image is not None and visual.uv is not None:
            uv = np.asarray(visual.uv, dtype=np.float32)
            texture = np.asarray(image.convert("RGB"), dtype=np.uint8)
            diffuse = np.asarray(getattr(mat, "diffuse", (255, 255, 255, 255)), dtype=np.float64)
            colors = np.tile(diffuse[:3] / 255.0, (len(geom.vertices), 1))
        else:
            colors = np.asarray(visual.to_color().vertex_colors, dtype=np.float64)[:, :3] / 255.0
    elif visual.kind in ("vertex", "face"):
        colors = np.asarray(visual.vertex_colors, dtype=np.float64)[:, :3] / 255.0
    else:
        colors = np.tile(albedo(default_color), (len(geom.vertices), 1))
    try:
        mesh = Mesh(np.asarray(geom.vertices), np.asarray(geom.faces), colors,
                    np.asarray(geom.vertex_normals), uv, texture)
    except ValueError as exc:
        raise RobotMeshError(where, "", f"invalid mesh: {exc}") from None
    return mesh.transformed(T), own_colors


def _load_parts(path: Path, scale: Sequence[float] | float, default_color: Color,
                keep_texture: bool) -> list[tuple[Mesh, bool]]:
    """The triangle meshes of a mesh file, each moved by its scene-graph transform and scaled
    by ``scale`` (one number or (3,) per axis), with whether the file gave it colours."""
    try:
        import trimesh
    except ImportError:  # pragma: no cover - trimesh is part of the sim extra
        raise RobotMeshError(str(path), "",
                             "loading mesh files needs trimesh (pip install 'trimesh>=4.0')"
                             ) from None
    try:
        scene = trimesh.load(str(path), force="scene")
    except Exception as exc:  # trimesh raises anything from its many parsers
        raise RobotMeshError(str(path), "", f"cannot read mesh: {type(exc).__name__}: {exc}"
                             ) from None
    S = np.diag([*np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)), 1.0])
    parts: list[tuple[Mesh, bool]] = []
    for node in scene.graph.nodes_geometry:
        T_file_node, geom_name = scene.graph[node]
        geom = scene.geometry.get(geom_name)
        if geom is None or not hasattr(geom, "faces") or len(geom.faces) == 0:
            continue  # point clouds, paths, empty meshes
        parts.append(_trimesh_to_mesh(geom, S @ np.asarray(T_file_node), default_color,
                                      keep_texture, str(path)))
    if not parts:
        raise RobotMeshError(str(path), "", "no triangles found (not a mesh file, empty, or "
                             "corrupt)")
    return parts


def load_robot_mesh(path: str | Path, *, scale: float | Sequence[float] = 1.0,
                    color: Color = DEFAULT_COLOR) -> Mesh:
    """A robot's mesh from an OBJ, STL, PLY, GLB/glTF (or any format trimesh reads), in the
    file's frame, which must be the robot base frame (x forward, y left, z up, origin on the
    floor at the rotation centre). ``scale`` (one number or (3,)) converts the file's units to
    metres (0.001 for millimetres).

    A multi-object file is flattened with its scene-graph transforms and merged; colours are the
    file's (vertex/face colours, or textures sampled at the vertices), ``color`` where it has
    none. A file with a single textured object keeps its image as ``uv`` + ``texture``.
    Raises :class:`RobotMeshError` for a missing, unreadable or empty file.
    """
    p = _existing_file(path, "mesh file")
    parts = [m for m, _ in _load_parts(p, scale, color, keep_texture=True)]
    mesh = parts[0] if len(parts) == 1 else concatenate(
        [m if m.texture is None else _untextured(m) for m in parts])
    logger.debug("loaded %s: %d triangles", p, mesh.num_triangles)
    return mesh


def _untextured(mesh: Mesh) -> Mesh:
    """``mesh`` without its image texture: the texture sampled at each vertex's uv."""
    tex = mesh.texture
    assert tex is not None and mesh.uv is not None
    h, w = tex.shape[:2]
    u = np.clip((mesh.uv[:, 0] % 1.0) * (w - 1), 0, w - 1).round().astype(int)
    v = np.clip((1.0 - mesh.uv[:, 1] % 1.0) * (h - 1), 0, h - 1).round().astype(int)
    colors = mesh.colors * tex[v, u].astype(np.float32) / 255.0
    return Mesh(mesh.vertices, mesh.faces, colors, mesh.normals)


# ---- URDF


_OPTENV_RE: Final = re.compile(r"\$\(optenv\s+\S+\s*([^)]*)\)")


def _floats(text: str | None, n: int, default: Sequence[float] | None, where: str, key: str,
            allow_one: bool = False) -> np.ndarray:
    """``n`` numbers of a URDF attribute (``"0 0 0.1"``; ``default`` when it is absent, an
    error if that is None); a leftover xacro ``$(optenv VAR default)`` takes its default, as
    xacro does when the variable is not set."""
    if text is None:
        if default is None:
            raise RobotMeshError(where, key, "required attribute is missing")
        return np.asarray(default, dtype=np.float64)
    vals = _OPTENV_RE.sub(lambda m: m.group(1), text).split()
    try:
        arr = np.array([float(x) for x in vals])
    except ValueError:
        raise RobotMeshError(where, key, f"expected {n} numbers, got {text!r}") from None
    if allow_one and arr.shape == (1,):
        arr = np.repeat(arr, n)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise RobotMeshError(where, key, f"expected {n} finite numbers, got {text!r}")
    return arr


def _origin(elem: ET.Element, where: str, key: str) -> np.ndarray:
    """(4, 4) transform of an element's ``<origin xyz rpy>`` (identity when absent)."""
    o = elem.find("origin")
    if o is None:
        return np.eye(4)
    xyz = _floats(o.get("xyz"), 3, (0.0, 0.0, 0.0), where, f"{key}.origin.xyz")
    rpy = _floats(o.get("rpy"), 3, (0.0, 0.0, 0.0), where, f"{key}.origin.rpy")
    return transform(rotation_from_rpy(*rpy), xyz)


def _resolve_uri(uri: str, urdf: Path,
                 package_dirs: Mapping[str, str | Path] | Sequence[str | Path]) -> tuple[
                     Path | None, list[Path]]:
    """(the file a URDF mesh ``filename`` names, or None; the candidates tried)."""
    if uri.startswith("file://"):
        cands = [Path(uri[len("file://"):])]
    elif uri.startswith("package://"):
        pkg, _, rel = uri[len("package://"):].partition("/")
        cands = []
        if isinstance(package_dirs, Mapping):
            if pkg in package_dirs:
                cands.append(Path(package_dirs[pkg]) / rel)
        else:
            for d in map(Path, package_dirs):
                cands.append(d / pkg / rel)
                if d.name == pkg:
                    cands.append(d / rel)
        # a URDF inside its package (pkg/urdf/robot.urdf) or next to it
        for anc in [urdf.parent, *urdf.parent.parents]:
            if anc.name == pkg:
                cands.append(anc / rel)
            cands.append(anc / pkg / rel)
        cands.append(urdf.parent / rel)
    else:
        p = Path(uri)
        cands = [p if p.is_absolute() else urdf.parent / p]
    for c in cands:
        if c.is_file():
            return c, cands
    return None, cands


def load_urdf(path: str | Path,
              package_dirs: Mapping[str, str | Path] | Sequence[str | Path] = (),
              base_link: str | None = None) -> tuple[Mesh, dict[str, np.ndarray]]:
    """The visual mesh of a URDF robot with every joint at position 0, in the base link's frame,
    and ``{link name: (4, 4) T_base_link}`` for every link.

    Visual geometry: ``<mesh filename scale>`` (any format :func:`load_robot_mesh` reads),
    ``<box size>``, ``<cylinder radius length>`` (about z, centred), ``<sphere radius>``, each
    placed by its ``<origin>``; colour from the visual's ``<material>`` (inline ``<color>`` or a
    robot-level material of that name) unless the mesh file has colours of its own, else grey.
    ``filename``: ``package://pkg/rel`` is looked up in ``package_dirs`` (a mapping package →
    folder, or folders holding packages or being one), then in the URDF's folder and its
    ancestors; ``file://`` and plain paths (relative to the URDF's folder) as they are.
    ``base_link``: the frame of the result (default: the root of the link tree; for a mobile
    robot that should be its floor-level base frame, e.g. ``base_footprint``).

    Raises :class:`RobotMeshError` (file and element named) for a missing or malformed URDF, a
    mesh file that is missing or unreadable, joints naming unknown links, or a link tree that
    is not one tree.
    """
    p = _existing_file(path, "URDF file")
    where = str(p)
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as exc:
        raise RobotMeshError(where, "", f"not valid XML: {exc}") from None
    except OSError as exc:
        raise RobotMeshError(where, "", f"cannot read URDF file: {exc.strerror}") from None
    if root.tag != "robot":
        raise RobotMeshError(where, "", f"root element is <{root.tag}>, expected <robot>")

    materials: dict[str, np.ndarray] = {}
    for m in root.findall("material"):
        col = m.find("color")
        if m.get("name") and col is not None:
            materials[m.get("name", "")] = _floats(col.get("rgba"), 4, None, where,
                                                   f"material[{m.get('name')}].color")[:3]
    links: dict[str, ET.Element] = {}
    for link in root.findall("link"):
        name = link.get("name")
        if not name:
            raise RobotMeshError(where, "link", "a <link> without a name")
        if name in links:
            raise RobotMeshError(where, f"link[{name}]", "duplicate link name")
        links[name] = link
    if not links:
        raise RobotMeshError(where, "", "no <link> elements")

    children: dict[str, list[tuple[str, np.ndarray]]] = {n: [] for n in links}
    parent_of: dict[str, str] = {}
    for joint in root.findall("joint"):
        jname = joint.get("name", "?")
        key = f"joint[{jname}]"
        pe, ce = joint.find("parent"), joint.find("child")
        if pe is None or ce is None:
            raise RobotMeshError(where, key, "needs <parent link> and <child link>")
        parent, child = pe.get("link", ""), ce.get("link", "")
        for role, name in (("parent", parent), ("child", child)):
            if name not in links:
                raise RobotMeshError(where, f"{key}.{role}", f"unknown link {name!r}")
        if child in parent_of:
            raise RobotMeshError(where, key, f"link {child!r} has two parent joints")
        parent_of[child] = parent
        children[parent].append((child, _origin(joint, where, key)))
    roots = [n for n in links if n not in parent_of]
    if len(roots) != 1:
        raise RobotMeshError(where, "joint", f"the links form {len(roots)} trees, expected one "
                             f"(roots: {roots[:10]})")

    T_root: dict[str, np.ndarray] = {roots[0]: np.eye(4)}
    stack = [roots[0]]
    while stack:
        name = stack.pop()
        for child, T_parent_child in children[name]:
            T_root[child] = T_root[name] @ T_parent_child
            stack.append(child)
    if len(T_root) != len(links):  # a cycle hangs off the tree
        raise RobotMeshError(where, "joint", "the joints contain a cycle")
    if base_link is not None and base_link not in links:
        raise RobotMeshError(where, "", f"base link {base_link!r} is not a link; links: "
                             f"{sorted(links)[:20]}")
    base = base_link or roots[0]
    T_base_root = np.linalg.inv(T_root[base])
    T_base = {n: T_base_root @ T for n, T in T_root.items()}

    cache: dict[tuple[Path, tuple[float, ...]], list[tuple[Mesh, bool]]] = {}
    meshes: list[Mesh] = []
    for name, link in links.items():
        for i, vis in enumerate(link.findall("visual")):
            key = f"link[{name}].visual[{i}]"
            T = T_base[name] @ _origin(vis, where, key)
            color = _material_color(vis, materials, where, key)
            meshes.extend(m.transformed(T) for m in _visual_geometry(
                vis, color, p, package_dirs, cache, where, key))
    if not meshes:
        raise RobotMeshError(where, "", "no visual geometry in any link")
    mesh = concatenate(meshes)
    logger.debug("loaded URDF %s: %d links, %d triangles", p, len(links), mesh.num_triangles)
    return mesh, T_base


def _material_color(vis: ET.Element, materials: Mapping[str, np.ndarray], where: str,
                    key: str) -> np.ndarray | None:
    mat = vis.find("material")
    if mat is None:
        return None
    col = mat.find("color")
    if col is not None:
        return np.clip(_floats(col.get("rgba"), 4, None, where, f"{key}.material.color")[:3], 0, 1)
    return materials.get(mat.get("name", ""))


def _visual_geometry(vis: ET.Element, color: np.ndarray | None, urdf: Path,
                     package_dirs: Mapping[str, str | Path] | Sequence[str | Path],
                     cache: dict[tuple[Path, tuple[float, ...]], list[tuple[Mesh, bool]]],
                     where: str,
                     key: str) -> list[Mesh]:
    """The meshes of one ``<visual>`` in its own frame (before its ``<origin>``)."""
    geo = vis.find("geometry")
    if geo is None or len(geo) == 0:
        raise RobotMeshError(where, key, "<visual> without <geometry>")
    g = geo[0]
    gkey = f"{key}.geometry.{g.tag}"
    c = DEFAULT_COLOR if color is None else color
    if g.tag == "box":
        return [box(_floats(g.get("size"), 3, None, where, f"{gkey}.size"), color=c)]
    if g.tag == "cylinder":
        r = _floats(g.get("radius"), 1, None, where, f"{gkey}.radius")[0]
        length = _floats(g.get("length"), 1, None, where, f"{gkey}.length")[0]
        return [cylinder(r, -length / 2, length / 2, c, 32)]
    if g.tag == "sphere":
        return [sphere(_floats(g.get("radius"), 1, None, where, f"{gkey}.radius")[0], color=c)]
    if g.tag != "mesh":
        raise RobotMeshError(where, gkey, "unsupported geometry; expected mesh, box, cylinder "
                             "or sphere")
    uri = g.get("filename")
    if not uri:
        raise RobotMeshError(where, f"{gkey}.filename", "missing")
    scale = _floats(g.get("scale"), 3, (1.0, 1.0, 1.0), where, f"{gkey}.scale", allow_one=True)
    file, tried = _resolve_uri(uri, urdf, package_dirs)
    if file is None:
        raise RobotMeshError(where, f"{gkey}.filename", f"mesh file {uri!r} not found; tried "
                             + ", ".join(str(t) for t in tried[:6]))
    ck = (file.resolve(), tuple(scale.tolist()))
    if ck not in cache:
        cache[ck] = _load_parts(file, scale, DEFAULT_COLOR, keep_texture=False)
    # The URDF's colour is for files without colours of their own (as RViz does).
    return [m if own or color is None else m.recolored(color) for m, own in cache[ck]]


# ---- keypoint files


def load_keypoint_file(path: str | Path,
                       link_transforms: Mapping[str, np.ndarray] | None = None,
                       ) -> tuple[tuple[str, ...], np.ndarray]:
    """Keypoints of a robot from a YAML file, in the base frame.

    Format::

        keypoints:
          - {name: front_bumper, link: front_bumper_link, xyz_m: [0.05, 0.0, 0.02]}
          - {name: top_rear, xyz_m: [-0.3, 0.0, 0.4]}      # no link: the base frame

    ``xyz_m`` is in the frame of ``link`` (metres), moved to the base frame with
    ``link_transforms[link]`` ((4, 4) ``T_base_link``, as :func:`load_urdf` returns). At least 3
    keypoints, unique names of ``[A-Za-z0-9_.-]``. Returns (names, (M, 3) positions).
    Raises :class:`RobotMeshError` naming the file and key for a missing file, bad YAML, a
    wrong or unknown key, or a link that is not in ``link_transforms``.
    """
    p = _existing_file(path, "keypoint file")
    doc = read_yaml_file(p, "keypoint file", RobotMeshError)
    ctx = ConfigReader(str(p), RobotMeshError)
    top = ctx.mapping("", doc)
    ctx.no_unknown("", top, {"keypoints"})
    kps = ctx.require("", top, "keypoints")
    if not isinstance(kps, list) or len(kps) < 3:
        raise ctx.fail("keypoints", "expected a list of at least 3 keypoints {name, link, xyz_m}")
    names: list[str] = []
    xyz: list[np.ndarray] = []
    links = link_transforms or {}
    for i, kp in enumerate(kps):
        ik = f"keypoints[{i}]"
        kp = ctx.mapping(ik, kp)
        ctx.no_unknown(ik, kp, {"name", "link", "xyz_m"})
        name = ctx.ident(join_key(ik, "name"), ctx.require(ik, kp, "name"))
        if name in names:
            raise ctx.fail(join_key(ik, "name"), f"duplicate keypoint name {name!r}")
        pt = ctx.vector(join_key(ik, "xyz_m"), ctx.require(ik, kp, "xyz_m"), 3)
        link = kp.get("link")
        if link is not None:
            if not isinstance(link, str) or link not in links:
                known = sorted(links)
                raise ctx.fail(join_key(ik, "link"), f"unknown link {link!r}; " + (
                    f"links: {known[:20]}" if known else "no link transforms given (load the "
                    "URDF and pass its link transforms)"))
            T = np.asarray(links[link], dtype=np.float64)
            pt = T[:3, :3] @ pt + T[:3, 3]
        names.append(name)
        xyz.append(pt)
    return tuple(names), np.stack(xyz)
