"""The edge's three networks at run time on onnxruntime: the robot detector (with its far
band, :class:`Detector`), the keypoint network (:class:`KeypointEstimator`) and the semantic
segmentation (:class:`SemanticSegmenter`), each decoding its outputs into pixels.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from edge_agent.boxes import box_iou
from edge_agent.crop import crop_transform, extract_crop, resize_for_detector, to_nchw
from edge_agent.far_band import FarBand
from edge_agent.flip import (
    FLIP_MATCH_IOU,
    fuse_flipped_detections,
    mirror_boxes,
    mirror_permutation,
)
from edge_agent.metrics import sigma_from_confidence
from edge_agent.model_cards import (
    DetectorCard,
    KeypointCard,
    ModelError,
    SegmentationCard,
    card_path,
    default_model_dir,
)
from edge_agent.providers import ExecutionProviders, as_execution_providers, check_io, open_session
from protocol.semantic_classes import SEMANTIC_CLASSES

log = logging.getLogger(__name__)


def decode_detections(peaks: np.ndarray, size: np.ndarray, offset: np.ndarray, stride: int,
                      min_score: float = 0.3, max_detections: int = 8) -> np.ndarray:
    """One image's detector outputs (peaks (1, h, w), size (2, h, w), offset (2, h, w)) →
    (n, 5) boxes ``x0, y0, x1, y1`` in input pixels (OpenCV centre convention) and score,
    best first."""
    heat = peaks[0]
    flat = heat.ravel()
    n = min(max_detections, flat.size)
    top = np.argpartition(-flat, n - 1)[:n] if n < flat.size else np.arange(flat.size)
    top = top[flat[top] >= min_score]
    top = top[np.argsort(-flat[top])]
    k, j = np.unravel_index(top, heat.shape)
    cx = (j + offset[0, k, j]) * stride - 0.5
    cy = (k + offset[1, k, j]) * stride - 0.5
    w, h = size[0, k, j], size[1, k, j]
    return np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2, flat[top]], axis=1)


#: far-band sizes whose onnxruntime sessions a :class:`Detector` keeps (each holds its own
#: memory arena): a camera has one band; cameras of many poses (the randomized evaluation)
#: make a session per size, and the least recently used ones are let go
MAX_BAND_SESSIONS: Final = 4


class Detector:
    """The robot detector: full frame → boxes in frame pixels with scores.

    ``flip``: test-time flip augmentation (None: as the card's ``flip_tta`` says): each frame
    also runs mirrored (in the same batch) and the two passes' boxes are fused
    (:func:`fuse_flipped_detections`). It doubles the detector's work (1.5-3.3 ms more per
    frame on two x86 cores, ``smartedge bench edge``); on the paper lab's site cameras it raised
    the pipeline's AP@0.5 from 0.79-0.86 to 0.87-0.88, and the detector's boxes on views without
    a robot fell from 0.22-0.51 to 0.01 of them (docs/models.md).

    A frame given a :class:`~edge_agent.far_band.FarBand` also runs the band's rows at the
    band's scale (one run per band for all its frames, no flip) and those boxes join the whole
    frame's (:func:`merge_far_band_boxes`). That needs a file whose input height and width are
    free (named) dimensions, as ``smartedge train detector`` exports them; a file with a fixed
    input size runs without its far band (logged once, :attr:`runs_far_band`)."""

    def __init__(self, onnx_path: Path | str, *, threads: int = 2,
                 providers: ExecutionProviders | Sequence[Any] | None = None,
                 spinning: bool = False, flip: bool | None = None) -> None:
        self.path = Path(onnx_path)
        if not self.path.is_file():
            raise ModelError(f"{self.path}: detector model file not found")
        self.card = DetectorCard.read(card_path(self.path))
        self.flip = self.card.flip_tta if flip is None else bool(flip)
        self._session_args = (threads, providers, spinning)
        self.session = open_session(self.path, threads, providers, spinning)
        shape = list(self.session.get_inputs()[0].shape)
        #: the file's names of its input's height and width, when they are free (else None)
        self.spatial_dims: tuple[str, str] | None = (
            (shape[2], shape[3]) if len(shape) == 4 and all(isinstance(d, str)
                                                            for d in shape[2:]) else None)
        if self.spatial_dims:  # the whole frame's session at the card's size, fixed
            self.session = self._session_at(self.card.input_h, self.card.input_w)
        self._band_sessions: dict[tuple[int, int], Any] = {}
        self._warned_band = False
        #: boxes the far band found that the whole frame did not, since start
        self.far_band_added = 0
        #: the execution providers the session runs on (``get_providers()``)
        self.providers_used: list[str] = list(self.session.get_providers())
        check_io(self.path, self.session, [("image", (3, self.card.input_h, self.card.input_w))],
                  ["peaks", "size", "offset"])

    @property
    def runs_far_band(self) -> bool:
        """Whether the file's input size is free, so that a far band can run."""
        return self.spatial_dims is not None

    def _session_at(self, input_h: int, input_w: int) -> Any:
        assert self.spatial_dims is not None
        threads, providers, spinning = self._session_args
        return open_session(self.path, threads, providers, spinning,
                        dims={self.spatial_dims[0]: input_h, self.spatial_dims[1]: input_w})

    def detect(self, image_rgb: np.ndarray, min_score: float = 0.3,
               max_detections: int = 8, far_band: FarBand | None = None) -> np.ndarray:
        """(n, 5) ``x0, y0, x1, y1, score`` in the frame's pixels, best first."""
        return self.detect_many([image_rgb], min_score, max_detections, [far_band])[0]

    def detect_many(self, images_rgb: Sequence[np.ndarray], min_score: float = 0.3,
                    max_detections: int = 8,
                    far_bands: Sequence[FarBand | None] | None = None) -> list[np.ndarray]:
        """:meth:`detect` of several frames (any sizes) in one network run (a batch);
        ``far_bands``: each frame's far band (None: none), a band applying only to frames of
        the size it was computed for."""
        c = self.card
        if not images_rgb:
            return []
        x = to_nchw(np.stack([resize_for_detector(im, c.input_w, c.input_h)
                              for im in images_rgb]))
        n = len(images_rgb)
        if self.flip:
            x = np.concatenate([x, x[..., ::-1]])  # the mirror images, as a batch after
        peaks, size, offset = self.session.run(None, {"image": x})
        out = []
        for i, image_rgb in enumerate(images_rgb):
            h, w = image_rgb.shape[:2]
            if self.flip:
                # each pass down to half the floor: a robot the other pass scores low is one
                # cluster, not a lone half-score box
                floor = min_score / 2.0
                direct = decode_detections(peaks[i], size[i], offset[i], c.stride, floor,
                                           2 * max_detections)
                mirrored = mirror_boxes(decode_detections(
                    peaks[n + i], size[n + i], offset[n + i], c.stride, floor,
                    2 * max_detections), c.input_w)
                boxes = fuse_flipped_detections(direct, mirrored, min_score, max_detections)
            else:
                boxes = decode_detections(peaks[i], size[i], offset[i], c.stride, min_score,
                                          max_detections)
            s = np.array([w / c.input_w, h / c.input_h] * 2)
            boxes[:, :4] = (boxes[:, :4] + 0.5) * s - 0.5
            out.append(boxes)
        if far_bands is not None and any(b is not None for b in far_bands):
            if len(far_bands) != n:
                raise ValueError(f"{len(far_bands)} far bands for {n} frames")
            self._add_far_bands(images_rgb, far_bands, out, min_score, max_detections)
        return out

    def _add_far_bands(self, images_rgb: Sequence[np.ndarray],
                       far_bands: Sequence[FarBand | None], out: list[np.ndarray],
                       min_score: float, max_detections: int) -> None:
        """Each far band's frames through the detector at the band's size (one batch per
        band), their boxes merged into ``out``."""
        if not self.runs_far_band:
            if not self._warned_band:
                log.warning("%s has a fixed input size: the far band does not run (export the "
                            "detector again with `smartedge train detector`, whose files have "
                            "a free input size)", self.path)
                self._warned_band = True
            return
        groups: dict[FarBand, list[int]] = {}
        for i, (image_rgb, band) in enumerate(zip(images_rgb, far_bands, strict=True)):
            h, w = image_rgb.shape[:2]
            if band is not None and band.applies_to(w, h):
                groups.setdefault(band, []).append(i)
        for band, index in groups.items():
            key = (band.input_h, band.input_w)
            session = self._band_sessions.pop(key, None) or self._session_at(*key)
            self._band_sessions[key] = session  # the most recently used last
            while len(self._band_sessions) > MAX_BAND_SESSIONS:
                self._band_sessions.pop(next(iter(self._band_sessions)))
            x = to_nchw(np.stack([resize_for_detector(images_rgb[i][band.v0:band.v1],
                                                      band.input_w, band.input_h)
                                  for i in index]))
            peaks, size, offset = session.run(None, {"image": x})
            for j, i in enumerate(index):
                boxes = decode_detections(peaks[j], size[j], offset[j], self.card.stride,
                                          min_score, max_detections)
                found = far_band_to_frame(boxes, band)
                out[i], added = merge_far_band_boxes(out[i], found, max_detections)
                self.far_band_added += added


#: a far-band box whose top lies this close to the band's upper edge (frame pixels), or whose
#: bottom lies this far below the lowest row of a far robot's feet, is a robot the band cuts:
#: the whole frame's
FAR_BAND_EDGE_PX: Final = 4.0


def far_band_to_frame(boxes: np.ndarray, band: FarBand) -> np.ndarray:
    """(n, 5) boxes in the far band's input pixels → those in frame pixels, less the boxes the
    band cuts: reaching up to its upper edge (where that is not the frame's), or down below the
    rows of a far robot's feet (``FarBand.feet_max_v``: a nearer robot, cut by the band's lower
    edge)."""
    out = boxes.copy()
    sx = band.frame_w / band.input_w
    sy = (band.v1 - band.v0) / band.input_h
    out[:, [0, 2]] = (boxes[:, [0, 2]] + 0.5) * sx - 0.5
    out[:, [1, 3]] = (boxes[:, [1, 3]] + 0.5) * sy - 0.5 + band.v0
    keep = out[:, 3] <= float(band.feet_max_v or band.v1) + FAR_BAND_EDGE_PX
    if band.v0 > 0:
        keep &= out[:, 1] > band.v0 - 0.5 + FAR_BAND_EDGE_PX
    return out[keep]


def merge_far_band_boxes(whole: np.ndarray, band: np.ndarray, max_detections: int,
                         iou: float = FLIP_MATCH_IOU) -> tuple[np.ndarray, int]:
    """The whole frame's boxes and the far band's (both (n, 5) in frame pixels, best first) →
    one list, best first, and how many boxes the band added. A band box on a robot the whole
    frame found (IoU >= ``iou`` with its box) makes one box with it: the score-weighted mean
    of the two boxes, scored as the higher of the two (the band sees the robot at twice the
    resolution; neither box is consistently the better one). A band box on no whole-frame
    box is added."""
    out = [row.copy() for row in whole.reshape(-1, 5)]
    matched = np.zeros(len(out), bool)
    added = 0
    for row in band.reshape(-1, 5):
        ious = [box_iou(row[:4], w[:4]) for w in out]
        j = int(np.argmax(ious)) if ious else -1
        if j >= 0 and ious[j] >= iou:
            if j < len(matched) and not matched[j]:  # one band box per whole-frame box
                w = out[j]
                weights = np.array([w[4], row[4]])
                box = (w[:4] * weights[0] + row[:4] * weights[1]) / weights.sum()
                out[j] = np.append(box, weights.max())
                matched[j] = True
            continue
        out.append(row.copy())
        added += 1
    merged = np.array(out).reshape(-1, 5)
    order = np.argsort(-merged[:, 4], kind="stable")[:max_detections]
    return merged[order], added


class KeypointEstimator:
    """The keypoint network: crops around boxes → keypoints in frame pixels + confidences.

    ``flip``: test-time flip augmentation (None: as the card's ``flip_tta`` says): each crop
    also runs mirrored (one batch of two), the mirrored result is mapped back
    (``u -> w - 1 - u``, each keypoint to its left/right partner, :func:`mirror_permutation`)
    and averaged with the direct one. It doubles the network's work; the result is exactly
    mirror-consistent (the estimate on a mirrored frame is the mirrored estimate)."""

    def __init__(self, onnx_path: Path | str, *, threads: int = 2,
                 providers: ExecutionProviders | Sequence[Any] | None = None,
                 spinning: bool = False, flip: bool | None = None) -> None:
        self.path = Path(onnx_path)
        if not self.path.is_file():
            raise ModelError(f"{self.path}: keypoint model file not found")
        self.card = KeypointCard.read(card_path(self.path))
        flip = self.card.flip_tta if flip is None else flip
        self.flip = flip
        self._mirror = mirror_permutation(self.card.keypoint_names) if flip else None
        self.session = open_session(self.path, threads, providers, spinning)
        self.providers_used: list[str] = list(self.session.get_providers())
        check_io(self.path, self.session, [("crop", (3, self.card.input_h, self.card.input_w))],
                  ["keypoints", "confidence"])

    @property
    def num_keypoints(self) -> int:
        return len(self.card.keypoint_names)

    @property
    def calibrated(self) -> bool:
        """Whether the card maps confidences to pixel sigmas."""
        return bool(self.card.sigma_calibration.get("confidence"))

    def estimate(self, image_rgb: np.ndarray, boxes_xyxy: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(n, K, 2) keypoints in frame pixels and (n, K) confidences for (n, 4) boxes."""
        kp, conf, _ = self.estimate_with_sigma(image_rgb, boxes_xyxy)
        return kp, conf

    def estimate_with_sigma(self, image_rgb: np.ndarray, boxes_xyxy: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """As :meth:`estimate`, plus (n, K) 1-sigma keypoint errors in frame pixels from the
        card's calibration (``None`` when the card has none)."""
        return self.estimate_many([image_rgb], [boxes_xyxy])[0]

    def estimate_many(self, images_rgb: Sequence[np.ndarray], boxes_xyxy: Sequence[np.ndarray]
                      ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]:
        """:meth:`estimate_with_sigma` of several frames, each with its (n_i, 4) boxes: the
        crops of all frames in one network run (a batch)."""
        c = self.card
        k = self.num_keypoints
        tfs = [[crop_transform(b[:4], c.input_w, c.input_h, padding=c.crop_padding)
                for b in boxes] for boxes in boxes_xyxy]
        crops = [extract_crop(image_rgb, tf, c.input_w, c.input_h)
                 for image_rgb, frame_tfs in zip(images_rgb, tfs, strict=True)
                 for tf in frame_tfs]
        if crops:
            kp_all, conf_all = self._run(np.stack(crops))
        out: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        start = 0
        for frame_tfs in tfs:
            n = len(frame_tfs)
            if n == 0:
                out.append((np.zeros((0, k, 2)), np.zeros((0, k)),
                            np.zeros((0, k)) if self.calibrated else None))
                continue
            kp, conf = kp_all[start:start + n], conf_all[start:start + n]
            start += n
            kp_img = np.stack([tf.to_image(p) for tf, p in zip(frame_tfs, kp, strict=True)])
            conf = conf.astype(np.float64)
            sigma_crop = sigma_from_confidence(conf, c.sigma_calibration)
            if sigma_crop is None:
                out.append((kp_img, conf, None))
                continue
            scales = np.array([tf.scale for tf in frame_tfs])[:, None]  # crop px per image px
            out.append((kp_img, conf, sigma_crop / scales))
        return out

    def _run(self, crops: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, K, 2) crop-pixel keypoints and (n, K) confidences of (n, h, w, 3) crops."""
        if self._mirror is None:
            kp, conf = self.session.run(None, {"crop": to_nchw(crops)})
            return kp, conf
        n = len(crops)
        kp, conf = self.session.run(None, {"crop": to_nchw(np.concatenate(
            [crops, crops[:, :, ::-1]]))})
        kp_m = kp[n:][:, self._mirror].astype(np.float64)
        kp_m[..., 0] = self.card.input_w - 1 - kp_m[..., 0]
        conf_m = conf[n:][:, self._mirror]
        return (kp[:n] + kp_m) / 2.0, (conf[:n] + conf_m) / 2.0


@dataclasses.dataclass(frozen=True)
class RobotObservation:
    """One detected robot: ``bbox_xyxy`` and ``score`` from the detector, ``keypoints_px``
    (K, 2) raw frame pixels, ``confidence`` (K,), ``sigma_px`` (K,) calibrated 1-sigma errors
    in frame pixels (``None``: the keypoint model's card has no calibration); ``robot_model``:
    the site's robot model whose networks saw it (``""``: not known)."""

    bbox_xyxy: np.ndarray
    score: float
    keypoints_px: np.ndarray
    confidence: np.ndarray
    sigma_px: np.ndarray | None = None
    robot_model: str = ""


@dataclasses.dataclass
class StageTimes:
    detector_ms: float = 0.0
    keypoints_ms: float = 0.0


@dataclasses.dataclass(frozen=True)
class Segmentation:
    """One segmented image. ``class_ids`` (h, w) uint8 ids of
    :data:`protocol.semantic_classes.SEMANTIC_CLASSES`; ``confidence`` (h, w) float32 in
    [0, 1], the softmax probability of that class; ``image_width`` x ``image_height`` (W, H):
    the image that was segmented. Output pixel ``(i, j)`` covers the image pixel centre
    ``((j + 0.5) * W / w - 0.5, (i + 0.5) * H / h - 0.5)`` (OpenCV convention: pixel centres
    at integer coordinates); ``infer_ms``: resize + network, milliseconds."""

    class_ids: np.ndarray
    confidence: np.ndarray
    image_width: int
    image_height: int
    infer_ms: float

    def image_pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """(h, w) image x and y (pixels, OpenCV convention) of every output pixel's centre."""
        h, w = self.class_ids.shape
        x = (np.arange(w) + 0.5) * (self.image_width / w) - 0.5
        y = (np.arange(h) + 0.5) * (self.image_height / h) - 0.5
        return np.broadcast_to(x[None], (h, w)), np.broadcast_to(y[:, None], (h, w))


class SemanticSegmenter:
    """The segmentation network: a whole frame → per-pixel classes and confidences.

    ``onnx_path``: the model (its :class:`SegmentationCard` beside it); ``None``: the shipped
    ``edge_agent/models/segmentation.onnx``. ``threads``: onnxruntime intra-op threads;
    ``providers``: execution providers in order of preference (default CPU; names or an
    :class:`ExecutionProviders`, the same the detector gets). A missing, corrupt
    or truncated model, a missing or wrong card, a card whose classes are not
    :data:`protocol.semantic_classes.SEMANTIC_CLASSES` and a graph whose input or output size is
    not the card's raise :class:`ModelError` naming the file."""

    def __init__(self, onnx_path: Path | str | None = None, *, threads: int = 2,
                 providers: ExecutionProviders | Sequence[Any] | None = None) -> None:
        self.path = Path(onnx_path) if onnx_path is not None else (
            default_model_dir() / "segmentation.onnx")
        if not self.path.is_file():
            raise ModelError(f"{self.path}: segmentation model file not found")
        card = SegmentationCard.read(card_path(self.path))
        if list(card.classes) != list(SEMANTIC_CLASSES):
            raise ModelError(f"{card_path(self.path)}: the model's classes {card.classes} are not "
                             f"smartedge's legend {list(SEMANTIC_CLASSES)} "
                             "(protocol.semantic_classes); retrain it")
        self.card = card
        self.execution = as_execution_providers(providers)
        self.session = open_session(self.path, threads, self.execution)
        self.providers_used: list[str] = list(self.session.get_providers())
        check_io(self.path, self.session, [("image", (3, card.input_h, card.input_w))],
                  ["class_ids", "confidence"])
        for out in self.session.get_outputs():
            if tuple(out.shape[1:]) != (card.output_h, card.output_w):
                raise ModelError(f"{self.path}: output {out.name} of shape {out.shape[1:]}, the "
                                 f"card says {card.output_h}x{card.output_w} (h x w)")

    @property
    def model_id(self) -> str:
        """Which model this is (provenance): ``segmentation/<its folder's name>``."""
        return f"{self.card.KIND}/{self.path.parent.name}"

    def __call__(self, image_rgb: np.ndarray) -> Segmentation:
        """Segment an (H, W, 3) uint8 RGB image of any size (resized to the network's input
        inside); raises ``ValueError`` for anything else."""
        if (not isinstance(image_rgb, np.ndarray) or image_rgb.ndim != 3
                or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8
                or min(image_rgb.shape[:2]) < 1):
            got = (f"{image_rgb.shape} {image_rgb.dtype}" if isinstance(image_rgb, np.ndarray)
                   else type(image_rgb).__name__)
            raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {got}")
        c = self.card
        h, w = image_rgb.shape[:2]
        t0 = time.perf_counter()
        x = to_nchw(resize_for_detector(image_rgb, c.input_w, c.input_h))
        class_ids, confidence = self.session.run(None, {"image": x})
        infer_ms = (time.perf_counter() - t0) * 1e3
        return Segmentation(class_ids[0].astype(np.uint8, copy=False),
                            np.clip(confidence[0], 0.0, 1.0).astype(np.float32, copy=False),
                            int(w), int(h), infer_ms)
