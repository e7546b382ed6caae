"""Robot meshes for rendering: procedural primitives, the built-in HSR-like robot, the distance
from keypoints to a mesh's surface and the :class:`RobotModel` of a loaded robot (the loaders of a
user's own robot files are in :mod:`simulation.robot_files`).

Every mesh here is a :class:`simulation.mesh.Mesh` in the robot's **base frame**: metres,
x forward, y left, z up, origin on the floor at the rotation centre (the frame of
``core.site.RobotModel.keypoints_base_m``). Colours are albedo in [0, 1]; the "textures" of
the built-in robot are vertex colours on cells with their own vertices, so merged meshes keep
them (:func:`simulation.mesh.concatenate` drops image textures). numpy only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Final

import numpy as np

from core.site import RobotModel
from simulation.mesh import Mesh, concatenate

Color = Sequence[float] | np.ndarray

#: Default albedo of parts that have no colour of their own (loaded meshes, URDF visuals).
DEFAULT_COLOR: Final = (0.6, 0.6, 0.6)

# Palette of the HSR-like robot (albedo).
_WHITE: Final = (0.92, 0.92, 0.90)
_LIGHT_GREY: Final = (0.74, 0.75, 0.76)
_DARK_GREY: Final = (0.20, 0.20, 0.22)
_BLACK: Final = (0.06, 0.06, 0.07)
_BUMPER_BLUE: Final = (0.10, 0.32, 0.78)
_LED_CYAN: Final = (0.15, 0.85, 0.90)
_LENS: Final = (0.25, 0.38, 0.50)
_FINGER_ORANGE: Final = (0.95, 0.45, 0.10)

#: Reference footprint radius (m) of the HSR that the built-in robot's horizontal sizes are
#: designed for; other radii scale them.
HSR_FOOTPRINT_RADIUS_M: Final = 0.215


# --------------------------------------------------------------------------------------------
# primitives
# --------------------------------------------------------------------------------------------


def albedo(color: Color) -> np.ndarray:
    """(3,) float64 albedo of ``color`` (three numbers); ValueError outside [0, 1]."""
    c = np.asarray(color, dtype=np.float64).reshape(3)
    if not np.all((c >= 0.0) & (c <= 1.0)):
        raise ValueError(f"colour {c.tolist()} outside [0, 1]")
    return c


def translation(xyz: Sequence[float] | np.ndarray) -> np.ndarray:
    """(4, 4) transform that translates by ``xyz`` (3,)."""
    T = np.eye(4)
    T[:3, 3] = np.asarray(xyz, dtype=np.float64).reshape(3)
    return T


def transform(rotation: np.ndarray | None = None,
              xyz: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) transform from a (3, 3) rotation (identity if None) and a translation (3,)."""
    T = translation(xyz)
    if rotation is not None:
        T[:3, :3] = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    return T


def _rotation_z_to(direction: np.ndarray) -> np.ndarray:
    """(3, 3) rotation taking +z onto the unit vector along ``direction`` (3,)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    z = np.array([0.0, 0.0, 1.0])
    c = float(z @ d)
    if c > 1.0 - 1e-12:
        return np.eye(3)
    if c < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(z, d)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def lathe(profile_rz: np.ndarray, colors: Color | np.ndarray, segments: int = 48,
          angle0_rad: float = 0.0, angle1_rad: float = 2.0 * math.pi) -> Mesh:
    """A surface of revolution about +z.

    ``profile_rz`` (K, 2): (radius, z) points in metres, traced bottom cap outwards, up the
    outside, top cap inwards (a solid cylinder is ``(0, z0), (r, z0), (r, z0), (r, z1),
    (r, z1), (0, z1)``), so that faces are counter-clockwise seen from outside.
    Repeating a point makes a sharp edge there (the zero-length step adds no triangles and the
    two copies keep their own normals) and lets the colour change there. ``colors``: (3,) or
    (K, 3), one per profile point. A partial revolution (``angle1_rad - angle0_rad < 2 pi``) is
    closed at both ends with fans of the profile (the profile must then be a closed convex loop).
    """
    prof = np.asarray(profile_rz, dtype=np.float64).reshape(-1, 2)
    K = len(prof)
    if K < 2 or segments < 3 or np.any(prof[:, 0] < 0.0):
        raise ValueError("lathe: need >= 2 profile points with radius >= 0 and >= 3 segments")
    cols = np.asarray(colors, dtype=np.float64)
    cols = np.tile(albedo(cols), (K, 1)) if cols.shape == (3,) else cols.reshape(K, 3)
    full = angle1_rad - angle0_rad >= 2.0 * math.pi - 1e-9
    n_ang = segments if full else segments + 1
    ang = angle0_rad + (angle1_rad - angle0_rad) * np.arange(n_ang) / segments
    ca, sa = np.cos(ang), np.sin(ang)
    # vertices[k * n_ang + j]: profile point k at angle j
    verts = np.stack([prof[:, :1] * ca[None, :], prof[:, :1] * sa[None, :],
                      np.repeat(prof[:, 1:2], n_ang, axis=1)], axis=-1).reshape(-1, 3)
    vcols = np.repeat(cols, n_ang, axis=0)
    faces: list[np.ndarray] = []
    j = np.arange(segments)
    j1 = (j + 1) % n_ang
    # np.allclose(prof[k], prof[k + 1]) for every k at once (finite profiles)
    repeated = np.all(np.abs(prof[:-1] - prof[1:]) <= 1e-8 + 1e-5 * np.abs(prof[1:]), axis=1)
    for k in range(K - 1):
        if repeated[k]:
            continue  # sharp edge / colour change: no triangles between the copies
        a, b = k * n_ang + j, k * n_ang + j1
        c, d = (k + 1) * n_ang + j1, (k + 1) * n_ang + j
        if prof[k, 0] > 0.0:
            faces.append(np.stack([a, b, c], axis=1))
        if prof[k + 1, 0] > 0.0:
            faces.append(np.stack([a, c, d], axis=1))
    normals = None
    if not full:
        # end caps: fans of the profile at both ends, with their own (flat) vertices
        keep = np.r_[True, np.any(np.abs(np.diff(prof, axis=0)) > 1e-12, axis=1)]
        loop = prof[keep]  # without the repeated points of sharp edges
        if len(loop) > 1 and np.allclose(loop[0], loop[-1]):
            loop = loop[:-1]
        caps_v, caps_f, caps_c, caps_n = [], [], [], []
        base = len(verts)
        for angle, sign in ((angle0_rad, -1.0), (angle1_rad, 1.0)):
            c0, s0 = math.cos(angle), math.sin(angle)
            pts = np.column_stack([loop[:, 0] * c0, loop[:, 0] * s0, loop[:, 1]])
            fan = np.array([[0, i, i + 1] for i in range(1, len(pts) - 1)])
            outward = sign * np.array([-s0, c0, 0.0])
            fn = np.cross(pts[fan[:, 1]] - pts[0], pts[fan[:, 2]] - pts[0]).sum(axis=0)
            if fn @ outward < 0.0:
                fan = fan[:, ::-1]
            caps_v.append(pts)
            caps_f.append(fan + base)
            caps_c.append(np.tile(cols[0], (len(pts), 1)))
            caps_n.append(np.tile(outward, (len(pts), 1)))
            base += len(pts)
        side = Mesh(verts, np.vstack(faces), vcols)
        verts = np.vstack([verts, *caps_v])
        faces = [np.vstack(faces), *caps_f]
        vcols = np.vstack([vcols, *caps_c])
        normals = np.vstack([side.normals, *caps_n])
    return Mesh(verts, np.vstack(faces), vcols, normals)


def cylinder(radius_m: float, z0_m: float, z1_m: float, color: Color = DEFAULT_COLOR,
             segments: int = 48, caps: bool = True) -> Mesh:
    """A cylinder about +z from ``z0_m`` to ``z1_m`` (flat caps unless ``caps`` is False);
    2 * ``segments`` side triangles + ``segments`` per cap."""
    r = float(radius_m)
    prof = [(r, z0_m), (r, z1_m)]
    if caps:
        prof = [(0.0, z0_m), (r, z0_m), *prof, (r, z1_m), (0.0, z1_m)]
    return lathe(np.array(prof), color, segments)


def box(size_m: Sequence[float], center_m: Sequence[float] = (0.0, 0.0, 0.0),
        color: Color = DEFAULT_COLOR,
        face_colors: Mapping[str, Color] | None = None) -> Mesh:
    """An axis-aligned box of extent ``size_m`` (3,) centred at ``center_m`` (3,): 12 triangles,
    flat normals. ``face_colors`` overrides the colour of faces named ``+x -x +y -y +z -z``."""
    h = np.asarray(size_m, dtype=np.float64).reshape(3) / 2.0
    c = np.asarray(center_m, dtype=np.float64).reshape(3)
    face_colors = dict(face_colors or {})
    unknown = set(face_colors) - {"+x", "-x", "+y", "-y", "+z", "-z"}
    if unknown:
        raise ValueError(f"box: unknown faces {sorted(unknown)}")
    if face_colors:
        cols = np.repeat(np.stack([albedo(face_colors.get(name, color))
                                   for name in _BOX_FACE_NAMES]), 4, axis=0)
    else:
        cols = np.tile(albedo(color), (24, 1))
    return Mesh(_BOX_CORNER_SIGNS * h + c, _BOX_FACES, cols, _BOX_NORMALS)


def _box_pattern() -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
    """Corner signs (24, 3), faces (12, 3), normals (24, 3) and face names of :func:`box`: per
    axis and sign one quad, corners counter-clockwise seen from outside."""
    signs, normals, names = [], [], []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for sign in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            quad = np.zeros((4, 3))
            quad[:, axis] = sign
            # (u, v) = (-,-), (+,-), (+,+), (-,+)
            quad[:, u] = np.array([-1.0, 1.0, 1.0, -1.0]) * sign
            quad[:, v] = np.array([-1.0, -1.0, 1.0, 1.0])
            signs.append(quad)
            normals.append(np.tile(n, (4, 1)))
            names.append(("+" if sign > 0 else "-") + "xyz"[axis])
    faces = np.array([[q * 4, q * 4 + 1, q * 4 + 2] for q in range(6)]
                     + [[q * 4, q * 4 + 2, q * 4 + 3] for q in range(6)])
    return np.vstack(signs), faces, np.vstack(normals), tuple(names)


# the ±1 signs are exact, so sign * half-size + centre is what a per-face loop computes
_BOX_CORNER_SIGNS, _BOX_FACES, _BOX_NORMALS, _BOX_FACE_NAMES = _box_pattern()


def sphere(radius_m: float, center_m: Sequence[float] = (0.0, 0.0, 0.0),
           color: Color = DEFAULT_COLOR, segments: int = 32, rings: int = 16) -> Mesh:
    """A UV sphere (``rings`` latitude steps) centred at ``center_m``."""
    t = np.linspace(-math.pi / 2.0, math.pi / 2.0, rings + 1)
    prof = np.column_stack([radius_m * np.cos(t), radius_m * np.sin(t)])
    prof[[0, -1], 0] = 0.0
    return lathe(prof, color, segments).transformed(translation(center_m))


def capsule(p0_m: Sequence[float], p1_m: Sequence[float], radius_m: float,
            color: Color = DEFAULT_COLOR, segments: int = 24, rings: int = 6) -> Mesh:
    """A capsule (cylinder with hemispherical ends) of ``radius_m`` around the segment from
    ``p0_m`` (3,) to ``p1_m`` (3,)."""
    p0 = np.asarray(p0_m, dtype=np.float64)
    p1 = np.asarray(p1_m, dtype=np.float64)
    length = float(np.linalg.norm(p1 - p0))
    if length <= 0.0:
        return sphere(radius_m, p0, color, segments, 2 * rings)
    t = np.linspace(0.0, math.pi / 2.0, rings + 1)
    bottom = np.column_stack([radius_m * np.sin(t), -radius_m * np.cos(t)])
    top = np.column_stack([radius_m * np.cos(t), length + radius_m * np.sin(t)])
    prof = np.vstack([bottom, top])
    prof[[0, -1], 0] = 0.0
    return lathe(prof, color, segments).transformed(transform(_rotation_z_to(p1 - p0), p0))


def grid_panel(cell_colors: np.ndarray, width_m: float, height_m: float) -> Mesh:
    """A flat rectangular panel in the y-z plane facing +x, centred at the origin, painted cell
    by cell: ``cell_colors`` (rows, cols, 3), row 0 at the top, column 0 on the left as seen from
    the front (at -y). Each cell has its own 4 vertices, so colours are sharp (a "texture" that
    survives :func:`concatenate`)."""
    cc = np.asarray(cell_colors, dtype=np.float64)
    if cc.ndim != 3 or cc.shape[2] != 3:
        raise ValueError(f"grid_panel: cell_colors {cc.shape}, expected (rows, cols, 3)")
    rows, ncols = cc.shape[:2]
    y = np.linspace(-width_m / 2.0, width_m / 2.0, ncols + 1)
    z = np.linspace(height_m / 2.0, -height_m / 2.0, rows + 1)
    r, c = np.meshgrid(np.arange(rows), np.arange(ncols), indexing="ij")
    r, c = r.ravel(), c.ravel()
    # corners counter-clockwise seen from +x: bottom-left(-y), bottom-right, top-right, top-left
    ys = np.stack([y[c], y[c + 1], y[c + 1], y[c]], axis=1)
    zs = np.stack([z[r + 1], z[r + 1], z[r], z[r]], axis=1)
    verts = np.stack([np.zeros_like(ys), ys, zs], axis=-1).reshape(-1, 3)
    q = np.arange(len(r)) * 4
    faces = np.vstack([np.stack([q, q + 1, q + 2], 1), np.stack([q, q + 2, q + 3], 1)])
    cols = np.repeat(cc.reshape(-1, 3), 4, axis=0)
    normals = np.tile([1.0, 0.0, 0.0], (len(verts), 1))
    return Mesh(verts, faces, cols, normals)


# 3x5 bitmap glyphs of the logo on the HSR-like robot's back.
_GLYPHS: Final = {
    "H": ("#.#", "#.#", "###", "#.#", "#.#"),
    "S": ("###", "#..", "###", "..#", "###"),
    "R": ("##.", "#.#", "##.", "#.#", "#.#"),
}


def text_cells(text: str, ink: Color, paper: Color, margin: int = 1) -> np.ndarray:
    """(rows, cols, 3) cell colours spelling ``text`` (letters of ``H S R``) in a 3x5 bitmap
    font with one blank column between letters, for :func:`grid_panel`."""
    glyphs = [_GLYPHS[ch] for ch in text]
    width = 4 * len(glyphs) - 1 + 2 * margin
    mask = np.zeros((5 + 2 * margin, width), dtype=bool)
    for i, g in enumerate(glyphs):
        for row, line in enumerate(g):
            for col, ch in enumerate(line):
                mask[margin + row, margin + 4 * i + col] = ch == "#"
    return np.where(mask[..., None], albedo(ink), albedo(paper))


# --------------------------------------------------------------------------------------------
# the built-in HSR-like robot
# --------------------------------------------------------------------------------------------


def _base_top_z(model: RobotModel) -> float:
    """Height (m) of the base's top plate: the highest keypoint on the base's rim (within 20 %
    of the footprint radius from it), 0.345 m (the HSR's) when there is none."""
    kp = np.asarray(model.keypoints_base_m, dtype=np.float64).reshape(-1, 3)
    rim = kp[np.hypot(kp[:, 0], kp[:, 1]) >= 0.8 * model.footprint_radius_m]
    z = float(rim[:, 2].max()) if len(rim) else 0.345
    return float(np.clip(z, 0.12, max(0.12, 0.6 * model.height_m)))


def hsr_like_parts(model: RobotModel, segments: int = 64) -> dict[str, Mesh]:
    """The parts of an HSR-like robot in the base frame, by name (for per-part use); see
    :func:`hsr_like_mesh` for the shape."""
    r = float(model.footprint_radius_m)
    s = r / HSR_FOOTPRINT_RADIUS_M  # horizontal scale
    H = float(model.height_m)
    z_top = _base_top_z(model)
    r_rim = r + 0.01 * s  # top plate rim and front bumper stand out 1 cm
    lid = 0.015  # thickness of the top plate
    parts: dict[str, Mesh] = {}

    # Base: dark lower band, white body, light-grey top plate with an overhanging rim.
    z_band = min(0.09, 0.3 * z_top)
    prof = [(0.0, 0.01), (r, 0.01), (r, 0.01), (r, z_band), (r, z_band), (r, z_top - lid),
            (r, z_top - lid), (r_rim, z_top - lid), (r_rim, z_top - lid), (r_rim, z_top),
            (r_rim, z_top), (0.0, z_top)]
    cols = [_DARK_GREY] * 4 + [_WHITE] * 2 + [_LIGHT_GREY] * 6
    parts["base"] = lathe(np.array(prof), np.array(cols), segments)
    # Front bumper (+-55 deg about +x) and a status LED strip over the front half only.
    a = math.radians(55.0)
    shell = [(r - 0.002, 0.02), (r_rim, 0.02), (r_rim, 0.02), (r_rim, z_band + 0.01),
             (r_rim, z_band + 0.01), (r - 0.002, z_band + 0.01), (r - 0.002, z_band + 0.01),
             (r - 0.002, 0.02)]
    parts["bumper"] = lathe(np.array(shell), _BUMPER_BLUE, segments // 2, -a, a)
    z_led = z_top - lid - 0.035
    led = [(r - 0.002, z_led), (r + 0.003, z_led), (r + 0.003, z_led),
           (r + 0.003, z_led + 0.012), (r + 0.003, z_led + 0.012), (r - 0.002, z_led + 0.012),
           (r - 0.002, z_led + 0.012), (r - 0.002, z_led)]
    parts["led_strip"] = lathe(np.array(led), _LED_CYAN, segments // 2, -math.pi / 2,
                               math.pi / 2)

    # Torso column set back from the centre: dark telescopic lower cover, white upper body.
    tx, tdx, tdy = -0.085 * s, 0.16 * s, 0.20 * s
    head_h, sensor_h = 0.13, 0.03  # head box and the depth-sensor bar on it reach height_m
    z_torso = max(z_top + 0.25, H - head_h - sensor_h - 0.04)
    z_split = z_top + 0.3 * (z_torso - z_top)
    parts["torso_lower"] = box((tdx, tdy, z_split - z_top), (tx, 0.0, (z_top + z_split) / 2),
                               _DARK_GREY)
    parts["torso_upper"] = box((tdx, tdy, z_torso - z_split), (tx, 0.0, (z_split + z_torso) / 2),
                               _WHITE)
    # "HSR" logo on the back of the torso (reads correctly from behind).
    cells = text_cells("HSR", _BLACK, _LIGHT_GREY)
    logo_w = 0.8 * tdy
    logo_h = logo_w * cells.shape[0] / cells.shape[1]
    T_logo = transform(np.diag([-1.0, -1.0, 1.0]),
                       (tx - tdx / 2 - 0.002, 0.0, z_split + 0.6 * (z_torso - z_split)))
    parts["logo"] = grid_panel(cells, logo_w, logo_h).transformed(T_logo)

    # Neck and head: white head with a dark face panel, two stereo lenses and a depth-sensor
    # bar on the front.
    hx, hdx, hdy = -0.045 * s, 0.15 * s, 0.24 * s
    z_head = max(H - head_h - sensor_h, z_torso + 0.02)
    parts["neck"] = cylinder(0.035 * s, z_torso, z_head, _DARK_GREY, segments // 2,
                             caps=False).transformed(translation((hx - 0.01 * s, 0.0, 0.0)))
    parts["head"] = box((hdx, hdy, head_h), (hx, 0.0, z_head + head_h / 2), _WHITE)
    x_face = hx + hdx / 2
    parts["face"] = box((0.006, 0.9 * hdy, 0.6 * head_h), (x_face + 0.003, 0.0,
                                                            z_head + 0.45 * head_h), _BLACK)
    lens_T = transform(_rotation_z_to(np.array([1.0, 0.0, 0.0])))
    for side, y in (("left", 0.06 * s), ("right", -0.06 * s)):
        lens = cylinder(0.016 * s, 0.0, 0.01, _LENS, segments // 2).transformed(lens_T)
        parts[f"lens_{side}"] = lens.transformed(
            translation((x_face + 0.006, y, z_head + 0.5 * head_h)))
    parts["depth_sensor"] = box((0.04 * s, 0.17 * s, sensor_h),
                                (x_face - 0.02 * s, 0.0, z_head + head_h + sensor_h / 2),
                                _DARK_GREY)

    # Folded arm on the front right: shoulder on the torso front, upper arm down to an elbow
    # above the base, forearm forward to the wrist, hand with two fingers pointing forward.
    y_arm = -0.10 * s
    x_torso_front = tx + tdx / 2
    z_shoulder = z_split + 0.5 * (z_torso - z_split)
    z_elbow = z_top + 0.075
    parts["shoulder"] = box((0.06 * s, 0.08 * s, 0.11),
                            (x_torso_front + 0.03 * s, -0.08 * s, z_shoulder), _DARK_GREY)
    elbow = (x_torso_front + 0.05 * s, y_arm, z_elbow)
    parts["upper_arm"] = capsule((x_torso_front + 0.05 * s, y_arm, z_shoulder), elbow,
                                 0.035 * s, _WHITE, segments // 2)
    wrist = (0.075 * s, y_arm, z_elbow)
    parts["forearm"] = capsule(elbow, wrist, 0.03 * s, _WHITE, segments // 2)
    parts["hand"] = box((0.05 * s, 0.06 * s, 0.06), (0.1 * s, y_arm, z_elbow), _DARK_GREY)
    for side, dy in (("left", 0.02 * s), ("right", -0.02 * s)):
        parts[f"finger_{side}"] = box(
            (0.04 * s, 0.012 * s, 0.03), (0.145 * s, y_arm + dy, z_elbow), _DARK_GREY,
            face_colors={"+x": _FINGER_ORANGE, "+z": _FINGER_ORANGE})
    return parts


def hsr_like_mesh(model: RobotModel, segments: int = 64) -> Mesh:
    """An HSR-like robot in the base frame (one untextured mesh, vertex colours), sized by
    ``model`` (footprint radius; ``height_m`` is the top of the head).

    Shape: a round base of the footprint radius with a dark lower band, a light-grey top plate
    whose rim stands out 1 cm, a blue front bumper (+-55 deg) and a cyan LED strip on the front
    half; a torso column set back from the centre (dark lower cover, white upper part, an "HSR"
    logo on its back); a white head with a black face panel, two stereo lenses and a depth-sensor
    bar on the front; a folded arm on the front right (y < 0) with an orange-tipped hand. Front,
    back, left and right all look different.

    The base's top plate is at the highest keypoint on the base's rim, so rim keypoints lie on
    the top plate's edge; with the default site's HSR keypoints every keypoint is within 1 mm
    of the surface (``front_top`` / ``front_bottom`` lie on the rim edge / the bumper, the
    others on the base's edge and side).
    """
    return concatenate(list(hsr_like_parts(model, segments).values()))


def surface_distance(mesh: Mesh, points_m: np.ndarray) -> np.ndarray:
    """(M,) Euclidean distance (m) from each of ``points_m`` (M, 3) (mesh frame) to the closest
    point of ``mesh``'s triangles."""
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    tri = mesh.vertices.astype(np.float64)[mesh.faces.astype(np.int64)]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, bc = b - a, c - a, c - b
    out = np.empty(len(pts))
    with np.errstate(divide="ignore", invalid="ignore"):
        for i, p in enumerate(pts):
            out[i] = np.sqrt(_closest_sq_dist(p, a, b, c, ab, ac, bc).min())
    return out


def _closest_sq_dist(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray,
                     ab: np.ndarray, ac: np.ndarray, bc: np.ndarray) -> np.ndarray:
    """Squared distances from point ``p`` (3,) to triangles (a, b, c) (each (F, 3)): the
    Voronoi-region test of Ericson, Real-Time Collision Detection, 5.1.5, vectorized."""

    def dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", u, v)

    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    denom = va + vb + vc
    # interior (face region) by default
    v = vb / denom
    w = vc / denom
    q = a + ab * v[:, None] + ac * w[:, None]
    # edges and vertices, in reverse order of precedence
    m = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    q = np.where(m[:, None], b + bc * t[:, None], q)
    m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    t = d2 / (d2 - d6)
    q = np.where(m[:, None], a + ac * t[:, None], q)
    q = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, q)
    m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    t = d1 / (d1 - d3)
    q = np.where(m[:, None], a + ab * t[:, None], q)
    q = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, q)
    q = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, q)
    dist2 = np.sum((q - p) ** 2, axis=1)
    # degenerate (zero-area) triangles: fall back to their vertices
    bad = ~np.isfinite(dist2)
    if np.any(bad):
        dist2[bad] = np.min(np.stack([np.sum((x[bad] - p) ** 2, axis=1) for x in (a, b, c)]),
                            axis=0)
    return dist2


def robot_model_from_mesh(name: str, mesh: Mesh, keypoint_names: Sequence[str],
                          keypoints_base_m: np.ndarray) -> RobotModel:
    """A :class:`RobotModel` for a loaded robot: the keypoints (M, 3) in the base frame, the
    footprint radius as the largest horizontal distance of a vertex from the base origin and
    the height as the highest vertex (m)."""
    kp = np.array(keypoints_base_m, dtype=np.float64).reshape(-1, 3)
    if len(kp) != len(keypoint_names):
        raise ValueError(f"{len(keypoint_names)} keypoint names for {len(kp)} keypoints")
    kp.setflags(write=False)
    v = mesh.vertices.astype(np.float64)
    radius = float(np.hypot(v[:, 0], v[:, 1]).max())
    return RobotModel(name, tuple(keypoint_names), kp, radius, float(v[:, 2].max()))


# --------------------------------------------------------------------------------------------
# the second built-in robot: a box-shaped base
# --------------------------------------------------------------------------------------------

#: name of the box-shaped base robot model (:func:`box_base_model`, :func:`box_base_mesh`)
BOX_BASE_MODEL: Final = "box_base"
#: the box base's body: length (x), width (y), height (z) in metres, ground clearance (m)
BOX_BASE_SIZE_M: Final = (0.5, 0.4, 0.3)
BOX_BASE_CLEARANCE_M: Final = 0.04

_BOX_ORANGE: Final = (0.93, 0.52, 0.12)
_BOX_YELLOW: Final = (0.95, 0.82, 0.20)


def box_base_keypoints(size_m: Sequence[float] = BOX_BASE_SIZE_M,
                       clearance_m: float = BOX_BASE_CLEARANCE_M
                       ) -> tuple[tuple[str, ...], np.ndarray]:
    """(names, (12, 3) base-frame positions in metres) of the box base's keypoints: the body's
    8 corners (``front_left_top`` ... ``rear_right_bottom``) and the midpoints of its 4 top
    edges (``front_top``, ``left_top``, ``rear_top``, ``right_top``): all on rigid edges."""
    lx, ly, h = (float(v) for v in size_m)
    hx, hy = lx / 2.0, ly / 2.0
    z0, z1 = float(clearance_m), float(clearance_m) + h
    names: list[str] = []
    pts: list[tuple[float, float, float]] = []
    for zname, z in (("top", z1), ("bottom", z0)):
        for xname, x in (("front", hx), ("rear", -hx)):
            for yname, y in (("left", hy), ("right", -hy)):
                names.append(f"{xname}_{yname}_{zname}")
                pts.append((x, y, z))
    for name, xy in (("front_top", (hx, 0.0)), ("left_top", (0.0, hy)),
                     ("rear_top", (-hx, 0.0)), ("right_top", (0.0, -hy))):
        names.append(name)
        pts.append((xy[0], xy[1], z1))
    return tuple(names), np.array(pts)


def box_base_parts(model: RobotModel) -> dict[str, Mesh]:
    """The parts of the box base in the base frame, sized by ``model``'s keypoints (the body is
    their bounding box, so a site file may scale it); see :func:`box_base_mesh`."""
    kp = np.asarray(model.keypoints_base_m, dtype=np.float64).reshape(-1, 3)
    lo, hi = kp.min(axis=0), kp.max(axis=0)
    size = hi - lo
    if np.any(size <= 0.0):
        raise ValueError(f"robot model {model.name!r}: the box base's keypoints span no volume")
    center = (lo + hi) / 2.0
    parts: dict[str, Mesh] = {}
    # body: orange sides, a dark front face with a yellow stripe, a light-grey lid
    parts["body"] = box(size, center, _BOX_ORANGE,
                        face_colors={"+z": _LIGHT_GREY, "+x": _DARK_GREY, "-x": _WHITE})
    stripe_h = 0.2 * size[2]
    parts["front_stripe"] = box((0.006, 0.9 * size[1], stripe_h),
                                (hi[0] + 0.003, center[1], hi[2] - 1.5 * stripe_h), _BOX_YELLOW)
    # four wheels under the body (dark, inside the footprint)
    wheel_r = max(0.01, float(lo[2]))
    axle_T = transform(_rotation_z_to(np.array([0.0, 1.0, 0.0])))
    for xname, x in (("front", lo[0] + 0.25 * size[0]), ("rear", hi[0] - 0.25 * size[0])):
        for yname, y in (("left", hi[1] - 0.04), ("right", lo[1] + 0.04)):
            wheel = cylinder(wheel_r, -0.015, 0.015, _BLACK, 24).transformed(axle_T)
            parts[f"wheel_{xname}_{yname}"] = wheel.transformed(translation((x, y, wheel_r)))
    # a lidar puck on the lid, towards the front
    lidar = cylinder(0.045, 0.0, 0.07, _BLACK, 32)
    parts["lidar"] = lidar.transformed(translation((center[0] + 0.25 * size[0], center[1],
                                                    hi[2])))
    return parts


def box_base_mesh(model: RobotModel) -> Mesh:
    """The box-shaped base (one mesh, vertex colours): the body is the bounding box of
    ``model``'s keypoints (default 0.5 x 0.4 x 0.3 m, 4 cm above the floor) with orange sides,
    a dark front face with a yellow stripe, a white rear face and a light-grey lid; four dark
    wheels under it and a lidar puck on the lid's front half. Every keypoint of
    :func:`box_base_keypoints` lies on a body corner or edge."""
    return concatenate(list(box_base_parts(model).values()))


def box_base_model(name: str = BOX_BASE_MODEL) -> RobotModel:
    """The :class:`RobotModel` of the default box base (12 keypoints, :func:`box_base_keypoints`):
    the footprint radius is the body's half diagonal, the height the lidar's top."""
    names, kp = box_base_keypoints()
    kp.setflags(write=False)
    lx, ly, h = BOX_BASE_SIZE_M
    return RobotModel(name, names, kp, float(math.hypot(lx / 2, ly / 2)),
                      BOX_BASE_CLEARANCE_M + h + 0.07)


#: the built-in meshes by robot model name (any other name: the HSR-like robot)
BUILTIN_MESHES: Final = {BOX_BASE_MODEL: box_base_mesh}


def builtin_robot_mesh(model: RobotModel) -> Mesh:
    """The built-in mesh of ``model``: the box base for a model named ``box_base``
    (:data:`BUILTIN_MESHES`), the HSR-like robot (:func:`hsr_like_mesh`) for any other."""
    make = BUILTIN_MESHES.get(model.name)
    return make(model) if make is not None else hsr_like_mesh(model)
