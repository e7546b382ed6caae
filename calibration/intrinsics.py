"""One camera's intrinsics from views of a ChArUco board: which views to keep (those that add
image coverage or a new board pose), OpenCV's calibration with the standard radial-tangential
lens model, the image coverage as a picture, and the calibration files (ROS ``camera_info``
YAML, OpenCV ``FileStorage`` YAML) that :func:`core.site.load_camera_calibration` reads.

Pixels: (u, v), pixel centres at integer coordinates, origin top-left (OpenCV's convention, the
one :class:`core.camera.CameraModel` projects with).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Final

import cv2
import numpy as np
import yaml

from calibration.board import (
    BoardDetection,
    BoardDetector,
    CalibrationError,
    CharucoBoardSpec,
)

log = logging.getLogger(__name__)

#: Fewest views a calibration runs on (5 distortion coefficients and 4 intrinsics from planar
#: views need several tilted ones; fewer give results that fit the views and little else).
MIN_VIEWS: Final = 8
#: Views kept at most (beyond ~40 good views the result barely changes; the solve time grows).
MAX_VIEWS: Final = 40
#: Columns of the coverage grid (rows follow the image's aspect ratio).
COVERAGE_COLUMNS: Final = 12
#: A view that adds no coverage cell is kept when its pose descriptor (centre, size, tilt)
#: differs from every kept view's by at least this much (sum of absolute differences).
MIN_POSE_DISTANCE: Final = 0.2
#: A view whose own RMS exceeds max(this, OUTLIER_FACTOR x the median view's) is dropped and the
#: calibration repeated (a misdetected corner, a moving board).
OUTLIER_MIN_PX: Final = 1.0
OUTLIER_FACTOR: Final = 3.0
_CRITERIA: Final = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)


# ------------------------------------------------------------------------------ view choice


@dataclasses.dataclass(frozen=True)
class ViewDescriptor:
    """Where and how a view shows the board: centre (u, v) / image size, size (square root of
    the corners' hull area / image area), tilt (log ratios of the board's opposite edges
    through the view's homography: left/right, top/bottom)."""

    centre_u: float
    centre_v: float
    size: float
    tilt_x: float
    tilt_y: float

    def distance(self, other: ViewDescriptor) -> float:
        return (abs(self.centre_u - other.centre_u) + abs(self.centre_v - other.centre_v)
                + abs(self.size - other.size) + abs(self.tilt_x - other.tilt_x)
                + abs(self.tilt_y - other.tilt_y))


def coverage_grid_shape(image_size: tuple[int, int]) -> tuple[int, int]:
    """(rows, columns) of the coverage grid of a (width, height) image."""
    w, h = image_size
    return max(3, round(COVERAGE_COLUMNS * h / w)), COVERAGE_COLUMNS


def coverage_cells(corners_px: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """(rows, columns) bool: grid cells holding at least one of ``corners_px`` (N, 2)."""
    rows, cols = coverage_grid_shape(image_size)
    w, h = image_size
    grid = np.zeros((rows, cols), bool)
    if len(corners_px):
        c = np.clip((corners_px[:, 0] + 0.5) * cols / w, 0, cols - 1).astype(int)
        r = np.clip((corners_px[:, 1] + 0.5) * rows / h, 0, rows - 1).astype(int)
        grid[r, c] = True
    return grid


def view_descriptor(detection: BoardDetection, spec: CharucoBoardSpec) -> ViewDescriptor:
    """The :class:`ViewDescriptor` of a usable detection."""
    w, h = detection.image_size
    pts = detection.corners_px
    board_xy = spec.corners_board_m()[detection.corner_ids, :2]
    H, _ = cv2.findHomography(board_xy, pts, 0)
    tilt_x = tilt_y = 0.0
    if H is not None:
        bw, bh = spec.size_m
        quad = cv2.perspectiveTransform(
            np.array([[[0, 0], [bw, 0], [bw, bh], [0, bh]]], np.float64), H)[0]
        top, right = np.linalg.norm(quad[1] - quad[0]), np.linalg.norm(quad[2] - quad[1])
        bottom, left = np.linalg.norm(quad[3] - quad[2]), np.linalg.norm(quad[0] - quad[3])
        if min(top, right, bottom, left) > 1e-6:
            tilt_x = float(np.clip(math.log(left / right), -1.0, 1.0))
            tilt_y = float(np.clip(math.log(top / bottom), -1.0, 1.0))
    hull = cv2.convexHull(pts.astype(np.float32))
    size = math.sqrt(max(float(cv2.contourArea(hull)), 0.0) / (w * h))
    centre = pts.mean(axis=0)
    return ViewDescriptor(float(centre[0] / w), float(centre[1] / h), size, tilt_x, tilt_y)


@dataclasses.dataclass(frozen=True)
class ViewChoice:
    """Which usable views were kept, and why the others were not (``name -> reason``)."""

    kept: tuple[str, ...]
    redundant: dict[str, str]


def select_views(detections: Sequence[tuple[str, BoardDetection]], spec: CharucoBoardSpec,
                 max_views: int = MAX_VIEWS) -> ViewChoice:
    """Keep, greedily from the views with the most corners, each usable view that covers a grid
    cell no kept view covers or whose pose descriptor differs from every kept one by
    :data:`MIN_POSE_DISTANCE`; at most ``max_views``."""
    usable = [(name, d) for name, d in detections if d.usable]
    usable.sort(key=lambda nd: -nd[1].num_corners)
    kept: list[str] = []
    kept_desc: list[ViewDescriptor] = []
    covered: np.ndarray | None = None
    redundant: dict[str, str] = {}
    for name, det in usable:
        cells = coverage_cells(det.corners_px, det.image_size)
        desc = view_descriptor(det, spec)
        new_cells = int(np.count_nonzero(cells & ~covered)) if covered is not None else 1
        nearest = min((desc.distance(k), i) for i, k in enumerate(kept_desc)) if kept_desc \
            else (math.inf, -1)
        if len(kept) >= max_views:
            redundant[name] = f"{max_views} views kept already"
            continue
        if new_cells == 0 and nearest[0] < MIN_POSE_DISTANCE:
            redundant[name] = (f"adds no coverage and repeats the pose of {kept[nearest[1]]} "
                               f"(distance {nearest[0]:.2f} < {MIN_POSE_DISTANCE})")
            continue
        kept.append(name)
        kept_desc.append(desc)
        covered = cells if covered is None else covered | cells
    return ViewChoice(tuple(kept), redundant)


# ------------------------------------------------------------------------------ calibration


@dataclasses.dataclass(frozen=True)
class ViewError:
    """One used view: its reprojection RMS (px) and corners after calibration."""

    name: str
    rms_px: float
    num_corners: int


@dataclasses.dataclass(frozen=True, eq=False)
class IntrinsicsResult:
    """A camera's calibration. ``K`` (3, 3) pixels; ``dist`` OpenCV coefficients (5: k1, k2,
    p1, p2, k3, or 8 with the rational model); ``rms_px`` reprojection RMS over every corner of
    the used views; ``std_K`` (4,) standard deviations of fx, fy, cx, cy (px) and ``std_dist``
    of the coefficients, from OpenCV; ``views`` per used view; ``skipped`` image name -> why it
    was not used (not usable, redundant, outlier); ``coverage`` (rows, cols) bool grid of the
    image cells some used corner falls in; ``T_cam_board`` per used view (4, 4)."""

    camera_id: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    rms_px: float
    std_K: np.ndarray
    std_dist: np.ndarray
    views: tuple[ViewError, ...]
    skipped: dict[str, str]
    coverage: np.ndarray
    corners_px: np.ndarray
    T_cam_board: dict[str, np.ndarray]
    num_images: int

    @property
    def coverage_fraction(self) -> float:
        return float(self.coverage.mean())

    def summary(self) -> str:
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        sfx, sfy, scx, scy = self.std_K
        return (f"camera {self.camera_id} {self.width}x{self.height}: RMS {self.rms_px:.3f} px "
                f"over {len(self.views)} views of {self.num_images} images; fx {fx:.2f}±{sfx:.2f}"
                f" fy {fy:.2f}±{sfy:.2f} cx {cx:.2f}±{scx:.2f} cy {cy:.2f}±{scy:.2f}; dist "
                f"{np.array2string(self.dist, precision=4, separator=', ')}; coverage "
                f"{100 * self.coverage_fraction:.0f} % of the image")


def _too_few(num_images: int, usable: int, min_views: int, skipped: dict[str, str]) -> str:
    counts = collections.Counter(r.split(" (")[0].split(";")[0] for r in skipped.values())
    why = ", ".join(f"{n} {kind}" for kind, n in counts.most_common())
    lines = [f"only {usable} usable views of {num_images} images (need at least {min_views})"
             + (f"; skipped: {why}" if why else "")]
    for name, reason in list(skipped.items())[:20]:
        lines.append(f"  {name}: {reason}")
    if len(skipped) > 20:
        lines.append(f"  ... and {len(skipped) - 20} more")
    lines.append("show the whole board, sharp, at several distances and tilts (about 45 deg), "
                 "reaching every part of the image")
    return "\n".join(lines)


def calibrate_intrinsics(detections: Sequence[tuple[str, BoardDetection]],
                         spec: CharucoBoardSpec, camera_id: str = "camera", *,
                         rational_model: bool = False, min_views: int = MIN_VIEWS,
                         max_views: int = MAX_VIEWS,
                         skipped: dict[str, str] | None = None) -> IntrinsicsResult:
    """Calibrate from ``(image name, detection)`` pairs (all of one image size): keep views by
    :func:`select_views`, run ``cv2.calibrateCameraExtended`` (standard 5-coefficient model, or
    8 with ``rational_model``), drop outlier views (:data:`OUTLIER_FACTOR`) and repeat.

    ``skipped``: images already refused before detection (name -> reason), reported with the
    rest. Raises :class:`CalibrationError` naming how many views were usable and why the
    others were skipped when fewer than ``min_views`` remain.
    """
    skipped = dict(skipped or {})
    num_images = len(detections) + len(skipped)
    sizes = collections.Counter(d.image_size for _, d in detections)
    if not sizes:
        raise CalibrationError(_too_few(num_images, 0, min_views, skipped))
    size = sizes.most_common(1)[0][0]
    dets: list[tuple[str, BoardDetection]] = []
    for name, det in detections:
        if det.image_size != size:
            skipped[name] = f"image size {det.image_size[0]}x{det.image_size[1]} is not the " \
                            f"camera's {size[0]}x{size[1]}"
        elif not det.usable:
            skipped[name] = str(det.reason)
        else:
            dets.append((name, det))
    if len(dets) < min_views:
        raise CalibrationError(_too_few(num_images, len(dets), min_views, skipped))
    choice = select_views(dets, spec, max_views)
    skipped.update({n: f"redundant: {r}" for n, r in choice.redundant.items()})
    by_name = dict(dets)
    used = list(choice.kept)
    if len(used) < min_views:  # redundant views still beat too few: take them back in order
        for name, _ in dets:
            if name not in used:
                used.append(name)
                skipped.pop(name, None)
            if len(used) >= min_views:
                break
    corners_board = spec.corners_board_m().astype(np.float32)
    flags = cv2.CALIB_RATIONAL_MODEL if rational_model else 0
    for _ in range(3):
        obj = [corners_board[by_name[n].corner_ids] for n in used]
        img = [by_name[n].corners_px.astype(np.float32).reshape(-1, 1, 2) for n in used]
        try:
            rms, K, dist, rvecs, tvecs, std_intr, _, per_view = cv2.calibrateCameraExtended(
                obj, img, size, None, None, flags=flags,  # type: ignore[call-overload]
                criteria=_CRITERIA)
        except cv2.error as exc:
            raise CalibrationError(f"OpenCV's calibration failed on {len(used)} views "
                                   f"({', '.join(used[:10])}...): {exc.err}") from None
        per_view = np.asarray(per_view, float).reshape(-1)
        bar = max(OUTLIER_MIN_PX, OUTLIER_FACTOR * float(np.median(per_view)))
        outliers = [n for n, e in zip(used, per_view, strict=True) if e > bar]
        if not outliers or len(used) - len(outliers) < min_views:
            break
        for n, e in zip(used, per_view, strict=True):
            if e > bar:
                skipped[n] = f"outlier: view RMS {e:.2f} px > {bar:.2f} px"
        used = [n for n in used if n not in outliers]
        log.info("calibration: dropped %d outlier views, repeating", len(outliers))
    n_dist = 8 if rational_model else 5
    dist = np.asarray(dist, float).reshape(-1)[:n_dist]
    std = np.asarray(std_intr, float).reshape(-1)
    views = tuple(ViewError(n, float(e), by_name[n].num_corners)
                  for n, e in zip(used, per_view, strict=True))
    all_corners = np.concatenate([by_name[n].corners_px for n in used])
    T_cam_board = {}
    for n, r, t in zip(used, rvecs, tvecs, strict=True):
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(np.asarray(r, float))[0]
        T[:3, 3] = np.asarray(t, float).reshape(3)
        T_cam_board[n] = T
    result = IntrinsicsResult(
        camera_id, size[0], size[1], np.asarray(K, float), dist, float(rms), std[:4],
        std[4:4 + n_dist], views, skipped, coverage_cells(all_corners, size), all_corners,
        T_cam_board, num_images)
    log.debug("%s", result.summary())
    return result


def calibrate_from_images(images: Iterable[tuple[str, np.ndarray]], spec: CharucoBoardSpec,
                          camera_id: str = "camera", *, detector: BoardDetector | None = None,
                          **kwargs: object) -> tuple[IntrinsicsResult, list[tuple[str,
                                                                              BoardDetection]]]:
    """Detect the board in every ``(name, image)`` and :func:`calibrate_intrinsics`; returns the
    result and the detections (for overlays)."""
    detector = detector or BoardDetector(spec)
    detections = [(name, detector.detect(img)) for name, img in images]
    return calibrate_intrinsics(detections, spec, camera_id, **kwargs), detections  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ evaluation


def model_difference_px(K_a: np.ndarray, dist_a: np.ndarray, K_b: np.ndarray,
                        dist_b: np.ndarray, image_size: tuple[int, int], step_px: int = 16,
                        coverage: np.ndarray | None = None) -> np.ndarray:
    """(N,) pixel distances between where two camera models put the same rays: a grid of image
    pixels (every ``step_px``) is taken back to rays through model a and projected through
    model b. 0 everywhere for identical models. ``coverage`` (rows, cols) bool (an
    :attr:`IntrinsicsResult.coverage`): only pixels in covered cells (a calibration says
    little about the lens where no view reached)."""
    w, h = image_size
    u, v = np.meshgrid(np.arange(step_px / 2, w, step_px, dtype=float),
                       np.arange(step_px / 2, h, step_px, dtype=float))
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    if coverage is not None:
        rows, cols = coverage.shape
        c = np.clip((px[:, 0] + 0.5) * cols / w, 0, cols - 1).astype(int)
        r = np.clip((px[:, 1] + 0.5) * rows / h, 0, rows - 1).astype(int)
        px = px[coverage[r, c]]
    rays = cv2.undistortPoints(px.reshape(-1, 1, 2), np.asarray(K_a, float),
                               np.asarray(dist_a, float), criteria=_CRITERIA).reshape(-1, 2)
    pts = np.column_stack([rays, np.ones(len(rays))])
    back, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.asarray(K_b, float),
                                np.asarray(dist_b, float))
    return np.linalg.norm(back.reshape(-1, 2) - px, axis=1)


# ------------------------------------------------------------------------------ pictures


def coverage_image(result: IntrinsicsResult, background: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) BGR picture of the image coverage: every used corner as a dot, the grid cells
    no used view reached tinted red, the covered fraction written at the top."""
    w, h = result.width, result.height
    canvas: np.ndarray
    if background is None:
        canvas = np.full((h, w, 3), 235, np.uint8)
    else:
        bg = np.asarray(background)
        bg = cv2.cvtColor(bg, cv2.COLOR_GRAY2BGR) if bg.ndim == 2 else bg
        canvas = (0.5 * bg.astype(np.float32) + 110).clip(0, 255).astype(np.uint8)
    rows, cols = result.coverage.shape
    overlay = canvas.copy()
    for r in range(rows):
        for c in range(cols):
            x0, x1 = round(c * w / cols), round((c + 1) * w / cols) - 1
            y0, y1 = round(r * h / rows), round((r + 1) * h / rows) - 1
            if not result.coverage[r, c]:
                cv2.rectangle(overlay, (x0, y0), (x1, y1), (60, 60, 230), -1)
    canvas = cv2.addWeighted(overlay, 0.45, canvas, 0.55, 0.0)
    for r in range(1, rows):
        y = round(r * h / rows)
        cv2.line(canvas, (0, y), (w - 1, y), (150, 150, 150), 1)
    for c in range(1, cols):
        x = round(c * w / cols)
        cv2.line(canvas, (x, 0), (x, h - 1), (150, 150, 150), 1)
    for u, v in result.corners_px:
        cv2.circle(canvas, (round(float(u)), round(float(v))), 2, (160, 90, 20), -1,
                   cv2.LINE_AA)
    text = (f"{result.camera_id}: {100 * result.coverage_fraction:.0f} % of the image covered "
            f"by {len(result.views)} views (red: no corner), RMS {result.rms_px:.2f} px")
    scale = max(0.45, w / 1600)
    cv2.putText(canvas, text, (8, round(24 * scale / 0.6)), cv2.FONT_HERSHEY_SIMPLEX, scale,
                (20, 20, 20), 2, cv2.LINE_AA)
    return canvas


# ------------------------------------------------------------------------------ files


def _ros_matrix(rows: int, cols: int, data: np.ndarray) -> dict[str, object]:
    return {"rows": rows, "cols": cols, "data": [float(x) for x in np.asarray(data).ravel()]}


def write_camera_info_yaml(result: IntrinsicsResult, path: str | Path) -> Path:
    """The ROS ``camera_info`` YAML (``camera_calibration_parsers`` layout: image size,
    camera_name, camera_matrix, distortion_model plumb_bob / rational_polynomial,
    distortion_coefficients, rectification_matrix, projection_matrix)."""
    P = np.zeros((3, 4))
    P[:, :3] = result.K
    doc = {
        "image_width": int(result.width),
        "image_height": int(result.height),
        "camera_name": result.camera_id,
        "camera_matrix": _ros_matrix(3, 3, result.K),
        "distortion_model": "rational_polynomial" if result.dist.size == 8 else "plumb_bob",
        "distortion_coefficients": _ros_matrix(1, int(result.dist.size), result.dist),
        "rectification_matrix": _ros_matrix(3, 3, np.eye(3)),
        "projection_matrix": _ros_matrix(3, 4, P),
    }
    head = (f"# {result.camera_id}: written by `smartedge calibrate intrinsics`; reprojection "
            f"RMS {result.rms_px:.3f} px over {len(result.views)} views, "
            f"{100 * result.coverage_fraction:.0f} % of the image covered\n")
    p = Path(path)
    p.write_text(head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None),
                 encoding="utf-8")
    return p


def write_opencv_yaml(result: IntrinsicsResult, path: str | Path) -> Path:
    """The OpenCV ``FileStorage`` YAML (``camera_matrix``, ``distortion_coefficients``,
    ``image_width``, ``image_height``, ``avg_reprojection_error``)."""
    p = Path(path)
    fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise OSError(f"{p}: OpenCV cannot open it for writing")
    try:
        fs.write("image_width", int(result.width))
        fs.write("image_height", int(result.height))
        fs.write("camera_matrix", np.asarray(result.K, np.float64))
        fs.write("distortion_coefficients", np.asarray(result.dist, np.float64).reshape(1, -1))
        fs.write("avg_reprojection_error", float(result.rms_px))
        fs.write("camera_name", result.camera_id)
    finally:
        fs.release()
    return p
