"""The renderer's camera model: the OpenGL projection of OpenCV intrinsics and the lens map
that warps an undistorted render into the image the distorted lens sees (numpy + OpenCV; no GL).

Conventions are OpenCV's (x right, y down, z forward; integer pixel coordinates are pixel
*centres*): a vertex drawn through :func:`projection_matrix` lands exactly where
``cv2.projectPoints`` puts it. With lens distortion the scene is rendered undistorted through
an internal pinhole camera (:attr:`LensMap.K_render`) whose field of view covers the
undistorted footprint of every image pixel, then warped with the maps of :func:`lens_map` and
``cv2.remap``. Pixels of a lens model that have no undistorted preimage (a polynomial that folds
back, see :func:`core.geometry.lens_fold_radius`) map outside the render and stay empty.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Final

import cv2
import numpy as np

from core.camera import CameraModel
from core.geometry import distort_normalized, lens_fold_radius

#: Default near / far clipping distances along the optical axis, metres.
DEFAULT_NEAR_M: Final = 0.05
DEFAULT_FAR_M: Final = 200.0
#: Spacing of the exact undistortion samples a lens map is interpolated from, pixels. The map
#: is smooth, so bilinear interpolation over 8 px is off by ~0.01 px for k1 = -0.2.
_LENS_GRID_STEP_PX: Final = 8
#: Margin of the internal render around the undistorted footprint, pixels (bilinear needs 1).
_LENS_PAD_PX: Final = 2
#: A pixel whose undistortion does not re-distort to within this many pixels has no preimage.
_LENS_MAX_RESIDUAL_PX: Final = 1e-3
#: Image regions where the lens squeezes more undistorted pixels than this into one image pixel
#: (only next to the fold of a lens polynomial that folds back) are left empty.
_LENS_MAX_STRETCH: Final = 3.0
#: Largest internal render relative to the image, per axis (caps degenerate lens models).
_MAX_INTERNAL_SCALE: Final = 3.0
_UNDISTORT_CRITERIA: Final = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


def projection_matrix(K: np.ndarray, width: int, height: int, near_m: float = DEFAULT_NEAR_M,
                      far_m: float = DEFAULT_FAR_M) -> np.ndarray:
    """(4, 4) OpenGL projection of the OpenCV-convention intrinsics ``K`` (3, 3, skew allowed).

    Takes camera optical-frame points (z forward) to clip space such that the GL window
    coordinate of a point is (u + 0.5, v + 0.5) for its OpenCV pixel (u, v): GL pixel centres
    sit at half-integers, OpenCV's at integers. Window row 0 is image row 0 (the top), so the
    image is read back unflipped (and triangle winding on screen is mirrored: faces
    counter-clockwise seen from outside are clockwise on screen). Depth maps [near_m, far_m] to
    [-1, 1].
    """
    fx, s, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    P = np.zeros((4, 4))
    P[0, :3] = (2.0 * fx / width, 2.0 * s / width, 2.0 * (cx + 0.5) / width - 1.0)
    P[1, 1:3] = (2.0 * fy / height, 2.0 * (cy + 0.5) / height - 1.0)
    P[2, 2:] = ((far_m + near_m) / (far_m - near_m), -2.0 * far_m * near_m / (far_m - near_m))
    P[3, 2] = 1.0
    return P


@dataclasses.dataclass(frozen=True, eq=False)
class LensMap:
    """How the internal undistorted render becomes the distorted image of one camera.

    ``K_render`` (3, 3) and ``render_size`` (width, height): the internal pinhole camera.
    ``color_maps``: OpenCV fixed-point maps (CV_16SC2 + CV_16UC1) for a bilinear ``cv2.remap``
    of the colour; ``nearest_map`` (H, W, 2) int16 (CV_16SC2): the internal pixel nearest to
    each image pixel's preimage, for ``cv2.remap`` with ``INTER_NEAREST`` of the label images.
    Pixels without preimage map outside the render (they get the border value: nothing).
    ``identity``: no distortion, the render is the image.
    """

    K_render: np.ndarray
    render_size: tuple[int, int]
    identity: bool
    color_maps: tuple[np.ndarray, np.ndarray] | None = None
    nearest_map: np.ndarray | None = None
    num_without_preimage: int = 0
    #: the camera's intrinsics (3, 3), distortion coefficients and the lens's fold radius
    #: (:func:`core.geometry.lens_fold_radius`): to map internal pixels to image pixels
    K: np.ndarray | None = None
    dist: np.ndarray | None = None
    fold_radius: float = math.inf


def lens_map(camera: CameraModel) -> LensMap:
    """The :class:`LensMap` of ``camera`` (numpy + OpenCV; 10-30 ms at 848x480).

    The exact undistortion (iterative, checked by re-distorting with
    :func:`core.geometry.distort_normalized`) is computed on a grid every
    ``_LENS_GRID_STEP_PX`` pixels and interpolated bilinearly in float. The internal focal
    length is the camera's, enlarged where the lens magnifies (pincushion) so the render is never
    coarser than the image.
    """
    W, H = camera.width, camera.height
    K, dist = camera.K, camera.dist
    if not np.any(dist) or dist.size == 0:
        return LensMap(K.copy(), (W, H), identity=True, K=K.copy(), dist=dist.copy())

    step = _LENS_GRID_STEP_PX
    # Coarse samples at the centres of step x step cells, plus one ring outside, so cv2.resize
    # (cell-centred, float weights) interpolates every image pixel between exact samples.
    gx = (np.arange(-1, math.ceil(W / step) + 1) * step + (step - 1) / 2.0)
    gy = (np.arange(-1, math.ceil(H / step) + 1) * step + (step - 1) / 2.0)
    gu, gv = np.meshgrid(gx, gy)
    xy_d = np.stack([gu, gv, np.ones_like(gu)], axis=-1) @ np.linalg.inv(K).T
    xy_d = xy_d[..., :2] / xy_d[..., 2:]
    xy_u = cv2.undistortPoints(
        xy_d.reshape(-1, 1, 2), np.eye(3), dist, criteria=_UNDISTORT_CRITERIA
    ).reshape(xy_d.shape)
    f_px = float(max(K[0, 0], K[1, 1]))
    with np.errstate(invalid="ignore", over="ignore"):
        residual_px = np.linalg.norm(distort_normalized(xy_u, dist) - xy_d, axis=-1) * f_px
    bad = ~(residual_px < _LENS_MAX_RESIDUAL_PX)  # NaN counts as bad
    bad |= np.hypot(xy_u[..., 0], xy_u[..., 1]) >= lens_fold_radius(dist)  # other branches
    # Next to a fold the lens squeezes many undistorted pixels into one image pixel: bilinear
    # interpolation is poor there and the footprint explodes, so such cells count as empty.
    with np.errstate(invalid="ignore"):
        sx = np.abs(np.diff(xy_u[..., 0], axis=1)) * (K[0, 0] / step) > _LENS_MAX_STRETCH
        sy = np.abs(np.diff(xy_u[..., 1], axis=0)) * (K[1, 1] / step) > _LENS_MAX_STRETCH
    bad[:, 1:] |= sx
    bad[:, :-1] |= sx
    bad[1:] |= sy
    bad[:-1] |= sy
    xy_u[bad] = 0.0

    def upsample(a: np.ndarray) -> np.ndarray:
        big = cv2.resize(a.astype(np.float32), (len(gx) * step, len(gy) * step),
                         interpolation=cv2.INTER_LINEAR)
        return big[step:step + H, step:step + W]

    x_u, y_u = upsample(xy_u[..., 0]), upsample(xy_u[..., 1])
    if bad.any():
        invalid = upsample(bad.astype(np.float32)) > 0.0  # any bad sample in the cell: empty
        num_invalid = int(np.count_nonzero(invalid))
    else:
        invalid = np.zeros(x_u.shape, bool)
        num_invalid = 0
    if num_invalid == invalid.size:
        raise ValueError(f"camera {camera.camera_id}: no pixel of its lens model is invertible")

    # Internal focal: as fine as the image everywhere (pincushion lenses magnify the edges):
    # the smallest step between neighbouring exact samples, in internal pixels per image pixel.
    fx, fy = float(K[0, 0]), float(K[1, 1])
    step_x = np.abs(np.diff(xy_u[..., 0], axis=1))[~(bad[:, 1:] | bad[:, :-1])] * fx / step
    step_y = np.abs(np.diff(xy_u[..., 1], axis=0))[~(bad[1:] | bad[:-1])] * fy / step
    min_step = min(float(step_x.min(initial=1.0)), float(step_y.min(initial=1.0)))
    scale = min(max(1.0, 1.0 / max(min_step, 1e-6)), 2.0)
    if num_invalid:
        xs, ys = x_u[~invalid], y_u[~invalid]
    else:
        xs, ys = x_u, y_u
    x_lo, x_hi, y_lo, y_hi = float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max())
    pad = _LENS_PAD_PX
    max_w, max_h = min(16384, _MAX_INTERNAL_SCALE * W), min(16384, _MAX_INTERNAL_SCALE * H)
    scale = min(scale, (max_w - 2 * pad - 2) / (fx * (x_hi - x_lo)),
                (max_h - 2 * pad - 2) / (fy * (y_hi - y_lo)))
    fxr, fyr = scale * fx, scale * fy
    # The internal principal point sits a whole number of pixels from the image's: around the
    # image centre (where the lens barely warps) nearest sampling then picks exactly the pixel
    # under each image pixel instead of one shifted by a constant fraction.
    cxr = K[0, 2] + math.ceil(pad - fxr * x_lo - K[0, 2])
    cyr = K[1, 2] + math.ceil(pad - fyr * y_lo - K[1, 2])
    rw = math.ceil(cxr + fxr * x_hi + pad) + 1
    rh = math.ceil(cyr + fyr * y_hi + pad) + 1
    K_render = np.array([[fxr, 0.0, cxr], [0.0, fyr, cyr], [0.0, 0.0, 1.0]])

    map_x = x_u * np.float32(fxr)
    map_x += np.float32(cxr)
    map_y = y_u * np.float32(fyr)
    map_y += np.float32(cyr)
    if num_invalid:
        map_x[invalid] = -100.0  # outside: cv2.remap fills the border (background) colour
        map_y[invalid] = -100.0
    color_maps = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
    nearest_map, _ = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2, nninterpolation=True)
    return LensMap(K_render, (rw, rh), identity=False, color_maps=color_maps,
                   nearest_map=nearest_map, num_without_preimage=num_invalid, K=K.copy(),
                   dist=dist.copy(), fold_radius=lens_fold_radius(dist))



def image_region(lm: LensMap, rect: tuple[int, int, int, int], width: int, height: int
                 ) -> tuple[int, int, int, int] | None:
    """Pixels (x0, y0, x1, y1), inclusive, of the ``width`` x ``height`` image whose value can
    depend on the internal-render pixels ``rect`` (the lens maps them there, bilinear footprint
    included); ``None``: not known, the whole image. (0, 0, -1, -1): none."""
    x0, y0, x1, y1 = rect
    if lm.identity:
        return rect
    # the rectangle's boundary (1 px wider for the bilinear footprint), every 4 px, through
    # the lens: a continuous one-to-one map inside the fold radius takes the rectangle to
    # the region its boundary's image encloses
    xs = np.arange(x0 - 1.0, x1 + 1.0 + 4.0, 4.0)
    ys = np.arange(y0 - 1.0, y1 + 1.0 + 4.0, 4.0)
    xs[-1], ys[-1] = min(xs[-1], x1 + 1.0), min(ys[-1], y1 + 1.0)
    pts = np.concatenate([np.column_stack([xs, np.full_like(xs, y0 - 1.0)]),
                          np.column_stack([xs, np.full_like(xs, ys[-1])]),
                          np.column_stack([np.full_like(ys, x0 - 1.0), ys]),
                          np.column_stack([np.full_like(ys, xs[-1]), ys])])
    Kr = lm.K_render
    xy = np.column_stack([(pts[:, 0] - Kr[0, 2]) / Kr[0, 0],
                          (pts[:, 1] - Kr[1, 2]) / Kr[1, 1]])
    if not float(np.hypot(xy[:, 0], xy[:, 1]).max()) < lm.fold_radius:
        return None
    assert lm.K is not None and lm.dist is not None
    d = distort_normalized(xy, lm.dist)
    K = lm.K
    u = K[0, 0] * d[:, 0] + K[0, 1] * d[:, 1] + K[0, 2]
    v = K[1, 1] * d[:, 1] + K[1, 2]
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(v))):
        return None
    ox0, ox1 = max(0, math.floor(float(u.min())) - 2), min(width - 1,
                                                             math.ceil(float(u.max())) + 2)
    oy0, oy1 = max(0, math.floor(float(v.min())) - 2), min(height - 1,
                                                              math.ceil(float(v.max())) + 2)
    if ox0 > ox1 or oy0 > oy1:
        return (0, 0, -1, -1)
    return (ox0, oy0, ox1, oy1)
