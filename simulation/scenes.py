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
from protocol.geometry import invert_transform, rotation_z, se3_from_planar
from protocol.site import RobotModel, look_at_T_world_cam
from simulation.mesh import CLASS_ID, Mesh, Scene, SceneObject

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


def box_mesh(size_m: Sequence[float], color: Sequence[float]) -> Mesh:
    """An axis-aligned box centred on the origin, flat-shaded (24 vertices)."""
    sx, sy, sz = (0.5 * float(s) for s in size_m)
    faces_axes = [  # (normal, u axis, v axis)
        ((1, 0, 0), (0, 1, 0), (0, 0, 1)), ((-1, 0, 0), (0, -1, 0), (0, 0, 1)),
        ((0, 1, 0), (-1, 0, 0), (0, 0, 1)), ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
        ((0, 0, 1), (1, 0, 0), (0, 1, 0)), ((0, 0, -1), (1, 0, 0), (0, -1, 0)),
    ]
    half = np.array([sx, sy, sz])
    verts, normals, faces = [], [], []
    for n, u, v in faces_axes:
        n_, u_, v_ = (np.array(a, dtype=np.float64) for a in (n, u, v))
        center = n_ * half
        du, dv = u_ * half, v_ * half
        base = len(verts)
        verts += [center - du - dv, center + du - dv, center + du + dv, center - du + dv]
        normals += [n_] * 4
        faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return Mesh(np.array(verts), np.array(faces), np.asarray(color, np.float32),
                np.array(normals))


def cylinder_mesh(radius_m: float, height_m: float, color: Sequence[float],
                  segments: int = 16) -> Mesh:
    """A capped cylinder standing on z = 0."""
    ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.column_stack([radius_m * np.cos(ang), radius_m * np.sin(ang)])
    side_v = np.vstack([np.column_stack([ring, np.zeros(segments)]),
                        np.column_stack([ring, np.full(segments, height_m)])])
    side_n = np.vstack([np.column_stack([np.cos(ang), np.sin(ang), np.zeros(segments)])] * 2)
    i = np.arange(segments)
    j = (i + 1) % segments
    side_f = np.vstack([np.column_stack([i, j, segments + j]),
                        np.column_stack([i, segments + j, segments + i])])
    top_c = len(side_v)
    top_v = np.vstack([[0, 0, height_m], np.column_stack([ring, np.full(segments, height_m)])])
    top_f = np.column_stack([np.full(segments, top_c), top_c + 1 + i, top_c + 1 + j])
    bot_c = top_c + len(top_v)
    bot_v = np.vstack([[0, 0, 0], np.column_stack([ring, np.zeros(segments)])])
    bot_f = np.column_stack([np.full(segments, bot_c), bot_c + 1 + j, bot_c + 1 + i])
    verts = np.vstack([side_v, top_v, bot_v])
    normals = np.vstack([side_n, np.tile([0, 0, 1.0], (len(top_v), 1)),
                         np.tile([0, 0, -1.0], (len(bot_v), 1))])
    return Mesh(verts, np.vstack([side_f, top_f, bot_f]), np.asarray(color, np.float32), normals)


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

    body = cylinder_mesh(0.18, 0.82 * height_m, color)
    head = box_mesh((0.2, 0.2, 0.22), (0.85, 0.7, 0.6)).transformed(
        _translation(0, 0, 0.82 * height_m + 0.11))
    return concatenate([body, head])


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
    for k in range(4):  # walls face into the room
        (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % 4]
        quad = np.array([[x0, y0, 0], [x1, y1, 0], [x1, y1, h], [x0, y0, h]])
        length = math.hypot(x1 - x0, y1 - y0)
        objs.append(SceneObject(textured_quad(quad, wall_tex, (length / 2, h / 2)), np.eye(4), 0,
                                CLASS_ID["wall"]))
    for box in scenario.obstacles:  # type: ignore[attr-defined]
        size = np.asarray(box.size_m, dtype=np.float64)
        color = rng.uniform(0.25, 0.85, 3)
        mesh = box_mesh(size, color)
        T = _planar_T(float(box.center_xy_m[0]), float(box.center_xy_m[1]), float(box.yaw_rad),
                      float(box.z_min_m) + size[2] / 2)
        objs.append(SceneObject(mesh, T, 0, obstacle_class(box.name)))
    return SiteGeometry(tuple(objs))


def site_scene(geometry: SiteGeometry, robot_mesh: Mesh, robot_pose: Sequence[float],
               occluders: Sequence[SceneObject] = (), *,
               light_dir_world: tuple[float, float, float] = (0.3, 0.2, 1.0)) -> Scene:
    """The site with the robot at ``robot_pose`` (x, y, theta in the world frame)."""
    x, y, theta = (float(v) for v in robot_pose)
    robot = SceneObject(robot_mesh, se3_from_planar(x, y, theta), ROBOT_INSTANCE,
                        CLASS_ID["robot"])
    return Scene((*geometry.objects, robot, *occluders), light_dir_world=light_dir_world)


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
                    ) -> tuple[Scene, CameraModel, np.ndarray]:
    """A random training scene with the robot near the origin; returns (scene, camera, robot
    pose (3,) x, y, theta)."""
    cfg = config or RandomizationConfig()
    pose = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-np.pi, np.pi)])
    half = cfg.room_half_size_m
    objs: list[SceneObject] = []
    floor = textured_quad(np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0],
                                    [-half, half, 0]]), procedural_texture(rng),
                          (half * rng.uniform(0.3, 1.5),) * 2)
    objs.append(SceneObject(floor, np.eye(4), 0, CLASS_ID["floor"]))
    wall_h = float(rng.uniform(2.5, 4.5))
    wall_tex = procedural_texture(rng)
    corners = [(-half, -half), (half, -half), (half, half), (-half, half)]
    for k in range(4):
        (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % 4]
        quad = np.array([[x0, y0, 0], [x1, y1, 0], [x1, y1, wall_h], [x0, y0, wall_h]])
        objs.append(SceneObject(textured_quad(quad, wall_tex, (half / 2, wall_h / 2)), np.eye(4),
                                0, CLASS_ID["wall"]))
    # camera: somewhere around the robot, looking at it (with jitter so it is not centred)
    dist = float(rng.uniform(*cfg.distance_m))
    az = float(rng.uniform(-np.pi, np.pi))
    cam_pos = np.array([pose[0] + dist * math.cos(az), pose[1] + dist * math.sin(az),
                        rng.uniform(*cfg.camera_height_m)])
    target = np.array([pose[0], pose[1], 0.5 * model.height_m]) + rng.normal(
        0, cfg.look_jitter_m * min(1.0, dist / 4), 3) * [1, 1, 0.4]
    k1 = float(rng.uniform(-cfg.max_k1, 0.05))
    distortion = np.array([k1, rng.uniform(-0.1, 0.1) * abs(k1), rng.normal(0, 5e-4),
                           rng.normal(0, 5e-4), 0.0])
    camera = look_at_camera("random", cam_pos, target, width, height,
                            float(rng.uniform(*cfg.hfov_deg)), distortion)
    instance = FIRST_OTHER_INSTANCE
    # distractors: random boxes and cylinders away from the robot and the camera
    for _ in range(int(rng.integers(cfg.distractors[0], cfg.distractors[1] + 1))):
        p = rng.uniform(-half + 1, half - 1, 2)
        if np.hypot(*(p - pose[:2])) < 0.8 or np.hypot(*(p - cam_pos[:2])) < 0.8:
            continue
        color = rng.uniform(0.05, 0.95, 3)
        if rng.uniform() < 0.5:
            mesh = box_mesh(rng.uniform([0.2, 0.2, 0.2], [1.5, 1.5, 2.0]), color)
            T = _planar_T(p[0], p[1], float(rng.uniform(-np.pi, np.pi)), 0.0)
            T[2, 3] = 0.5 * float(mesh.bounds()[1][2] - mesh.bounds()[0][2])
        else:
            mesh = cylinder_mesh(float(rng.uniform(0.1, 0.5)), float(rng.uniform(0.3, 2.0)),
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
                occ = box_mesh(rng.uniform([0.3, 0.3, 0.3], [0.9, 0.9, 1.2]),
                               rng.uniform(0.1, 0.9, 3))
                T = _planar_T(p[0], p[1], float(rng.uniform(-np.pi, np.pi)))
                T[2, 3] = 0.5 * float(occ.bounds()[1][2] - occ.bounds()[0][2])
                objs.append(SceneObject(occ, T, instance, CLASS_ID["box"]))
    objs.append(SceneObject(robot_mesh, se3_from_planar(*pose), ROBOT_INSTANCE,
                            CLASS_ID["robot"]))
    light = rng.normal(0, 1, 3)
    light[2] = abs(light[2]) + 0.5
    scene = Scene(tuple(objs), light_dir_world=tuple(light / np.linalg.norm(light)),
                  ambient=float(rng.uniform(0.25, 0.6)))
    return scene, camera, pose
