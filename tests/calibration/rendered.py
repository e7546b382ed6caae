"""Rendered ChArUco views shared by the calibration tests (the project's renderer through the
paper lab's camera model; ground-truth corner pixels from the board's pose)."""

from __future__ import annotations

import functools

import numpy as np

from calibration.board import CharucoBoardSpec, board_image
from core.camera import CameraModel
from core.site import load_site
from simulation.board_views import (
    BoardRenderer,
    BoardTexture,
    BoardView,
    board_walk,
    calibration_sweep,
    camera_looking_at,
)
from tests.conftest import REPO_ROOT

PAPER_LAB = REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"
#: an A2-sized board (540 x 420 mm), as a lab prints for ~850 px wide cameras
INTRINSICS_BOARD = CharucoBoardSpec(9, 7, 0.06, 0.045, "DICT_5X5_100")


def paper_lab_camera(camera_id: str = "cam1") -> CameraModel:
    return load_site(PAPER_LAB).cameras[camera_id]


def texture(spec: CharucoBoardSpec, px_per_square: int = 60) -> BoardTexture:
    img = board_image(spec, px_per_square)
    return BoardTexture(img.image, img.extent_board_m)


@functools.lru_cache(maxsize=2)
def sweep_views(count: int = 30, seed: int = 4) -> tuple[CameraModel, tuple[BoardView, ...]]:
    """(true camera, ``count`` rendered views of :data:`INTRINSICS_BOARD` at the origin)."""
    cam = paper_lab_camera()
    spec = INTRINSICS_BOARD
    with BoardRenderer(texture(spec), cam.width, cam.height) as br:
        views = tuple(br.render(c, np.eye(4), spec.corners_board_m())
                      for c in calibration_sweep(cam, spec.size_m, count, seed=seed))
    return cam, views


def partial_view() -> BoardView:
    """The board mostly off the image: 4 corners left."""
    cam = paper_lab_camera()
    spec = INTRINSICS_BOARD
    w, h = spec.size_m
    c = camera_looking_at(cam, (w / 2, h / 2, -0.6), (w / 2 + 1.0, h / 2, 0.0),
                          up_world=(0, -1, 0))
    with BoardRenderer(texture(spec), cam.width, cam.height) as br:
        return br.render(c, np.eye(4), spec.corners_board_m())


def boardless_view() -> BoardView:
    """The camera looking away from the board (only the background)."""
    cam = paper_lab_camera()
    spec = INTRINSICS_BOARD
    c = camera_looking_at(cam, (0.0, 0.0, -1.0), (0.0, 0.0, -2.0), up_world=(0, -1, 0))
    with BoardRenderer(texture(spec), cam.width, cam.height) as br:
        return br.render(c, np.eye(4), spec.corners_board_m())


#: an A0-sized board (1000 x 800 mm) with large 4x4 markers: the paper lab's ceiling cameras
#: (fx 428 px) see it from 3-5 m with ~20 px squares
EXTRINSICS_BOARD = CharucoBoardSpec(5, 4, 0.2, 0.156, "DICT_4X4_50")


def paper_lab_board_poses(cameras: dict[str, CameraModel], rounds: int, seed: int = 3
                          ) -> dict[str, np.ndarray]:
    """:func:`simulation.board_views.board_walk` of :data:`EXTRINSICS_BOARD` in the paper lab."""
    return board_walk(cameras, EXTRINSICS_BOARD.size_m, rounds, seed)


def render_sightings(cameras: dict[str, CameraModel], poses: dict[str, np.ndarray]
                     ) -> dict[str, dict[str, np.ndarray]]:
    """camera id -> stamp -> rendered image (RGB) of :data:`EXTRINSICS_BOARD` at every pose."""
    first = next(iter(cameras.values()))
    out: dict[str, dict[str, np.ndarray]] = {c: {} for c in cameras}
    with BoardRenderer(texture(EXTRINSICS_BOARD, 50), first.width, first.height) as br:
        for stamp, T in poses.items():
            for cid, cam in cameras.items():
                out[cid][stamp] = br.render(cam, T).image_rgb
    return out
