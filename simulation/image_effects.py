"""Image-space effects of the rendered samples: what the camera does to an image (vignetting,
defocus and motion blur, exposure, white balance, gamma, saturation, sensor noise, JPEG;
:func:`camera_effects`), what the scene adds around the robot (its shadow and dirt;
:func:`scene_effects`), and the training-time photometric augmentation (:func:`augment`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from core.camera import CameraModel
from simulation.mesh import CLASS_ID
from simulation.scenes import (
    ROBOT_INSTANCE,
    RandomizationConfig,
    shadow_polygon_world,
)


def augment(image_rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Colour jitter (contrast, brightness, white balance, saturation), blur, sensor noise and
    JPEG compression of an (H, W, 3) uint8 RGB image; labels are unaffected. uint8 OpenCV
    operations on contiguous images throughout (3-5 ms at 848x480, most of it the Gaussian noise
    draw); the same ``rng`` state gives the same image."""
    import cv2

    gain = rng.uniform(0.6, 1.4) * rng.uniform(0.85, 1.15, 3)  # contrast x white balance
    bias = rng.uniform(-30, 30)
    lut = np.clip(np.arange(256)[:, None] * gain + bias, 0, 255).astype(np.uint8)
    img = cv2.LUT(image_rgb, lut.reshape(256, 1, 3))
    sat = rng.uniform(0.5, 1.5)
    gray = cv2.cvtColor(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)
    img = cv2.addWeighted(img, sat, gray, 1.0 - sat, 0.0)
    if rng.uniform() < 0.3:
        k = int(rng.choice([3, 5]))
        img = cv2.GaussianBlur(img, (k, k), 0)
    sigma = rng.uniform(0, 8)
    if sigma > 0.5:
        noise = np.empty(img.shape, np.int16)
        cv2.setRNGSeed(int(rng.integers(2**31)))  # OpenCV's generator, seeded from ours
        cv2.randn(noise, 0, sigma)
        img = cv2.add(img, noise, dtype=cv2.CV_8U)  # saturating: clip(img + noise, 0, 255)
    if rng.uniform() < 0.6:
        # colour conversions instead of [..., ::-1] views: the codec would copy a strided
        # image pixel by pixel
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(40, 96))])
        if ok:
            img = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(img)


def _vignetting_gain(width: int, height: int, strength: float, rng: np.random.Generator,
                     ) -> np.ndarray:
    """(H, W, 3) uint8 gain (255 = 1) falling off as ``1 - strength * r^2`` to the corners,
    about an optical centre a little off the image centre (built at 1/8 resolution and
    resized: smooth)."""
    import cv2

    w8, h8 = max(2, width // 8), max(2, height // 8)
    cx, cy = 0.5 + rng.normal(0, 0.04, 2)
    y, x = np.mgrid[0:h8, 0:w8]
    dx = (x + 0.5) / w8 - cx
    dy = ((y + 0.5) / h8 - cy) * (height / width)
    r2 = (dx * dx + dy * dy) / (0.25 * (1 + (height / width) ** 2))
    g = np.clip(255.0 * (1.0 - strength * r2), 0, 255).astype(np.uint8)
    return cv2.resize(np.repeat(g[..., None], 3, axis=2), (width, height),
                      interpolation=cv2.INTER_LINEAR)


def _disk_kernel(radius_px: float) -> np.ndarray:
    """A normalized disk (defocus) kernel with an anti-aliased rim."""
    n = math.ceil(radius_px)
    y, x = np.mgrid[-n:n + 1, -n:n + 1]
    k = np.clip(radius_px + 0.5 - np.hypot(x, y), 0.0, 1.0).astype(np.float32)
    return _trimmed(k)


def _trimmed(kernel: np.ndarray) -> np.ndarray:
    """``kernel`` without its all-zero border rows and columns, normalized to sum 1 (kept odd
    and centred: trimmed symmetrically)."""
    n = kernel.shape[0] // 2
    used = np.flatnonzero(kernel.any(axis=0) | kernel.any(axis=1))
    m = max(int(np.max(np.abs(used - n))), 0) if len(used) else 0
    k = kernel[n - m:n + m + 1, n - m:n + m + 1]
    return k / max(float(k.sum()), 1e-6)


def _line_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    """A normalized straight motion-blur kernel of ``length_px`` at ``angle_rad``."""
    import cv2

    n = math.ceil(length_px / 2)
    k = np.zeros((2 * n + 1, 2 * n + 1), np.float32)
    d = 0.5 * (length_px - 1) * np.array([math.cos(angle_rad), math.sin(angle_rad)])
    p0 = np.round((n - d) * 16).astype(int)
    p1 = np.round((n + d) * 16).astype(int)
    cv2.line(k, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), 1.0, 1, cv2.LINE_AA,
             shift=4)
    return _trimmed(k)


def camera_effects(image_rgb: np.ndarray, rng: np.random.Generator,
                   config: RandomizationConfig | None = None) -> np.ndarray:
    """What a real camera does to an (H, W, 3) uint8 RGB image, drawn from ``config``
    (:class:`simulation.scenes.RandomizationConfig`): the lens (vignetting, defocus, motion
    blur), the sensor (exposure, Gaussian noise), the image processing (white balance, gamma,
    saturation) and JPEG compression. Labels are unaffected (blur and noise do not move
    anything). uint8 OpenCV operations throughout; the same ``rng`` state gives the same
    image."""
    import cv2

    cfg = config or RandomizationConfig()
    h, w = image_rgb.shape[:2]
    img = image_rgb
    if rng.uniform() < cfg.vignetting_probability:
        gain = _vignetting_gain(w, h, float(rng.uniform(*cfg.vignetting)), rng)
        img = cv2.multiply(img, gain, scale=1.0 / 255.0)
    if rng.uniform() < cfg.defocus_probability:
        img = cv2.filter2D(img, -1, _disk_kernel(float(rng.uniform(*cfg.defocus_px))))
    if rng.uniform() < cfg.motion_blur_probability:
        img = cv2.filter2D(img, -1, _line_kernel(float(rng.uniform(*cfg.motion_blur_px)),
                                                 float(rng.uniform(0, np.pi))))
    # exposure x white balance, then the tone curve: one lookup table per channel
    gain3 = 2.0 ** rng.uniform(*cfg.exposure_ev) * rng.uniform(*cfg.white_balance, 3)
    gamma = float(rng.uniform(*cfg.gamma))
    levels = np.clip(np.arange(256)[:, None] / 255.0 * gain3, 0.0, 1.0) ** (1.0 / gamma)
    offset = float(rng.uniform(*cfg.brightness_offset))
    lut = np.clip(np.round(255.0 * levels + offset), 0, 255).astype(np.uint8)
    img = cv2.LUT(np.ascontiguousarray(img), lut.reshape(256, 1, 3))
    sat = float(rng.uniform(*cfg.saturation))
    gray = cv2.cvtColor(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)
    img = cv2.addWeighted(img, sat, gray, 1.0 - sat, 0.0)
    sigma = float(rng.uniform(*cfg.noise_sigma))
    if sigma > 0.5:
        noise = np.empty(img.shape, np.int16)
        cv2.setRNGSeed(int(rng.integers(2**31)))  # OpenCV's generator, seeded from ours
        cv2.randn(noise, 0, sigma)
        img = cv2.add(img, noise, dtype=cv2.CV_8U)
    if rng.uniform() < cfg.jpeg_probability:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY,
                                int(rng.integers(cfg.jpeg_quality[0], cfg.jpeg_quality[1] + 1))])
        if ok:
            img = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(img)


def scene_effects(image_rgb: np.ndarray, class_id: np.ndarray, instance_id: np.ndarray,
                  camera: CameraModel, scene: Any, robot_pose: np.ndarray, model: Any,
                  robot_bbox_xyxy: np.ndarray | None, rng: np.random.Generator,
                  config: RandomizationConfig | None = None) -> np.ndarray:
    """Shading the renderer does not do, in image space and only near the robot: its contact
    and cast shadow on the floor (:func:`simulation.scenes.shadow_polygon_world`, darkening
    only floor pixels, soft-edged) and dirt and wear patches on its visible pixels. Returns
    the image (a new array where changed)."""
    import cv2

    cfg = config or RandomizationConfig()
    h, w = image_rgb.shape[:2]
    img = image_rgb
    if rng.uniform() < cfg.shadow_probability:
        strength = float(rng.uniform(*cfg.shadow_strength))
        poly = shadow_polygon_world(robot_pose, model, scene.light_dir_world)
        uv, z = camera.project(poly)
        if np.all(z > 0.2) and np.all(np.isfinite(uv)) and np.all(np.abs(uv) < 4 * (w + h)):
            hull = cv2.convexHull(uv.astype(np.float32))[:, 0]
            soft = max(1.5, 0.06 * float(np.ptp(hull[:, 1])))
            pad = int(3 * soft) + 1
            x0, y0 = (max(0, int(v) - pad) for v in hull.min(axis=0))
            x1, y1 = (min(m, int(v) + pad + 1) for m, v in zip((w, h), hull.max(axis=0),
                                                                 strict=True))
            if x1 > x0 and y1 > y0:
                # drawn and blurred at 1/4 resolution (a soft shadow has no fine detail), then
                # applied as an 8-bit gain on the floor pixels
                q = 4
                small = np.zeros(((y1 - y0 + q - 1) // q, (x1 - x0 + q - 1) // q), np.float32)
                pts = np.round((hull - [x0 + 0.5 * q - 0.5, y0 + 0.5 * q - 0.5]) * (16 / q))
                cv2.fillConvexPoly(small, pts.astype(np.int32), 1.0, cv2.LINE_AA, shift=4)
                small = cv2.GaussianBlur(small, (0, 0), max(0.5, soft / q))
                mask = cv2.resize(small, (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR)
                mask *= class_id[y0:y1, x0:x1] == CLASS_ID["floor"]
                gain = np.clip(255.0 * (1.0 - strength * mask), 0, 255).astype(np.uint8)
                img = img.copy()
                roi = img[y0:y1, x0:x1]
                cv2.multiply(roi, cv2.cvtColor(gain, cv2.COLOR_GRAY2RGB), dst=roi,
                             scale=1.0 / 255.0)
    if robot_bbox_xyxy is not None and rng.uniform() < cfg.dirt_probability:
        x0, y0 = (max(0, int(v)) for v in robot_bbox_xyxy[:2])
        x1, y1 = min(w, int(robot_bbox_xyxy[2]) + 1), min(h, int(robot_bbox_xyxy[3]) + 1)
        if x1 - x0 >= 2 and y1 - y0 >= 2:
            grid = rng.uniform(0, 1, (int(rng.integers(3, 9)),) * 2).astype(np.float32)
            patches = cv2.resize(grid, (x1 - x0, y1 - y0), interpolation=cv2.INTER_CUBIC)
            cover = np.clip((patches - rng.uniform(0.45, 0.75)) / 0.15, 0.0, 1.0)
            cover *= float(rng.uniform(0.3, 0.7)) * (instance_id[y0:y1, x0:x1] == ROBOT_INSTANCE)
            dirt = (rng.uniform(0.15, 0.45) * np.array([1.0, 0.9, 0.75]) * 255.0).astype(
                np.float32)
            if img is image_rgb:
                img = img.copy()
            roi = img[y0:y1, x0:x1]
            a = cover[..., None]
            roi[...] = np.clip(roi * (1.0 - a) + dirt * a, 0, 255).astype(np.uint8)
    return img
