"""Scenes the simulated cameras see (numpy only; drawn by :mod:`.render_gl`).

- :func:`site_scene`: the simulated site as the scenario describes it (floor, walls, the
  obstacles with semantic classes by name, the robot at its simulated pose, optional occluders
  such as people), for closed-loop runs and for training views from the site's own cameras.
- :func:`randomized_view`: a domain-randomized training scene and a random camera looking at the
  robot: random camera pose, height, distance, focal length and lens distortion (or none),
  procedural floor/wall textures, distractor objects, occluders partly covering the robot,
  a coloured key light and a fill light, matte or specular materials, the robot's colours
  worn or faded (:func:`robot_appearances`), all drawn from a :class:`RandomizationConfig`.
- :data:`HELD_OUT_VARIATION`: renderer variations never used in training (other texture
  families, occluder shapes, lens, light), kept disjoint from training by
  :func:`check_disjoint`, for the held-out evaluation.

Instance ids: the robot is :data:`ROBOT_INSTANCE` (one robot per scene here); other instances
(people, distractors) count up from :data:`FIRST_OTHER_INSTANCE`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Final

import numpy as np

from core.camera import CameraModel
from core.geometry import (
    distort_normalized,
    invert_transform,
    lens_fold_radius,
    rotation_z,
    se3_from_planar,
)
from core.site import RobotModel, look_at_T_world_cam
from protocol.errors import SmartedgeError
from simulation.mesh import CLASS_ID, Mesh, Scene, SceneObject
from simulation.robot_mesh import box, cylinder

ROBOT_INSTANCE: Final = 1
FIRST_OTHER_INSTANCE: Final = 100
#: obstacle name fragment → semantic class (first match wins; default "obstacle")
OBSTACLE_CLASSES: Final = (
    ("table", "table"), ("desk", "table"), ("shelf", "shelf"), ("rack", "shelf"),
    ("cabinet", "cabinet"), ("box", "box"), ("chair", "chair"), ("door", "door"),
)


# --------------------------------------------------------------------------------------------
# textured primitives
# --------------------------------------------------------------------------------------------


def textured_quad(corners: np.ndarray, texture: np.ndarray, repeat: tuple[float, float] = (1, 1),
                  color: Sequence[float] = (1.0, 1.0, 1.0)) -> Mesh:
    """A two-triangle quad through ``corners`` (4, 3), counter-clockwise seen from its front,
    with ``texture`` repeated ``repeat`` times along its two edges."""
    c = np.asarray(corners, dtype=np.float64)
    ru, rv = repeat
    uv = np.array([[0, 0], [ru, 0], [ru, rv], [0, rv]], dtype=np.float32)
    normal = np.cross(c[1] - c[0], c[3] - c[0])
    normal = normal / np.linalg.norm(normal)
    return Mesh(c, np.array([[0, 1, 2], [0, 2, 3]]), np.asarray(color, np.float32),
                np.tile(normal, (4, 1)), uv, texture)


def textured_quads(quads: Sequence[np.ndarray], texture: np.ndarray,
                   repeats: Sequence[tuple[float, float]]) -> Mesh:
    """Several quads (each (4, 3), counter-clockwise from the front) sharing one texture, as one
    mesh (one upload, one texture)."""
    parts = [textured_quad(q, texture, r) for q, r in zip(quads, repeats, strict=True)]
    return Mesh(np.vstack([p.vertices for p in parts]),
                np.vstack([p.faces + 4 * i for i, p in enumerate(parts)]),
                np.vstack([p.colors for p in parts]), np.vstack([p.normals for p in parts]),
                np.vstack([p.uv for p in parts]), texture)


#: procedural texture families (:func:`procedural_texture`); the site's own textures and
#: training use the first group, the held-out variations (:data:`HELD_OUT_VARIATION`) others
TEXTURE_KINDS: Final = ("checker", "stripes", "blotches", "tiles", "noise", "planks", "terrazzo")
#: the families the site's own floor and walls are drawn from
SITE_TEXTURE_KINDS: Final = ("checker", "stripes", "blotches", "tiles")


def _value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """(size, size) smooth noise in [0, 1]: a random ``cells`` x ``cells`` grid, bilinearly
    interpolated."""
    grid = rng.uniform(0, 1, (cells + 1, cells + 1))
    t = np.linspace(0, cells, size, endpoint=False)
    i = t.astype(np.int64)
    f = t - i
    rows = grid[i] * (1 - f)[:, None] + grid[i + 1] * f[:, None]  # (size, cells + 1)
    return rows[:, i] * (1 - f)[None, :] + rows[:, i + 1] * f[None, :]


def procedural_texture(rng: np.random.Generator, size: int = 128,
                       kinds: Sequence[str] = SITE_TEXTURE_KINDS) -> np.ndarray:
    """A random (size, size, 3) uint8 texture of one of ``kinds`` (:data:`TEXTURE_KINDS`):
    checker, stripes, blotchy noise, tiles with grout, smooth multi-scale noise (concrete,
    carpet), wooden planks, terrazzo (stone chips in a binder)."""
    kind = kinds[int(rng.integers(len(kinds)))]
    c0, c1 = rng.uniform(0.1, 0.95, 3), rng.uniform(0.1, 0.95, 3)
    y, x = np.mgrid[0:size, 0:size] / size
    if kind == "checker":
        n = int(rng.integers(2, 9))
        m = ((np.floor(x * n) + np.floor(y * n)) % 2)[..., None]
    elif kind == "stripes":
        n = int(rng.integers(3, 16))
        a = rng.uniform(0, np.pi)
        m = (0.5 + 0.5 * np.sin(2 * np.pi * n * (x * np.cos(a) + y * np.sin(a))))[..., None]
    elif kind == "blotches":
        coarse = rng.uniform(0, 1, (int(rng.integers(3, 12)),) * 2)
        idx = (np.arange(size) * coarse.shape[0] // size)
        m = coarse[np.ix_(idx, idx)][..., None]
    elif kind == "tiles":
        n = int(rng.integers(2, 7))
        grout = ((x * n) % 1 < 0.06) | ((y * n) % 1 < 0.06)
        m = grout[..., None].astype(np.float64)
    elif kind == "noise":
        m = sum(w * _value_noise(rng, size, c) for w, c in ((0.55, 4), (0.3, 16), (0.15, 64)))
        m = np.clip((m - 0.5) * rng.uniform(1.0, 3.0) + 0.5, 0, 1)[..., None]
    elif kind == "planks":
        n = int(rng.integers(3, 9))  # planks across the tile
        plank = np.floor(y * n).astype(np.int64)
        shade = rng.uniform(0.0, 1.0, n)[plank]
        grain = 0.5 + 0.5 * np.sin(2 * np.pi * (x * rng.uniform(1, 4) + 6 * shade
                                                 + 0.15 * _value_noise(rng, size, 8)) * 5)
        seam = ((y * n) % 1 < 0.04) | (((x + shade) % 1) < 0.01)
        m = np.where(seam, 1.0, 0.6 * shade + 0.25 * grain)[..., None]
        c0 = np.array([0.55, 0.38, 0.22]) * rng.uniform(0.6, 1.4) * rng.uniform(0.9, 1.1, 3)
        c1 = c0 * 0.45
    else:  # terrazzo
        chips = int(rng.integers(60, 220))
        centres = rng.uniform(0, 1, (chips, 2))
        radius = rng.uniform(0.006, 0.03, chips)
        palette = rng.uniform(0.05, 0.95, (3, 3))
        colour = palette[rng.integers(3, size=chips)]
        img = np.tile(c0, (size, size, 1))
        for (cx, cy), r, col in zip(centres, radius, colour, strict=True):
            lo_x, hi_x = max(0, int((cx - r) * size)), min(size, int((cx + r) * size) + 1)
            lo_y, hi_y = max(0, int((cy - r) * size)), min(size, int((cy + r) * size) + 1)
            inside = ((x[lo_y:hi_y, lo_x:hi_x] - cx) ** 2
                      + (y[lo_y:hi_y, lo_x:hi_x] - cy) ** 2) < r * r
            img[lo_y:hi_y, lo_x:hi_x][inside] = col
        img *= rng.uniform(0.85, 1.0, (size, size, 1))
        return np.clip(img * 255, 0, 255).astype(np.uint8)
    img = c0 * (1 - m) + c1 * m
    img *= rng.uniform(0.85, 1.0, (size, size, 1))  # a little grain
    return np.clip(img * 255, 0, 255).astype(np.uint8)


def person_mesh(height_m: float, color: Sequence[float]) -> Mesh:
    """A person-shaped occluder (legs+torso column and a head), standing on z = 0."""
    from simulation.mesh import concatenate

    body = _cylinder(0.18, 0.82 * height_m, color)
    head = box((0.2, 0.2, 0.22), color=(0.85, 0.7, 0.6)).transformed(
        _translation(0, 0, 0.82 * height_m + 0.11))
    return concatenate([body, head])


def _walls(corners: Sequence[tuple[float, float]], height_m: float, texture: np.ndarray,
           tile_m: float) -> Mesh:
    """Walls along a closed polygon of floor ``corners`` (counter-clockwise seen from above, so
    the walls face inwards), one texture tile every ``tile_m``."""
    quads, repeats = [], []
    for k in range(len(corners)):
        (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % len(corners)]
        quads.append(np.array([[x0, y0, 0], [x1, y1, 0], [x1, y1, height_m],
                               [x0, y0, height_m]]))
        repeats.append((math.hypot(x1 - x0, y1 - y0) / tile_m, height_m / tile_m))
    return textured_quads(quads, texture, repeats)


def _cylinder(radius_m: float, height_m: float, color: Sequence[float]) -> Mesh:
    return cylinder(radius_m, 0.0, height_m, color=color, segments=16)


def _translation(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def _planar_T(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    T = se3_from_planar(x, y, yaw)
    T[2, 3] = z
    return T


# --------------------------------------------------------------------------------------------
# the simulated site
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class SiteGeometry:
    """The static part of the site scene (built once, reused every frame)."""

    objects: tuple[SceneObject, ...]


def obstacle_class(name: str) -> int:
    lowered = name.lower()
    for fragment, cls in OBSTACLE_CLASSES:
        if fragment in lowered:
            return CLASS_ID[cls]
    return CLASS_ID["obstacle"]


def site_geometry(scenario: object, seed: int = 0) -> SiteGeometry:
    """Floor, walls and obstacles of a :class:`simulation.scenario.Scenario` (textures from
    ``seed``, so a site looks the same every time)."""
    rng = np.random.default_rng(seed)
    lo = np.asarray(scenario.room_min_xy_m, dtype=np.float64)  # type: ignore[attr-defined]
    hi = np.asarray(scenario.room_max_xy_m, dtype=np.float64)  # type: ignore[attr-defined]
    h = float(scenario.room_height_m)  # type: ignore[attr-defined]
    floor_tex = procedural_texture(rng)
    wall_tex = procedural_texture(rng)
    objs: list[SceneObject] = []
    floor = textured_quad(np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0],
                                    [lo[0], hi[1], 0]]), floor_tex,
                          ((hi[0] - lo[0]) / 2, (hi[1] - lo[1]) / 2))
    objs.append(SceneObject(floor, np.eye(4), 0, CLASS_ID["floor"]))
    corners = [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])]
    objs.append(SceneObject(_walls(corners, h, wall_tex, 2.0), np.eye(4), 0, CLASS_ID["wall"]))
    for obstacle in scenario.obstacles:  # type: ignore[attr-defined]
        size = np.asarray(obstacle.size_m, dtype=np.float64)
        color = rng.uniform(0.25, 0.85, 3)
        mesh = box(size, color=color)
        cx, cy = (float(v) for v in obstacle.center_xy_m)
        T = _planar_T(cx, cy, float(obstacle.yaw_rad), float(obstacle.z_min_m) + size[2] / 2)
        objs.append(SceneObject(mesh, T, 0, obstacle_class(obstacle.name)))
    return SiteGeometry(tuple(objs))


def surface_samples(objects: Sequence[SceneObject], spacing_m: float, seed: int = 0,
                    classes: Sequence[int] | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on the objects' triangles, about one per ``spacing_m``² of surface (area-weighted
    uniform sampling): (N, 3) world metres, (N, 3) unit face normals, (N,) class ids. Only
    objects whose class is in ``classes`` (default: all). The ground truth of the semantic map
    (every static surface with its class) and its prior model (floor and walls only: the empty
    room) come from here."""
    rng = np.random.default_rng(seed)
    out_p, out_n, out_c = [], [], []
    for obj in objects:
        if classes is not None and obj.class_id not in classes:
            continue
        T = obj.T_world_object
        v = obj.mesh.vertices.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        tri = v[obj.mesh.faces.astype(np.int64)]  # (M, 3, 3)
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area2 = np.linalg.norm(cross, axis=1)
        ok = area2 > 1e-12
        tri, cross, area2 = tri[ok], cross[ok], area2[ok]
        expected = 0.5 * area2 / spacing_m**2
        counts = rng.poisson(expected)
        if counts.sum() == 0:
            continue
        which = np.repeat(np.arange(len(tri)), counts)
        a, b = rng.random((2, len(which)))
        flip = a + b > 1.0
        a[flip], b[flip] = 1.0 - a[flip], 1.0 - b[flip]
        t = tri[which]
        out_p.append(t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0]))
        out_n.append(cross[which] / area2[which, None])
        out_c.append(np.full(len(which), obj.class_id, dtype=np.int64))
    if not out_p:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.concatenate(out_p), np.concatenate(out_n), np.concatenate(out_c)


def site_scene(geometry: SiteGeometry, robot_mesh: Mesh, robot_pose: Sequence[float],
               occluders: Sequence[SceneObject] = (), *,
               light_dir_world: tuple[float, float, float] = (0.3, 0.2, 1.0)) -> Scene:
    """The site with the robot at ``robot_pose`` (x, y, theta in the world frame)."""
    x, y, theta = (float(v) for v in robot_pose)
    robot = SceneObject(robot_mesh, se3_from_planar(x, y, theta), ROBOT_INSTANCE,
                        CLASS_ID["robot"])
    # the site's own objects are the same instances every frame: renderers keep their render
    # per camera and draw the robot and occluders on top
    return Scene((*geometry.objects, robot, *occluders), light_dir_world=light_dir_world,
                 static_objects=len(geometry.objects))


def robot_keypoints_world(model: RobotModel, robot_pose: Sequence[float]) -> np.ndarray:
    """(M, 3) keypoints of ``model`` at ``robot_pose`` (x, y, theta) in the world frame."""
    x, y, theta = (float(v) for v in robot_pose)
    return np.asarray(model.keypoints_base_m) @ rotation_z(theta).T + [x, y, 0.0]


# --------------------------------------------------------------------------------------------
# domain-randomized training views
# --------------------------------------------------------------------------------------------


class RandomizationError(SmartedgeError, ValueError):
    """Randomization settings that contradict each other (bad ranges, held-out settings that
    overlap the training ones)."""


@dataclasses.dataclass(frozen=True)
class RandomizationConfig:
    """Ranges of the domain randomization (metres, degrees; ``(lo, hi)`` drawn uniformly).

    Geometry: camera ``distance_m`` from the robot (on the floor) and ``camera_height_m``,
    horizontal field of view ``hfov_deg``, radial distortion ``k1_range`` (barrel < 0) of which
    ``no_distortion_probability`` of the lenses have none, ``look_jitter_m`` of the aim.

    Scene: ``textures`` (:data:`TEXTURE_KINDS`) of floor and walls, ``distractors`` objects,
    an occluder between camera and robot with ``occluder_probability``, one of
    ``occluder_shapes`` (``person``, ``box``, ``panel``: a partition or screen, ``pole``).

    Light and materials (the renderer's shading, :class:`simulation.mesh.Scene`): ``ambient``
    share; the key light's colour temperature ``light_temperature_k`` with a green (> 0) /
    magenta (< 0) ``light_tint_green`` and ``light_intensity``; a coloured fill light with
    ``fill_light_probability`` at ``fill_intensity``; a specular highlight with
    ``specular_probability`` of strength ``specular`` and exponent ``shininess`` (else matte).

    The robot's appearance: ``robot_appearances`` colour variants of its mesh (per-channel
    ``robot_color_jitter``, ``robot_brightness``; variant 0 is the mesh as given; the built-in
    HSR-like mesh also, with ``robot_arm_poses``, its arm raised by ``robot_arm_raise_deg`` at
    the shoulder and bent by ``robot_elbow_deg`` at the elbow, :func:`hsr_arm_poses`), dirt and
    wear
    patches with ``dirt_probability``; a contact and cast shadow on the floor with
    ``shadow_probability`` and ``shadow_strength`` (image space, :mod:`simulation.dataset`).

    The camera (image space, :func:`simulation.image_effects.camera_effects`): ``exposure_ev``,
    per-channel ``white_balance`` gain, ``gamma``, ``brightness_offset`` (8-bit levels),
    ``saturation``, ``vignetting`` (corner
    darkening share) with ``vignetting_probability``, defocus (disk of ``defocus_px`` radius)
    and motion blur (a line of ``motion_blur_px``) with their probabilities, Gaussian sensor
    noise ``noise_sigma`` (8-bit levels) and JPEG at ``jpeg_quality`` with ``jpeg_probability``.
    """

    distance_m: tuple[float, float] = (1.2, 9.0)
    camera_height_m: tuple[float, float] = (0.4, 3.6)
    hfov_deg: tuple[float, float] = (55.0, 100.0)
    k1_range: tuple[float, float] = (-0.25, 0.05)
    no_distortion_probability: float = 0.2
    look_jitter_m: float = 0.6
    distractors: tuple[int, int] = (2, 10)
    occluder_probability: float = 0.5
    occluder_shapes: tuple[str, ...] = ("person", "box")
    room_half_size_m: float = 12.0
    textures: tuple[str, ...] = ("checker", "stripes", "blotches", "tiles", "noise")
    #: distinct floor/wall looks drawn per generator (re-used across samples, so the renderer
    #: uploads their textures once; camera, light, objects and image noise change every sample)
    environments: int = 48
    ambient: tuple[float, float] = (0.25, 0.6)
    light_temperature_k: tuple[float, float] = (2700.0, 6500.0)
    light_tint_green: tuple[float, float] = (-0.04, 0.04)
    light_intensity: tuple[float, float] = (0.8, 1.2)
    fill_light_probability: float = 0.5
    fill_intensity: tuple[float, float] = (0.1, 0.5)
    specular_probability: float = 0.5
    specular: tuple[float, float] = (0.05, 0.5)
    shininess: tuple[float, float] = (4.0, 48.0)
    robot_appearances: int = 8
    robot_color_jitter: float = 0.12
    robot_brightness: tuple[float, float] = (0.75, 1.15)
    #: the built-in HSR-like robot's arm in other poses (the shipped networks are trained with
    #: it since 2026-11-27)
    robot_arm_poses: bool = True
    robot_arm_raise_deg: tuple[float, float] = (0.0, 80.0)
    robot_elbow_deg: tuple[float, float] = (-20.0, 60.0)
    dirt_probability: float = 0.3
    shadow_probability: float = 0.7
    shadow_strength: tuple[float, float] = (0.15, 0.55)
    exposure_ev: tuple[float, float] = (-1.0, 0.6)
    white_balance: tuple[float, float] = (0.85, 1.15)
    gamma: tuple[float, float] = (0.8, 1.25)
    brightness_offset: tuple[float, float] = (-8.0, 8.0)
    saturation: tuple[float, float] = (0.5, 1.5)
    vignetting_probability: float = 0.6
    vignetting: tuple[float, float] = (0.0, 0.4)
    defocus_probability: float = 0.2
    defocus_px: tuple[float, float] = (1.0, 2.5)
    motion_blur_probability: float = 0.15
    motion_blur_px: tuple[float, float] = (3.0, 9.0)
    noise_sigma: tuple[float, float] = (0.0, 8.0)
    jpeg_probability: float = 0.6
    jpeg_quality: tuple[int, int] = (40, 95)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name.endswith("_probability") and not 0.0 <= value <= 1.0:
                raise RandomizationError(f"randomization: {f.name} {value} not in [0, 1]")
            if isinstance(value, tuple) and len(value) == 2 and all(
                    isinstance(v, (int, float)) for v in value) and value[0] > value[1]:
                raise RandomizationError(f"randomization: {f.name} {value}: lo > hi")
        for name in (*self.textures, *self.occluder_shapes):
            if name not in TEXTURE_KINDS and name not in OCCLUDER_SHAPES:
                raise RandomizationError(f"randomization: unknown texture or occluder {name!r}")
        if not self.textures:
            raise RandomizationError("randomization: textures is empty")


#: occluder shapes :func:`randomized_view` can place between the camera and the robot
OCCLUDER_SHAPES: Final = ("person", "box", "panel", "pole")

#: Held-out renderer variations: settings NEVER used in training, for
#: ``smartedge evaluate keypoints --held-out-variations``. Disjoint from the training ranges
#: (:data:`HELD_OUT_DISJOINT_FIELDS`, checked by :func:`check_disjoint`): floor and wall
#: texture families (planks, terrazzo), occluder shapes (partitions, poles), a lens with
#: pincushion distortion, darker ambient light, cold and green-tinted (fluorescent) key light,
#: stronger vignetting. Shared with training: camera heights 1.8-3.2 m, robot 1.5-8 m away,
#: fields of view 60-90 deg, exposure, noise, blur and JPEG.
HELD_OUT_VARIATION: Final = RandomizationConfig(
    distance_m=(1.5, 8.0), camera_height_m=(1.8, 3.2), hfov_deg=(60.0, 90.0),
    k1_range=(0.06, 0.12), no_distortion_probability=0.0, look_jitter_m=0.4,
    occluder_shapes=("panel", "pole"), textures=("planks", "terrazzo"), environments=16,
    ambient=(0.12, 0.24), light_temperature_k=(6800.0, 9500.0),
    light_tint_green=(0.06, 0.12), vignetting_probability=1.0, vignetting=(0.45, 0.6),
)

#: the :class:`RandomizationConfig` fields whose held-out values must not overlap training's
HELD_OUT_DISJOINT_FIELDS: Final = ("k1_range", "occluder_shapes", "textures", "ambient",
                                   "light_temperature_k", "light_tint_green", "vignetting")


def check_disjoint(training: RandomizationConfig,
                   held_out: RandomizationConfig = HELD_OUT_VARIATION,
                   fields: Sequence[str] = HELD_OUT_DISJOINT_FIELDS) -> None:
    """Raise :class:`RandomizationError` naming every field of ``fields`` where the
    ``held_out`` settings overlap the ``training`` ones: numeric ranges must not intersect
    (closed intervals), name sets (textures, occluder shapes) must not share a name. An
    undistorted lens counts as k1 = 0 of ``k1_range`` when training draws any."""
    problems = []
    for name in fields:
        a, b = getattr(training, name), getattr(held_out, name)
        if name == "k1_range":
            a = (min(a[0], 0.0), max(a[1], 0.0)) if training.no_distortion_probability else a
            b = (min(b[0], 0.0), max(b[1], 0.0)) if held_out.no_distortion_probability else b
        if all(isinstance(v, str) for v in (*a, *b)):
            common = sorted(set(a) & set(b))
            if common:
                problems.append(f"{name}: training and held-out share {common}")
        elif float(a[0]) <= float(b[1]) and float(b[0]) <= float(a[1]):
            problems.append(f"{name}: training {tuple(a)} overlaps held-out {tuple(b)}")
    if problems:
        raise RandomizationError("held-out renderer variations overlap the training "
                                 "randomization: " + "; ".join(problems))


def light_rgb(temperature_k: float, tint_green: float = 0.0) -> np.ndarray:
    """(3,) RGB of a light at ``temperature_k`` kelvin (a fit of the black-body colour,
    1000-40000 K), green (> 0) or magenta (< 0) shifted by ``tint_green``, mean 1."""
    t = float(np.clip(temperature_k, 1000.0, 40000.0)) / 100.0
    r = 1.0 if t <= 66 else 1.2929 * (t - 60) ** -0.1332
    g = (0.3901 * math.log(t) - 0.6318) if t <= 66 else 1.1299 * (t - 60) ** -0.0755
    b = 1.0 if t >= 66 else (0.0 if t <= 19 else 0.5432 * math.log(t - 10) - 1.1963)
    rgb = np.clip([r, g, b], 0.0, 1.0) * np.array([1 - tint_green / 2, 1 + tint_green,
                                                    1 - tint_green / 2])
    return rgb / rgb.mean()


def robot_appearances(robot_mesh: Mesh, seed: int, config: RandomizationConfig | None = None,
                      shapes: Sequence[Mesh] = ()) -> tuple[Mesh, ...]:
    """``config.robot_appearances`` colour variants of ``robot_mesh`` (worn, faded or darker
    paint: a per-channel gain and a brightness per variant, a little per-vertex variation),
    deterministic per ``seed``; the first is ``robot_mesh`` itself. ``shapes``: other poses of
    the same robot (:func:`hsr_arm_poses`), used in turn by the other variants."""
    cfg = config or RandomizationConfig()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 611953]))
    out = [robot_mesh]
    for k in range(max(0, cfg.robot_appearances - 1)):
        base = shapes[k % len(shapes)] if shapes else robot_mesh
        colors = np.asarray(base.colors, np.float64)
        gain = rng.uniform(*cfg.robot_brightness) * (
            1.0 + rng.uniform(-cfg.robot_color_jitter, cfg.robot_color_jitter, 3))
        wear = 1.0 + rng.normal(0.0, 0.5 * cfg.robot_color_jitter, (len(colors), 1))
        c = np.clip(colors * gain * wear, 0.0, 1.0).astype(np.float32)
        out.append(dataclasses.replace(base, colors=c))
    return tuple(out)


#: the parts of the HSR-like mesh that move with its arm (:func:`hsr_arm_poses`)
_ARM_PARTS: Final = ("upper_arm", "forearm", "hand", "finger_left", "finger_right")
_FOREARM_PARTS: Final = ("forearm", "hand", "finger_left", "finger_right")


def _rotation_y_about(angle_rad: float, pivot: np.ndarray) -> np.ndarray:
    """(4, 4) rotation by ``angle_rad`` about the y axis through ``pivot`` (3,)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = pivot - T[:3, :3] @ pivot
    return T


def hsr_arm_poses(model: RobotModel, seed: int, count: int,
                  config: RandomizationConfig | None = None) -> tuple[Mesh, ...]:
    """``count`` meshes of the built-in HSR-like robot (:func:`simulation.robot_mesh.
    hsr_like_parts`) with the arm in other poses: raised forward at the shoulder by
    ``config.robot_arm_raise_deg`` and bent at the elbow by ``config.robot_elbow_deg``
    (poses that would put the hand into the base are drawn again). The base, where the
    keypoints are, does not move. Deterministic per ``seed``."""
    from simulation.mesh import concatenate
    from simulation.robot_mesh import hsr_like_parts

    cfg = config or RandomizationConfig()
    parts = hsr_like_parts(model)
    if not all(name in parts for name in (*_ARM_PARTS, "shoulder", "base")):
        return ()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7331]))
    # the upper arm is a vertical capsule from the shoulder joint down to the elbow joint
    lo, hi = (np.asarray(b, np.float64) for b in parts["upper_arm"].bounds())
    radius = 0.5 * float(hi[0] - lo[0])
    shoulder = np.array([0.5 * (lo[0] + hi[0]), 0.0, hi[2] - radius])
    elbow_rest = np.array([0.5 * (lo[0] + hi[0]), 0.0, lo[2] + radius, 1.0])
    z_base_top = float(parts["base"].bounds()[1][2])
    out: list[Mesh] = []
    for _ in range(max(0, count)):
        moved: dict[str, Mesh] = {}
        for _try in range(20):
            raise_rad = math.radians(float(rng.uniform(*cfg.robot_arm_raise_deg)))
            bend_rad = math.radians(float(rng.uniform(*cfg.robot_elbow_deg)))
            T_shoulder = _rotation_y_about(-raise_rad, shoulder)  # elbow swings forward (+x)
            elbow = (T_shoulder @ elbow_rest)[:3]
            T_elbow = _rotation_y_about(-bend_rad, elbow) @ T_shoulder
            moved = {name: parts[name].transformed(T_elbow if name in _FOREARM_PARTS
                                                   else T_shoulder) for name in _ARM_PARTS}
            if min(float(m.bounds()[0][2]) for m in moved.values()) > z_base_top + 0.01:
                break
        out.append(concatenate([moved.get(name, mesh) for name, mesh in parts.items()]))
    return tuple(out)


@dataclasses.dataclass(frozen=True, eq=False)
class Environment:
    """A textured floor and walls for randomized scenes."""

    floor: SceneObject
    walls: SceneObject


def random_environments(seed: int, config: RandomizationConfig | None = None,
                        ) -> tuple[Environment, ...]:
    """``config.environments`` floor/wall looks, deterministic per ``seed``."""
    cfg = config or RandomizationConfig()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 104729]))
    half = cfg.room_half_size_m
    out = []
    for _ in range(max(1, cfg.environments)):
        floor = textured_quad(np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0],
                                        [-half, half, 0]]),
                              procedural_texture(rng, kinds=cfg.textures),
                              (half * rng.uniform(0.3, 1.5),) * 2)
        corners = [(-half, -half), (half, -half), (half, half), (-half, half)]
        walls = _walls(corners, float(rng.uniform(2.5, 4.5)),
                       procedural_texture(rng, kinds=cfg.textures), float(rng.uniform(1.0, 6.0)))
        out.append(Environment(SceneObject(floor, np.eye(4), 0, CLASS_ID["floor"]),
                               SceneObject(walls, np.eye(4), 0, CLASS_ID["wall"])))
    return tuple(out)


def _lens_covers(dist: np.ndarray, radius: float) -> bool:
    """The lens images every distorted radius up to ``radius`` from a real direction: its
    radial polynomial is still growing when it reaches it (it does not fold back before)."""
    fold = lens_fold_radius(dist)
    if not math.isfinite(fold):
        return True
    d = np.asarray(dist, np.float64).copy()
    d[2:4] = 0.0
    reached = float(distort_normalized(np.array([[fold, 0.0]]), d)[0, 0])
    return reached > radius


def look_at_camera(camera_id: str, position: np.ndarray, target: np.ndarray, width: int,
                   height: int, hfov_deg: float, dist: np.ndarray | None = None) -> CameraModel:
    """A pinhole camera at ``position`` looking at ``target`` (world frame, z up, no roll)."""
    T_world_cam = look_at_T_world_cam(position, target)
    f = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return CameraModel(camera_id, width, height, K,
                       np.zeros(5) if dist is None else np.asarray(dist, np.float64),
                       invert_transform(T_world_cam))


def randomized_view(rng: np.random.Generator, robot_mesh: Mesh, model: RobotModel, width: int,
                    height: int, config: RandomizationConfig | None = None,
                    environments: Sequence[Environment] | None = None,
                    appearances: Sequence[Mesh] | None = None,
                    ) -> tuple[Scene, CameraModel, np.ndarray]:
    """A random training scene with the robot near the origin; returns (scene, camera, robot
    pose (3,) x, y, theta). ``environments``: the floor/wall looks to draw from (default: a
    fresh set from ``rng``, slower: textures are uploaded again); ``appearances``: colour
    variants of the robot's mesh to draw one from (:func:`robot_appearances`; default: the
    mesh as given)."""
    cfg = config or RandomizationConfig()
    pose = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-np.pi, np.pi)])
    half = cfg.room_half_size_m
    if not environments:
        environments = random_environments(
            int(rng.integers(2**31)), dataclasses.replace(cfg, environments=1))
    env = environments[int(rng.integers(len(environments)))]
    objs: list[SceneObject] = [env.floor, env.walls]
    # camera: somewhere around the robot, looking at it (with jitter so it is not centred)
    dist = float(rng.uniform(*cfg.distance_m))
    az = float(rng.uniform(-np.pi, np.pi))
    cam_pos = np.array([pose[0] + dist * math.cos(az), pose[1] + dist * math.sin(az),
                        rng.uniform(*cfg.camera_height_m)])
    target = np.array([pose[0], pose[1], 0.5 * model.height_m]) + rng.normal(
        0, cfg.look_jitter_m * min(1.0, dist / 4), 3) * [1, 1, 0.4]
    hfov_deg = float(rng.uniform(*cfg.hfov_deg))
    k1 = float(rng.uniform(*cfg.k1_range))
    distortion = np.array([k1, rng.uniform(-0.1, 0.1) * abs(k1), rng.normal(0, 5e-4),
                           rng.normal(0, 5e-4), 0.0])
    if rng.uniform() < cfg.no_distortion_probability:
        distortion[:] = 0.0  # a rectified image or a lens without distortion
    # a physical lens: its radial polynomial must keep growing over the whole image (with a
    # margin), else a wide field of view with strong barrel distortion folds back
    f_norm = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    corner_radius = math.hypot(0.5 * width, 0.5 * height) / f_norm  # distorted, normalized
    while not _lens_covers(distortion, 1.15 * corner_radius):
        distortion[:2] *= 0.5
    camera = look_at_camera("random", cam_pos, target, width, height, hfov_deg, distortion)
    instance = FIRST_OTHER_INSTANCE
    # distractors: random boxes and cylinders away from the robot and the camera
    for _ in range(int(rng.integers(cfg.distractors[0], cfg.distractors[1] + 1))):
        p = rng.uniform(-half + 1, half - 1, 2)
        if np.hypot(*(p - pose[:2])) < 0.8 or np.hypot(*(p - cam_pos[:2])) < 0.8:
            continue
        color = rng.uniform(0.05, 0.95, 3)
        if rng.uniform() < 0.5:
            mesh = box(rng.uniform([0.2, 0.2, 0.2], [1.5, 1.5, 2.0]), color=color)
            T = _planar_T(p[0], p[1], float(rng.uniform(-np.pi, np.pi)), 0.0)
            T[2, 3] = 0.5 * float(mesh.bounds()[1][2] - mesh.bounds()[0][2])
        else:
            mesh = _cylinder(float(rng.uniform(0.1, 0.5)), float(rng.uniform(0.3, 2.0)),
                                 color)
            T = _planar_T(p[0], p[1], 0.0)
        objs.append(SceneObject(mesh, T, instance, CLASS_ID["distractor"]))
        instance += 1
    # an occluder between camera and robot, partly covering it
    if rng.uniform() < cfg.occluder_probability:
        a = float(rng.uniform(0.25, 0.75))
        p = (1 - a) * pose[:2] + a * cam_pos[:2] + rng.normal(0, 0.25, 2)
        if np.hypot(*(p - pose[:2])) > model.footprint_radius_m + 0.3:
            shape = cfg.occluder_shapes[int(rng.integers(len(cfg.occluder_shapes)))]
            objs.append(_occluder(rng, shape, p, cam_pos, instance))
    robot = robot_mesh if not appearances else appearances[int(rng.integers(len(appearances)))]
    objs.append(SceneObject(robot, se3_from_planar(*pose), ROBOT_INSTANCE, CLASS_ID["robot"]))
    light = rng.normal(0, 1, 3)
    light[2] = abs(light[2]) + 0.5
    ambient = float(rng.uniform(*cfg.ambient))
    key_rgb = light_rgb(rng.uniform(*cfg.light_temperature_k),
                        rng.uniform(*cfg.light_tint_green)) * rng.uniform(*cfg.light_intensity)
    fill_dir = rng.normal(0, 1, 3)
    fill_dir[2] = abs(fill_dir[2]) + 0.2
    fill_rgb = np.zeros(3)
    if rng.uniform() < cfg.fill_light_probability:
        # a second lamp or a coloured wall's bounce: any hue, weak
        fill_rgb = rng.uniform(0.3, 1.0, 3) * rng.uniform(*cfg.fill_intensity)
    specular, shininess = 0.0, 16.0
    if rng.uniform() < cfg.specular_probability:
        specular = float(rng.uniform(*cfg.specular))
        shininess = float(rng.uniform(*cfg.shininess))
    scene = Scene(tuple(objs), light_dir_world=tuple(light / np.linalg.norm(light)),
                  ambient=ambient,
                  background_rgb=tuple(float(v) for v in rng.uniform(0.0, 1.0, 3)),
                  light_rgb=tuple(float(v) for v in key_rgb),
                  fill_dir_world=tuple(float(v) for v in fill_dir / np.linalg.norm(fill_dir)),
                  fill_rgb=tuple(float(v) for v in fill_rgb), specular=specular,
                  shininess=shininess)
    return scene, camera, pose


def _occluder(rng: np.random.Generator, shape: str, p: np.ndarray, cam_pos: np.ndarray,
              instance: int) -> SceneObject:
    """An occluder of ``shape`` (:data:`OCCLUDER_SHAPES`) standing at ``p`` (2,), a partition
    or screen turned roughly towards the camera at ``cam_pos``."""
    color = rng.uniform(0.1, 0.9, 3)
    if shape == "person":
        return SceneObject(person_mesh(float(rng.uniform(1.5, 1.9)), color),
                           _planar_T(p[0], p[1], 0.0), instance, CLASS_ID["person"])
    if shape == "pole":
        mesh = _cylinder(float(rng.uniform(0.04, 0.15)), float(rng.uniform(1.0, 2.5)), color)
        return SceneObject(mesh, _planar_T(p[0], p[1], 0.0), instance, CLASS_ID["distractor"])
    if shape == "panel":
        size = (float(rng.uniform(0.03, 0.08)), float(rng.uniform(0.5, 1.4)),
                float(rng.uniform(0.6, 1.6)))
        toward = math.atan2(cam_pos[1] - p[1], cam_pos[0] - p[0]) + rng.uniform(-0.6, 0.6)
        mesh = box(size, color=color)
        T = _planar_T(p[0], p[1], toward, 0.5 * size[2] + float(rng.uniform(0.0, 0.4)))
        return SceneObject(mesh, T, instance, CLASS_ID["distractor"])
    mesh = box(rng.uniform([0.3, 0.3, 0.3], [0.9, 0.9, 1.2]), color=color)
    T = _planar_T(p[0], p[1], float(rng.uniform(-np.pi, np.pi)))
    T[2, 3] = 0.5 * float(mesh.bounds()[1][2] - mesh.bounds()[0][2])
    return SceneObject(mesh, T, instance, CLASS_ID["box"])


def robot_distance_m(camera: CameraModel, robot_pose: Sequence[float]) -> float:
    """Distance on the floor from the camera to the robot's centre, metres (what the held-out
    evaluation bins recall by)."""
    c = camera.position_world
    return float(math.hypot(float(c[0]) - float(robot_pose[0]),
                            float(c[1]) - float(robot_pose[1])))


def shadow_polygon_world(robot_pose: Sequence[float], model: RobotModel,
                         light_dir_world: Sequence[float], segments: int = 16) -> np.ndarray:
    """(2 * segments, 3) floor points (z = 0) around the robot's footprint and its outline cast
    along the light (a cylinder of the footprint radius and the robot's height): the convex
    hull of these is the floor its shadow covers (an approximation: the robot's real outline
    is not traced)."""
    x, y = float(robot_pose[0]), float(robot_pose[1])
    light = np.asarray(light_dir_world, np.float64)
    lz = max(float(light[2]), 0.25)  # a low light would cast the shadow across the room
    shift = -light[:2] / lz * model.height_m * 0.85
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = model.footprint_radius_m * np.stack([np.cos(a), np.sin(a)], axis=1)
    pts = np.vstack([ring, 0.8 * ring + shift]) + np.array([x, y])
    return np.hstack([pts, np.zeros((len(pts), 1))])
