"""Image geometry shared by training and inference (numpy + OpenCV, no torch, no onnxruntime).

The detector sees the whole frame resized to its input size; the keypoint network sees a crop
around each detected box, resized to a fixed size with the network's aspect ratio. Training
builds its inputs with exactly these functions, so the deployed pipeline feeds the networks
what they were trained on.

Pixel convention: OpenCV's (pixel centres at integer coordinates, ``(0, 0)`` the centre of the
top-left pixel), the same as the keypoint labels and ``cv2.projectPoints``.
"""

from __future__ import annotations

import dataclasses
from typing import Final

import numpy as np

#: the crop box is the detected box enlarged by this factor (context for occluded keypoints)
CROP_PADDING: Final = 1.25


@dataclasses.dataclass(frozen=True)
class CropTransform:
    """An axis-aligned crop: ``crop_px = (image_px - origin_px) * scale``."""

    origin_px: np.ndarray  # (2,) image pixel that maps to crop pixel (0, 0)
    scale: float  # crop pixels per image pixel

    def to_image(self, crop_px: np.ndarray) -> np.ndarray:
        """(..., 2) crop pixels → image pixels."""
        return np.asarray(crop_px, np.float64) / self.scale + self.origin_px

    def to_crop(self, image_px: np.ndarray) -> np.ndarray:
        """(..., 2) image pixels → crop pixels."""
        return (np.asarray(image_px, np.float64) - self.origin_px) * self.scale

    def matrix(self) -> np.ndarray:
        """(2, 3) affine image → crop for ``cv2.warpAffine``."""
        s = self.scale
        return np.array([[s, 0.0, -s * self.origin_px[0]], [0.0, s, -s * self.origin_px[1]]])


def crop_box(bbox_xyxy: np.ndarray, crop_w: int, crop_h: int, *,
             padding: float = CROP_PADDING, shift: tuple[float, float] = (0.0, 0.0),
             zoom: float = 1.0) -> tuple[np.ndarray, float]:
    """Centre (2,) and height (image pixels) of the crop window for a box: the box enlarged by
    ``padding``, widened to the crop's aspect ratio. ``shift`` (fractions of the window size) and
    ``zoom`` (>1: a larger window) jitter it for training."""
    x0, y0, x1, y1 = (float(v) for v in bbox_xyxy)
    centre = np.array([(x0 + x1) / 2.0, (y0 + y1) / 2.0])
    w, h = max(x1 - x0, 1.0), max(y1 - y0, 1.0)
    height = max(h, w * crop_h / crop_w) * padding * zoom
    width = height * crop_w / crop_h
    centre = centre + np.array([shift[0] * width, shift[1] * height])
    return centre, height


def crop_transform(bbox_xyxy: np.ndarray, crop_w: int, crop_h: int,
                   **jitter: float | tuple[float, float]) -> CropTransform:
    """The :class:`CropTransform` of :func:`crop_box` (same keyword jitter)."""
    centre, height = crop_box(bbox_xyxy, crop_w, crop_h, **jitter)  # type: ignore[arg-type]
    scale = crop_h / height
    # crop pixel centre (crop_w - 1) / 2 sits on the window centre
    origin = centre - np.array([(crop_w - 1) / 2.0, (crop_h - 1) / 2.0]) / scale
    return CropTransform(origin, float(scale))


def extract_crop(image_rgb: np.ndarray, transform: CropTransform, crop_w: int, crop_h: int
                 ) -> np.ndarray:
    """(crop_h, crop_w, 3) uint8 crop of ``image_rgb``; outside the image is black."""
    import cv2

    # bilinear (warpAffine has no area averaging; training crops are made the same way)
    return cv2.warpAffine(image_rgb, transform.matrix(), (crop_w, crop_h),
                          flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))


def resize_for_detector(image_rgb: np.ndarray, input_w: int, input_h: int) -> np.ndarray:
    """The frame resized to the detector's input (area interpolation when shrinking)."""
    import cv2

    h, w = image_rgb.shape[:2]
    if (w, h) == (input_w, input_h):
        return image_rgb
    interp = cv2.INTER_AREA if input_w < w else cv2.INTER_LINEAR
    return cv2.resize(image_rgb, (input_w, input_h), interpolation=interp)


def downscale_labels(class_id: np.ndarray, out_w: int, out_h: int) -> np.ndarray:
    """(H, W) integer class image → (out_h, out_w) uint8 by nearest neighbour: output pixel
    ``(i, j)`` takes the image pixel nearest to its centre ``((j + 0.5) * W / out_w - 0.5,
    (i + 0.5) * H / out_h - 0.5)`` (the segmentation network's output convention)."""
    import cv2

    labels = np.asarray(class_id)
    if labels.ndim != 2:
        raise ValueError(f"expected an (H, W) class image, got shape {labels.shape}")
    h, w = labels.shape
    if (w, h) == (out_w, out_h):
        return labels.astype(np.uint8)
    # INTER_NEAREST_EXACT samples floor((j + 0.5) * W / out_w): the pixel holding that centre
    return cv2.resize(labels.astype(np.uint8), (out_w, out_h),
                      interpolation=cv2.INTER_NEAREST_EXACT)


def to_nchw(images_rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) or (N, H, W, 3) uint8 → (N, 3, H, W) float32 in [0, 1] (the models' input;
    they normalise inside the graph)."""
    x = np.asarray(images_rgb)
    if x.ndim == 3:
        x = x[None]
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2), dtype=np.float32) * np.float32(1 / 255)
