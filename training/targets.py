"""What the networks are trained towards: the detector's heat-map targets and focal loss, the
keypoint network's SimCC targets and per-keypoint weights, the segmentation's class weights, the
mirrored crops of the flip augmentation and the photometric jitter (torch, no training loop).
"""

from __future__ import annotations

import numpy as np
import torch


def frame_to_input(box: np.ndarray, frame_size: np.ndarray, w: int, h: int) -> np.ndarray:
    """Box edges (..., 4) in frame pixels → detector-input pixels (edges scale exactly)."""
    s = np.array([w, h, w, h]) / np.concatenate([frame_size, frame_size], -1)
    return (box + 0.5) * s - 0.5


def detector_targets(boxes_in: np.ndarray, out_w: int, out_h: int, stride: int
                     ) -> tuple[np.ndarray, ...]:
    """Per image (B, 4) input-pixel boxes (NaN row: no robot) → heat (B, 1, h, w), log-size
    and offset (B, 2, h, w) targets and their mask (B, 1, h, w)."""
    b = len(boxes_in)
    heat = np.zeros((b, 1, out_h, out_w), np.float32)
    size = np.zeros((b, 2, out_h, out_w), np.float32)
    off = np.zeros((b, 2, out_h, out_w), np.float32)
    mask = np.zeros((b, 1, out_h, out_w), np.float32)
    gx, gy = np.arange(out_w) + 0.5, np.arange(out_h) + 0.5
    for i, box in enumerate(boxes_in):
        if not np.all(np.isfinite(box)):
            continue
        # edge coordinates (0 = the image's left edge) in output cells
        x0, y0, x1, y1 = (box + 0.5) / stride
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        j = int(np.clip(np.floor(cx), 0, out_w - 1))
        k = int(np.clip(np.floor(cy), 0, out_h - 1))
        sx, sy = max(0.8, (x1 - x0) / 6), max(0.8, (y1 - y0) / 6)
        g = np.exp(-((gx[None] - cx) ** 2) / (2 * sx * sx)
                   - ((gy[:, None] - cy) ** 2) / (2 * sy * sy))
        heat[i, 0] = np.maximum(heat[i, 0], g)
        heat[i, 0, k, j] = 1.0
        w_px, h_px = (x1 - x0) * stride, (y1 - y0) * stride
        size[i, :, k, j] = np.log(max(w_px, 1.0)), np.log(max(h_px, 1.0))
        off[i, :, k, j] = cx - j, cy - k
        mask[i, 0, k, j] = 1.0
    return heat, size, off, mask


def focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss, normalised by the number of centres."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = target.eq(1).float()
    pos_loss = -torch.log(p) * (1 - p) ** 2 * pos
    neg_loss = -torch.log(1 - p) * p ** 2 * (1 - target) ** 4 * (1 - pos)
    return (pos_loss.sum() + neg_loss.sum()) / pos.sum().clamp_min(1.0)


def simcc_targets(kp_px: torch.Tensor, bins: int, split: int, sigma_px: float) -> torch.Tensor:
    """(B, K) pixel coordinates → (B, K, bins) Gaussian label distributions."""
    centres = torch.arange(bins, dtype=kp_px.dtype, device=kp_px.device) / split
    t = torch.exp(-((centres - kp_px[..., None]) ** 2) / (2 * sigma_px ** 2))
    return t / t.sum(-1, keepdim=True).clamp_min(1e-12)


def keypoint_weights(kp: np.ndarray, in_image: np.ndarray, w: int, h: int) -> np.ndarray:
    """(M, K) 1 for keypoints to learn: in the frame and inside the crop."""
    u, v = kp[..., 0], kp[..., 1]
    inside = (u > -0.5) & (u < w - 0.5) & (v > -0.5) & (v < h - 0.5)
    return (inside & in_image).astype(np.float32)


def photometric(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Per-image contrast/brightness/colour gain in [0, 1] space (cheap, in torch)."""
    b = x.shape[0]
    # drawn on the (CPU) generator, so a run draws the same numbers on any device
    gain = 0.75 + 0.5 * torch.rand(b, 1, 1, 1, generator=gen)
    colour = 0.9 + 0.2 * torch.rand(b, 3, 1, 1, generator=gen)
    bias = 0.12 * (torch.rand(b, 1, 1, 1, generator=gen) - 0.5)
    dev = x.device
    return (x * gain.to(dev) * colour.to(dev) + bias.to(dev)).clamp(0, 1)


def class_weights(labels: np.ndarray, num_classes: int, lo: float = 0.2, hi: float = 5.0
                  ) -> np.ndarray:
    """(num_classes,) float32 cross-entropy weights from (N, h, w) training labels: the square
    root of median frequency balancing (median class frequency / class frequency, over the
    classes present), clipped to [lo, hi]; 0 for classes absent from the labels. The square
    root keeps the rare classes (robot, person) learnt without trading away the large ones
    (floor, wall) that the map needs most."""
    counts = np.bincount(np.asarray(labels).ravel(), minlength=num_classes)[:num_classes]
    freq = counts / max(int(counts.sum()), 1)
    present = freq > 0
    w = np.zeros(num_classes, np.float64)
    if present.any():
        w[present] = np.clip(np.sqrt(np.median(freq[present]) / freq[present]), lo, hi)
    return w.astype(np.float32)


def mirror_crops(x: torch.Tensor, kp: np.ndarray, wgt: np.ndarray, flip: np.ndarray,
                 perm: np.ndarray) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
    """Mirror the crops where ``flip`` (B,) is set: images (B, 3, H, W) left/right, and the
    labels with them: the mirrored crop's keypoint j is the original's partner ``perm[j]``,
    at ``u -> W - 1 - u`` (pixel centres); its weight moves along."""
    w = x.shape[-1]
    kp_m = kp[:, perm].copy()
    kp_m[..., 0] = w - 1 - kp_m[..., 0]
    kp = np.where(flip[:, None, None], kp_m, kp)
    wgt = np.where(flip[:, None], wgt[:, perm], wgt)
    f = torch.from_numpy(flip).to(x.device)[:, None, None, None]
    return torch.where(f, x.flip(-1), x), kp, wgt
