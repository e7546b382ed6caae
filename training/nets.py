"""The two networks, in plain torch (no torchvision), sized for an edge board.

- :class:`RobotDetector`: CenterNet-style single-stage detector. A MobileNetV3-small-like
  backbone, a light FPN back to stride 4, and three heads: a centre heatmap (one class: robot),
  the box size (log pixels of the detector input) and the sub-cell centre offset. Peaks are kept
  by a 3x3 max-pool inside the graph, so no NMS is needed.
- :class:`SemanticSegNet`: per-pixel semantic classes (:data:`protocol.semantic_classes.
  SEMANTIC_CLASSES`) on the whole resized frame: the backbone and an FPN back to stride 4 as in
  the detector, a classifier head, and the logits upsampled (bilinear) to stride 2 inside the
  graph, which returns the arg-max class and its softmax probability per output pixel.
- :class:`KeypointNet`: top-down keypoints on a fixed-size crop with a SimCC head (one 1-D
  classification over sub-pixel bins per axis and keypoint, no heatmaps). The exported graph
  decodes inside: a soft-argmax in a window around the best bin gives sub-pixel coordinates and
  the probability mass in that window is the keypoint's confidence.

All take float32 RGB in [0, 1] (N, 3, H, W) and normalise inside, so the edge pipeline only
resizes and scales.
"""

from __future__ import annotations

import dataclasses
from typing import Final

import torch
import torch.nn.functional as F
from torch import nn

#: ImageNet-style normalisation constants (applied inside the graph)
_MEAN: Final = (0.485, 0.456, 0.406)
_STD: Final = (0.229, 0.224, 0.225)
#: heat values this close to their 3x3 neighbourhood's maximum count as peaks
PEAK_TIE: Final = 1e-5


class ConvBNAct(nn.Sequential):
    def __init__(self, c_in: int, c_out: int, k: int = 3, s: int = 1, groups: int = 1,
                 act: type[nn.Module] | None = nn.ReLU) -> None:
        layers: list[nn.Module] = [nn.Conv2d(c_in, c_out, k, s, k // 2, groups=groups, bias=False),
                                   nn.BatchNorm2d(c_out)]
        if act is not None:
            layers.append(act())
        super().__init__(*layers)


class SqueezeExcite(nn.Module):
    def __init__(self, c: int, reduction: int = 4) -> None:
        super().__init__()
        hidden = max(8, c // reduction)
        self.fc1 = nn.Conv2d(c, hidden, 1)
        self.fc2 = nn.Conv2d(hidden, c, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = F.adaptive_avg_pool2d(x, 1)
        s = F.hardsigmoid(self.fc2(F.relu(self.fc1(s))))
        return x * s


class InvertedResidual(nn.Module):
    """MobileNetV3 block: expand 1x1, depthwise k x k, optional squeeze-excite, project 1x1."""

    def __init__(self, c_in: int, c_exp: int, c_out: int, k: int, s: int, se: bool,
                 act: type[nn.Module]) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        if c_exp != c_in:
            layers.append(ConvBNAct(c_in, c_exp, 1, act=act))
        layers.append(ConvBNAct(c_exp, c_exp, k, s, groups=c_exp, act=act))
        if se:
            layers.append(SqueezeExcite(c_exp))
        layers.append(ConvBNAct(c_exp, c_out, 1, act=None))
        self.body = nn.Sequential(*layers)
        self.residual = s == 1 and c_in == c_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.body(x)
        return x + y if self.residual else y


RE, HS = nn.ReLU, nn.Hardswish
#: (expansion, out, kernel, stride, squeeze-excite, activation) per block, MobileNetV3-small
_BLOCKS: Final = (
    (16, 16, 3, 2, True, RE),     # /4
    (72, 24, 3, 2, False, RE),    # /8
    (88, 24, 3, 1, False, RE),
    (96, 40, 5, 2, True, HS),     # /16
    (240, 40, 5, 1, True, HS),
    (240, 40, 5, 1, True, HS),
    (120, 48, 5, 1, True, HS),
    (144, 48, 5, 1, True, HS),
    (288, 96, 5, 2, True, HS),    # /32
    (576, 96, 5, 1, True, HS),
)


class Backbone(nn.Module):
    """MobileNetV3-small-like; returns the features at strides 4, 8, 16 and 32
    (16, 24, 48, 96 channels)."""

    channels: Final = (16, 24, 48, 96)

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("mean", torch.tensor(_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(_STD).view(1, 3, 1, 1))
        self.stem = ConvBNAct(3, 16, 3, 2, act=HS)
        blocks, c = [], 16
        for exp, out, k, s, se, act in _BLOCKS:
            blocks.append(InvertedResidual(c, exp, out, k, s, se, act))
            c = out
        self.blocks = nn.ModuleList(blocks)
        self.taps = (0, 2, 7, 9)  # last block of each stride

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - self.mean) / self.std
        x = self.stem(x)
        feats = []
        for i, block in enumerate(self.blocks):
            x = block(x)
            if i in self.taps:
                feats.append(x)
        return feats


class _Fuse(nn.Module):
    """Top-down FPN step: upsample the coarser map to the finer one's size, add the finer map's
    1x1 lateral, smooth with a depthwise-separable 3x3."""

    def __init__(self, c_lateral: int, c: int) -> None:
        super().__init__()
        self.lateral = ConvBNAct(c_lateral, c, 1, act=None)
        self.smooth = nn.Sequential(ConvBNAct(c, c, 3, groups=c, act=None), ConvBNAct(c, c, 1))

    def forward(self, coarse: torch.Tensor, fine: torch.Tensor) -> torch.Tensor:
        up = F.interpolate(coarse, size=fine.shape[-2:], mode="nearest")
        return self.smooth(up + self.lateral(fine))


def _head(c: int, c_out: int, bias: float = 0.0) -> nn.Sequential:
    head = nn.Sequential(ConvBNAct(c, c, 3, groups=c), ConvBNAct(c, c, 1), nn.Conv2d(c, c_out, 1))
    nn.init.constant_(head[-1].bias, bias)
    return head


@dataclasses.dataclass(frozen=True)
class DetectorOutput:
    heat_logits: torch.Tensor  # (N, 1, H/4, W/4)
    log_size: torch.Tensor  # (N, 2, H/4, W/4) log of box width, height in input pixels
    offset: torch.Tensor  # (N, 2, H/4, W/4) centre offset within the cell, cells


class RobotDetector(nn.Module):
    """CenterNet-style detector; output stride 4."""

    stride: Final = 4

    def __init__(self, width: int = 32) -> None:
        super().__init__()
        self.backbone = Backbone()
        c4, c8, c16, c32 = Backbone.channels
        self.top = ConvBNAct(c32, width, 1)
        self.fuse16, self.fuse8, self.fuse4 = _Fuse(c16, width), _Fuse(c8, width), _Fuse(c4, width)
        self.heat = _head(width, 1, bias=-2.19)  # prior 0.1 (CenterNet)
        self.size = _head(width, 2, bias=3.0)
        self.offset = _head(width, 2)

    def forward_train(self, x: torch.Tensor) -> DetectorOutput:
        f4, f8, f16, f32 = self.backbone(x)
        y = self.fuse4(self.fuse8(self.fuse16(self.top(f32), f16), f8), f4)
        return DetectorOutput(self.heat(y), self.size(y), self.offset(y))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Exported graph: (peaks (N, 1, h, w) heat where it is a 3x3 local maximum, else 0;
        size (N, 2, h, w) box width/height in input pixels; offset (N, 2, h, w) cells)."""
        out = self.forward_train(x)
        heat = torch.sigmoid(out.heat_logits)
        # a local maximum, ties (up to float noise) included
        peaks = heat * (heat >= F.max_pool2d(heat, 3, 1, 1) - PEAK_TIE).to(heat.dtype)
        return peaks, torch.exp(out.log_size.clamp(-2.0, 8.0)), out.offset


@dataclasses.dataclass(frozen=True)
class KeypointOutput:
    logits_x: torch.Tensor  # (N, K, W * split)
    logits_y: torch.Tensor  # (N, K, H * split)


class KeypointNet(nn.Module):
    """Top-down SimCC keypoint network on a ``input_h`` x ``input_w`` crop."""

    def __init__(self, num_keypoints: int, input_w: int = 192, input_h: int = 256,
                 split: int = 2, hidden: int = 256, per_keypoint: int = 8,
                 window_bins: int = 6) -> None:
        super().__init__()
        if input_w % 32 or input_h % 32:
            raise ValueError(f"keypoint input {input_w}x{input_h}: both must be multiples of 32")
        self.num_keypoints, self.input_w, self.input_h = num_keypoints, input_w, input_h
        self.split, self.window_bins, self.per_keypoint = split, window_bins, per_keypoint
        self.backbone = Backbone()
        c16, c32 = Backbone.channels[2:]
        width = 96
        self.top = ConvBNAct(c32, width, 1)
        self.fuse16 = _Fuse(c16, width)
        self.to_kp = nn.Conv2d(width, num_keypoints * per_keypoint, 3, padding=1)
        cells = (input_w // 16) * (input_h // 16) * per_keypoint
        self.mlp = nn.Sequential(nn.Linear(cells, hidden), nn.GELU())
        self.cls_x = nn.Linear(hidden, input_w * split)
        self.cls_y = nn.Linear(hidden, input_h * split)

    def forward_train(self, x: torch.Tensor) -> KeypointOutput:
        _, _, f16, f32 = self.backbone(x)
        y = self.to_kp(self.fuse16(self.top(f32), f16))  # (N, K * C, H/16, W/16)
        n = y.shape[0]
        y = y.reshape(n, self.num_keypoints, -1)
        h = self.mlp(y)
        return KeypointOutput(self.cls_x(h), self.cls_y(h))

    def _decode_axis(self, logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        prob = torch.softmax(logits, dim=-1)
        bins = torch.arange(logits.shape[-1], dtype=logits.dtype, device=logits.device)
        best = prob.argmax(dim=-1, keepdim=True).to(logits.dtype)
        window = ((bins - best).abs() <= self.window_bins).to(logits.dtype)
        mass = (prob * window).sum(-1)
        coord = (prob * window * bins).sum(-1) / mass.clamp_min(1e-9)
        return coord / self.split, mass

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Exported graph: (keypoints (N, K, 2) crop pixels, confidence (N, K) in [0, 1])."""
        out = self.forward_train(x)
        px, mx = self._decode_axis(out.logits_x)
        py, my = self._decode_axis(out.logits_y)
        return torch.stack([px, py], dim=-1), torch.sqrt(mx * my)


class SemanticSegNet(nn.Module):
    """Per-pixel classes on the whole frame; output stride 2 (half the input size).

    The backbone's stride-32 features come back to stride 4 through FPN steps (``width``
    channels); a depthwise-separable head predicts ``num_classes`` logits there, upsampled
    bilinearly to stride 2 (decoding at stride 2 itself doubled the training cost on a CPU).
    Output pixel ``(i, j)`` stands for input pixel centre ``(2 j + 0.5, 2 i + 0.5)`` (OpenCV
    convention), as the labels of :func:`edge_agent.crop.downscale_labels` do."""

    output_stride: Final = 2

    def __init__(self, num_classes: int, width: int = 48) -> None:
        super().__init__()
        self.num_classes = num_classes
        self.backbone = Backbone()
        c4, c8, c16, c32 = Backbone.channels
        self.top = ConvBNAct(c32, width, 1)
        self.fuse16, self.fuse8, self.fuse4 = _Fuse(c16, width), _Fuse(c8, width), _Fuse(c4, width)
        self.classifier = _head(width, num_classes)

    def forward_train(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) RGB in [0, 1] → (N, num_classes, H/2, W/2) logits."""
        f4, f8, f16, f32 = self.backbone(x)
        y = self.fuse4(self.fuse8(self.fuse16(self.top(f32), f16), f8), f4)
        # a fixed factor (not the input's size) keeps the exported output shape static
        return F.interpolate(self.classifier(y), scale_factor=4 / self.output_stride,
                             mode="bilinear", align_corners=False)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Exported graph: (class_ids (N, H/2, W/2) uint8, the arg-max class; confidence
        (N, H/2, W/2) float32, its softmax probability in [0, 1])."""
        prob = torch.softmax(self.forward_train(x), dim=1)
        confidence, class_ids = prob.max(dim=1)
        return class_ids.to(torch.uint8), confidence
