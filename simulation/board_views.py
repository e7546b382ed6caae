"""Rendered views of a calibration board: the board's image as a texture on a flat quad, placed
at given poses and drawn through a camera with known intrinsics and lens distortion by the
project's renderer (:class:`simulation.render_gl.Renderer`, lens maps of
:mod:`simulation.lens`), with the exact pixels of the board's corners as ground truth.

The board's image comes in as numpy (the simulation imports only ``protocol``; the top floor or
a test draws it with ``calibration.board``). Board frame: the calibration
board's (OpenCV's ChArUco convention): x along the printed columns, y along the rows (down on
the print), z into the board; the printed side faces a camera looking along +z.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence

import numpy as np

from core.camera import CameraModel
from core.geometry import invert_transform, rotation_from_rpy
from simulation.mesh import Mesh, Scene, SceneObject
from simulation.render_gl import Renderer

#: Grey level of the empty background around the board (a wall far behind it).
BACKGROUND_RGB: tuple[float, float, float] = (0.45, 0.45, 0.45)


@dataclasses.dataclass(frozen=True, eq=False)
class BoardTexture:
    """A board's printed image and where it lies in the board frame.

    ``image`` (H, W) or (H, W, 3) uint8; ``extent_board_m`` (x0, y0, x1, y1): the image's
    left, top, right and bottom edges in the board frame, metres (the top-left pixel's outer
    corner is (x0, y0))."""

    image: np.ndarray
    extent_board_m: tuple[float, float, float, float]

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.ndim == 2:
            img = np.repeat(img[:, :, None], 3, axis=2)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"board texture: expected (H, W[, 3]) uint8, got {img.dtype} "
                             f"{img.shape}")
        x0, y0, x1, y1 = (float(v) for v in self.extent_board_m)
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"board texture: empty extent {self.extent_board_m}")
        object.__setattr__(self, "image", np.ascontiguousarray(img))
        object.__setattr__(self, "extent_board_m", (x0, y0, x1, y1))


def board_mesh(texture: BoardTexture) -> Mesh:
    """The textured quad of ``texture`` in the board frame (z = 0), white albedo."""
    x0, y0, x1, y1 = texture.extent_board_m
    vertices = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    # texture v runs up from the image's bottom row; the board's y runs down the image
    uv = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    faces = np.array([[0, 2, 1], [0, 3, 2]])  # normal along -z: towards the viewing side
    normals = np.tile([0.0, 0.0, -1.0], (4, 1))
    return Mesh(vertices, faces, np.ones(3), normals, uv, texture.image)


def board_pose(x_m: float, y_m: float, z_m: float, roll_deg: float = 0.0,
               pitch_deg: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """(4, 4) ``T_world_board`` from a position and roll/pitch/yaw in degrees (protocol's
    convention, :func:`core.geometry.rotation_from_rpy`)."""
    T = np.eye(4)
    T[:3, :3] = rotation_from_rpy(*np.deg2rad([roll_deg, pitch_deg, yaw_deg]))
    T[:3, 3] = (x_m, y_m, z_m)
    return T


@dataclasses.dataclass(frozen=True, eq=False)
class BoardView:
    """One rendered image of the board: ``image_rgb`` (H, W, 3) uint8; ``corners_px`` (N, 2)
    the true pixels of the given board points (NaN where behind the camera);
    ``corners_visible`` (N,) bool: inside the image and in front of the camera (not checked
    for occlusion by other objects)."""

    image_rgb: np.ndarray
    corners_px: np.ndarray
    corners_visible: np.ndarray


class BoardRenderer:
    """Renders one board texture through cameras of one image size (one GL context).

    ``extra_objects``: other scene objects drawn with the board (a room around it)."""

    def __init__(self, texture: BoardTexture, width: int, height: int,
                 extra_objects: Sequence[SceneObject] = (),
                 background_rgb: tuple[float, float, float] = BACKGROUND_RGB) -> None:
        self.texture = texture
        self.mesh = board_mesh(texture)
        self.extra_objects = tuple(extra_objects)
        self.background_rgb = background_rgb
        self.renderer = Renderer(width, height, near_m=0.02, far_m=100.0)

    def close(self) -> None:
        self.renderer.release()

    def __enter__(self) -> BoardRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def scene(self, T_world_board: np.ndarray) -> Scene:
        board = SceneObject(self.mesh, np.asarray(T_world_board, np.float64))
        # ambient 1: the texture as printed, no shading gradient across the board
        return Scene((*self.extra_objects, board), ambient=1.0,
                     background_rgb=self.background_rgb, static_objects=0)

    def render(self, camera: CameraModel, T_world_board: np.ndarray,
               points_board_m: np.ndarray | None = None) -> BoardView:
        """The board at ``T_world_board`` seen by ``camera`` (whose size must be the
        renderer's); ``points_board_m`` (N, 3): board points whose true pixels to return."""
        out = self.renderer.render(self.scene(T_world_board), camera)
        pts = np.zeros((0, 3)) if points_board_m is None else np.asarray(points_board_m, float)
        uv, visible = true_pixels(camera, T_world_board, pts)
        return BoardView(out.color_rgb.copy(), uv, visible)

    def render_many(self, views: Iterable[tuple[CameraModel, np.ndarray]],
                    points_board_m: np.ndarray | None = None) -> list[BoardView]:
        return [self.render(cam, T, points_board_m) for cam, T in views]


def true_pixels(camera: CameraModel, T_world_board: np.ndarray, points_board_m: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """((N, 2) distorted pixels, (N,) bool in the image and in front) of board points."""
    pts = np.asarray(points_board_m, np.float64).reshape(-1, 3)
    T = np.asarray(T_world_board, np.float64)
    world = pts @ T[:3, :3].T + T[:3, 3]
    uv, depth = camera.project(world)
    visible = (depth > 1e-6) & camera.in_image(uv)
    return uv, visible


def camera_looking_at(camera: CameraModel, position_world_m: Sequence[float] | np.ndarray,
                      target_world_m: Sequence[float] | np.ndarray,
                      up_world: Sequence[float] = (0, 0, 1),
                      roll_deg: float = 0.0) -> CameraModel:
    """``camera`` (same intrinsics) placed at ``position_world_m`` looking at
    ``target_world_m``, image up towards ``up_world``, rolled about its optical axis."""
    p = np.asarray(position_world_m, float)
    z = np.asarray(target_world_m, float) - p
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up_world, float))
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    c, s = np.cos(np.deg2rad(roll_deg)), np.sin(np.deg2rad(roll_deg))
    R = R @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    T_world_cam = np.eye(4)
    T_world_cam[:3, :3] = R
    T_world_cam[:3, 3] = p
    return dataclasses.replace(camera, T_cam_world=invert_transform(T_world_cam))


def calibration_sweep(camera: CameraModel, board_size_m: tuple[float, float], count: int,
                      seed: int = 0, *, max_tilt_deg: float = 40.0,
                      fill: tuple[float, float] = (0.35, 0.8)) -> list[CameraModel]:
    """``count`` poses of ``camera`` around a board lying at the world origin (``T_world_board``
    = identity), as a person waves a board in front of a camera for intrinsics: the line of
    sight tilted 10 deg to ``max_tilt_deg`` from the board's normal in every direction,
    rolled, at distances where the board spans ``fill`` (a range) of the image width, and aimed
    so the board lands all over the image (some views run partly off the image, as real ones
    do). Tilts far beyond 45 deg make corners at grazing angles that no detector places well."""
    rng = np.random.default_rng(seed)
    bw, bh = board_size_m
    centre = np.array([bw / 2, bh / 2, 0.0])
    fx, fy = float(camera.K[0, 0]), float(camera.K[1, 1])
    cams = []
    for _ in range(count):
        tilt = np.deg2rad(rng.uniform(min(10.0, max_tilt_deg), max_tilt_deg))
        azimuth = rng.uniform(0.0, 2 * np.pi)
        d = fx * bw / (rng.uniform(*fill) * camera.width)
        direction = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth),
                              -np.cos(tilt)])
        position = centre + d * direction
        # aim off the board's centre so it lands anywhere in the image
        ox = rng.uniform(-0.6, 0.6) * d * camera.width / (2 * fx)
        oy = rng.uniform(-0.6, 0.6) * d * camera.height / (2 * fy)
        target = centre + np.array([ox, oy, 0.0])
        cams.append(camera_looking_at(camera, position, target, up_world=(0.0, -1.0, 0.0),
                                      roll_deg=rng.uniform(-30, 30)))
    return cams


def board_facing(board_size_m: tuple[float, float], centre_world_m: Sequence[float] | np.ndarray,
                 toward_world_m: Sequence[float] | np.ndarray, spin_deg: float = 0.0
                 ) -> np.ndarray:
    """``T_world_board`` of a board of ``board_size_m`` (width, height of the square grid)
    centred at ``centre_world_m`` with its printed side facing ``toward_world_m``, its rows
    level (board x horizontal) before it is spun by ``spin_deg`` about its normal."""
    centre = np.asarray(centre_world_m, float)
    n = np.asarray(toward_world_m, float) - centre
    z = -n / np.linalg.norm(n)
    x = np.cross([0.0, 0.0, 1.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
    R = np.stack([x, np.cross(z, x), z], axis=1)
    a = np.deg2rad(spin_deg)
    R = R @ np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0, 0, 1.0]])
    w, h = board_size_m
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ np.array([w / 2, h / 2, 0.0])
    return T


def board_walk(cameras: dict[str, CameraModel], board_size_m: tuple[float, float], rounds: int,
               seed: int = 3) -> dict[str, np.ndarray]:
    """Board poses (stamp -> ``T_world_board``) of a person walking a board through a room
    watched by ``cameras`` (ceiling cameras around its centre, as in the paper lab): stamp
    "000" held at 1 m in the centre facing the first two cameras (by id), then per round one
    pose per camera near the centre at 0.8-1.4 m, facing that camera and the next one (even
    rounds) or that camera alone (odd rounds), spun by up to 30 deg."""
    rng = np.random.default_rng(seed)
    pos = {c: m.T_world_cam[:3, 3] for c, m in cameras.items()}
    ids = sorted(pos)
    mid = np.mean(list(pos.values()), axis=0)
    poses = {"000": board_facing(board_size_m, np.array([mid[0], mid[1], 1.0]),
                                 (pos[ids[0]] + pos[ids[1 % len(ids)]]) / 2)}
    k = 1
    for rep in range(rounds):
        for i in range(len(ids)):
            a, b = ids[i], ids[(i + 1) % len(ids)]
            centre = np.array([*(mid[:2] + rng.uniform(-1.0, 1.0, 2)), rng.uniform(0.8, 1.4)])
            target = (pos[a] + pos[b]) / 2 if rep % 2 == 0 else pos[a]
            poses[f"{k:03d}"] = board_facing(board_size_m, centre, target,
                                             rng.uniform(-30, 30))
            k += 1
    return poses
