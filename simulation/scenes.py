"""Scenes the simulated cameras see (numpy only; drawn by :mod:`.render_gl`).

- :func:`site_scene`: the simulated site as the scenario describes it (floor, walls, the
  obstacles with semantic classes by name, the robot at its simulated pose, optional occluders
  such as people), for closed-loop runs and for training views from the site's own cameras.
- :func:`randomized_view`: a domain-randomized training scene and a random camera looking at the
  robot: random camera pose, height, distance, focal length and lens distortion, procedural
  floor/wall textures, distractor objects, occluders partly covering the robot, random light.

Instance ids: the robot is :data:`ROBOT_INSTANCE` (one robot per scene here); other instances
(people, distractors) count up from :data:`FIRST_OTHER_INSTANCE`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Final

import numpy as np

from protocol.camera import CameraModel
from protocol.geometry import (
    distort_normalized,
    invert_transform,
    lens_fold_radius,
    rotation_z,
    se3_from_planar,
)
from protocol.site import RobotModel, look_at_T_world_cam
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


def procedural_texture(rng: np.random.Generator, size: int = 128) -> np.ndarray:
    """A random (size, size, 3) uint8 texture: checker, stripes, blotchy noise or tiles."""
    kind = int(rng.integers(4))
    c0, c1 = rng.uniform(0.1, 0.95, 3), rng.uniform(0.1, 0.95, 3)
    y, x = np.mgrid[0:size, 0:size] / size
    if kind == 0:
        n = int(rng.integers(2, 9))
        m = ((np.floor(x * n) + np.floor(y * n)) % 2)[..., None]
    elif kind == 1:
        n = int(rng.integers(3, 16))
        a = rng.uniform(0, np.pi)
        m = (0.5 + 0.5 * np.sin(2 * np.pi * n * (x * np.cos(a) + y * np.sin(a))))[..., None]
    elif kind == 2:
        coarse = rng.uniform(0, 1, (int(rng.integers(3, 12)),) * 2)
        idx = (np.arange(size) * coarse.shape[0] // size)
        m = coarse[np.ix_(idx, idx)][..., None]
    else:
        n = int(rng.integers(2, 7))
        grout = ((x * n) % 1 < 0.06) | ((y * n) % 1 < 0.06)
        m = grout[..., None].astype(np.float64)
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


@dataclasses.dataclass(frozen=True)
class RandomizationConfig:
    """Ranges of the domain randomization (metres, degrees)."""

    distance_m: tuple[float, float] = (1.2, 9.0)
    camera_height_m: tuple[float, float] = (0.4, 3.6)
    hfov_deg: tuple[float, float] = (55.0, 100.0)
    max_k1: float = 0.25
    look_jitter_m: float = 0.6
    distractors: tuple[int, int] = (2, 10)
    occluder_probability: float = 0.5
    room_half_size_m: float = 12.0
    #: distinct floor/wall looks drawn per generator (re-used across samples, so the renderer
    #: uploads their textures once; camera, light, objects and image noise change every sample)
    environments: int = 48


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
                                        [-half, half, 0]]), procedural_texture(rng),
                              (half * rng.uniform(0.3, 1.5),) * 2)
        corners = [(-half, -half), (half, -half), (half, half), (-half, half)]
        walls = _walls(corners, float(rng.uniform(2.5, 4.5)), procedural_texture(rng),
                       float(rng.uniform(1.0, 6.0)))
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
                    ) -> tuple[Scene, CameraModel, np.ndarray]:
    """A random training scene with the robot near the origin; returns (scene, camera, robot
    pose (3,) x, y, theta). ``environments``: the floor/wall looks to draw from (default: a
    fresh set from ``rng``, slower: textures are uploaded again)."""
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
    k1 = float(rng.uniform(-cfg.max_k1, 0.05))
    distortion = np.array([k1, rng.uniform(-0.1, 0.1) * abs(k1), rng.normal(0, 5e-4),
                           rng.normal(0, 5e-4), 0.0])
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
            if rng.uniform() < 0.5:
                occ = person_mesh(float(rng.uniform(1.5, 1.9)), rng.uniform(0.1, 0.9, 3))
                objs.append(SceneObject(occ, _planar_T(p[0], p[1], 0.0), instance,
                                        CLASS_ID["person"]))
            else:
                occ = box(rng.uniform([0.3, 0.3, 0.3], [0.9, 0.9, 1.2]),
                          color=rng.uniform(0.1, 0.9, 3))
                T = _planar_T(p[0], p[1], float(rng.uniform(-np.pi, np.pi)))
                T[2, 3] = 0.5 * float(occ.bounds()[1][2] - occ.bounds()[0][2])
                objs.append(SceneObject(occ, T, instance, CLASS_ID["box"]))
    objs.append(SceneObject(robot_mesh, se3_from_planar(*pose), ROBOT_INSTANCE,
                            CLASS_ID["robot"]))
    light = rng.normal(0, 1, 3)
    light[2] = abs(light[2]) + 0.5
    scene = Scene(tuple(objs), light_dir_world=tuple(light / np.linalg.norm(light)),
                  ambient=float(rng.uniform(0.25, 0.6)),
                  background_rgb=tuple(float(v) for v in rng.uniform(0.0, 1.0, 3)))
    return scene, camera, pose
