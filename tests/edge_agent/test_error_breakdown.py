"""The keypoint error breakdown (``lab.evaluation.keypoints.error_breakdown``) separates a
keypoint's systematic error (bias) from its random one (spread), and per distance a shift
common to all keypoints from the rest that turns the heading. Checked on planted errors: the
pipeline's answer is the true keypoints plus a known bias per keypoint, a known shift per
detection and known random noise."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np

from edge_agent.networks import RobotObservation
from lab.evaluation.keypoints import error_breakdown

NAMES = ["front_top", "left_top", "rear_top", "right_top"]
RING = np.array([[40.0, 0.0], [0.0, -20.0], [-40.0, 0.0], [0.0, 20.0]])


@dataclasses.dataclass
class PlantedPipeline:
    """Answers each frame with the true keypoints + ``bias`` + a per-frame shift + noise."""

    bias: np.ndarray
    noise_px: float
    shift_px: float
    rng: np.random.Generator
    keypoints: SimpleNamespace = dataclasses.field(
        default_factory=lambda: SimpleNamespace(card=SimpleNamespace(keypoint_names=NAMES)))
    truth: dict[int, np.ndarray] = dataclasses.field(default_factory=dict)

    def __call__(self, image_rgb: np.ndarray, **_: object) -> list[RobotObservation]:
        true = self.truth[id(image_rgb)]
        kp = (true + self.bias + self.rng.normal(0, self.shift_px, 2)
              + self.rng.normal(0, self.noise_px, true.shape))
        x0, y0 = true.min(axis=0)
        x1, y1 = true.max(axis=0)
        return [RobotObservation(np.array([x0, y0, x1, y1]), 0.9, kp, np.ones(len(kp)))]


def _samples(pipeline: PlantedPipeline, n: int, depth_m: float, rng: np.random.Generator
             ) -> list[SimpleNamespace]:
    out = []
    for _ in range(n):
        true = RING + rng.uniform(100, 300, 2)
        image = np.zeros((4, 4, 3), np.uint8)
        pipeline.truth[id(image)] = true
        x0, y0 = true.min(axis=0)
        x1, y1 = true.max(axis=0)
        robot = SimpleNamespace(bbox_xyxy=np.array([x0, y0, x1, y1]), keypoints_px=true,
                                in_image=np.ones(4, bool), visible=np.array([1, 1, 0, 1], bool),
                                depth_m=np.full(4, depth_m))
        out.append(SimpleNamespace(image_rgb=image, robots=(robot,)))
    return out


def test_breakdown_separates_bias_spread_and_common_shift() -> None:
    rng = np.random.default_rng(0)
    bias = np.array([[0.0, 0.0], [0.8, 0.0], [0.0, -0.5], [0.0, 0.0]])
    pipeline = PlantedPipeline(bias, noise_px=0.3, shift_px=1.0, rng=rng)
    samples = _samples(pipeline, 300, 2.0, rng) + _samples(pipeline, 300, 7.0, rng)
    result = error_breakdown(pipeline, samples)
    k = result.per_keypoint
    assert set(k) == set(NAMES)
    # the per-frame shift (1 px) is random per keypoint too: spread ~ sqrt(1 + 0.3^2)
    assert abs(k["left_top"]["bias x px"] - 0.8) < 0.15
    assert abs(k["rear_top"]["bias y px"] + 0.5) < 0.15
    assert abs(k["front_top"]["bias x px"]) < 0.15
    assert 0.9 < k["front_top"]["spread px"] < 1.2
    assert k["rear_top"]["occluded share"] == 1.0 and k["front_top"]["occluded share"] == 0.0
    d = result.per_distance
    assert set(d) == {"0-3 m", ">= 6 m"}
    for figs in d.values():
        assert figs["n"] == 300
        assert 0.85 < figs["shift px"] < 1.3  # the common shift, pooled over both axes
        assert figs["rest px"] < 0.6  # noise + the biases left after the shift fit
    assert any(line.startswith("keypoint left_top:") for line in result.lines())
