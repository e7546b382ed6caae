"""Test-time flip augmentation of the keypoint network: the left/right partner of every keypoint
is found by name, and with flip on, a mirrored render gives the mirrored keypoints (each
left keypoint where its right partner was, mirrored), which fails if the swap were wrong."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from edge_agent.flip import mirror_permutation
from edge_agent.model_cards import ModelError, default_model_dir
from edge_agent.networks import KeypointEstimator


def test_mirror_permutation_pairs_left_and_right() -> None:
    names = ["front_top", "front_left_top", "left_top", "right_top", "front_right_top"]
    perm = mirror_permutation(names)
    assert [names[i] for i in perm] == ["front_top", "front_right_top", "right_top",
                                        "left_top", "front_left_top"]
    np.testing.assert_array_equal(perm[perm], np.arange(len(names)))  # an involution
    with pytest.raises(ModelError, match="no mirror partner 'right_top'"):
        mirror_permutation(["front_top", "left_top"])
    # "leftover" is not a side: only whole words count
    np.testing.assert_array_equal(mirror_permutation(["leftover", "rightmost"]), [0, 1])


def _mirror(kp: np.ndarray, width: int, perm: np.ndarray) -> np.ndarray:
    """Keypoints (n, K, 2) of a frame → those of its mirror image."""
    out = kp[:, perm].copy()
    out[..., 0] = width - 1 - out[..., 0]
    return out


@pytest.fixture(scope="module")
def site_view():  # type: ignore[no-untyped-def]
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    gen = SampleGenerator(load_scenario(), "site", seed=5)
    for i in range(20):
        s = gen(i)
        box = s.robots[0].bbox_xyxy if s.robots else None
        if box is not None and (box[2] - box[0]) > 60 and s.robots[0].in_image.all():
            return s
    pytest.fail("no site view with the whole robot in 20 renders")


def test_mirrored_render_gives_mirrored_keypoints_with_flip(site_view) -> None:  # type: ignore[no-untyped-def]
    image = site_view.image_rgb
    w = image.shape[1]
    box = np.asarray(site_view.robots[0].bbox_xyxy, np.float64)
    box_m = np.array([w - 1 - box[2], box[1], w - 1 - box[0], box[3]])
    mirrored = np.ascontiguousarray(image[:, ::-1])
    path = default_model_dir() / "keypoints.onnx"
    tta = KeypointEstimator(path, threads=1, flip=True)
    perm = mirror_permutation(tta.card.keypoint_names)
    kp, conf = tta.estimate(image, box[None])
    kp_m, conf_m = tta.estimate(mirrored, box_m[None])
    np.testing.assert_allclose(kp_m, _mirror(kp, w, perm), atol=0.02)
    np.testing.assert_allclose(conf_m, conf[:, perm], atol=1e-4)
    # the keypoints are near the truth, so the check above is about real keypoints
    true = np.asarray(site_view.robots[0].keypoints_px)
    assert np.median(np.linalg.norm(kp[0] - true, axis=1)) < 3.0
    # without the left/right swap the mirrored estimate is far off: the swap is what is tested
    wrong = kp.copy()
    wrong[..., 0] = w - 1 - wrong[..., 0]
    assert np.max(np.linalg.norm(kp_m - wrong, axis=-1)) > 5.0
    # without the flip the network is not mirror-consistent by itself (the robot is not
    # left/right symmetric)
    plain = KeypointEstimator(path, threads=1, flip=False)
    p, _ = plain.estimate(image, box[None])
    p_m, _ = plain.estimate(mirrored, box_m[None])
    assert np.max(np.linalg.norm(p_m - _mirror(p, w, perm), axis=-1)) > 0.05


def test_the_card_decides_the_default(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """The estimator flips when its card says the model was trained for it (the shipped one),
    not otherwise; a card written before the field existed reads as no flip."""
    assert KeypointEstimator(default_model_dir() / "keypoints.onnx", threads=1).flip is True
    onnx = _shipped_without_flip_field("keypoints", tmp_path)
    old = KeypointEstimator(onnx, threads=1)
    assert old.flip is False and old.card.flip_tta is False
    assert KeypointEstimator(onnx, threads=1, flip=True).flip is True


def _shipped_without_flip_field(kind: str, folder: Path) -> Path:
    """A copy of the shipped ``kind`` model in ``folder`` whose card has no ``flip_tta`` (as
    cards written before the field existed); returns the copy's .onnx path."""
    for suffix in (".onnx", ".json"):
        shutil.copy(default_model_dir() / f"{kind}{suffix}", folder / f"{kind}{suffix}")
    card = folder / f"{kind}.json"
    doc = json.loads(card.read_text())
    doc.pop("flip_tta")
    card.write_text(json.dumps(doc))
    return folder / f"{kind}.onnx"


# --- the detector's test-time flip ------------------------------------------------------------


def test_fused_boxes_average_both_passes_and_halve_a_one_sided_box() -> None:
    from edge_agent.flip import fuse_flipped_detections

    direct = np.array([[10.0, 20.0, 50.0, 80.0, 0.8],     # the robot, both passes see it
                       [200.0, 10.0, 230.0, 60.0, 0.5]])  # seen in this orientation only
    mirrored = np.array([[12.0, 20.0, 52.0, 80.0, 0.6]])
    fused = fuse_flipped_detections(direct, mirrored, min_score=0.2, max_detections=8)
    assert fused.shape == (2, 5)
    np.testing.assert_allclose(fused[0, 4], 0.7)
    np.testing.assert_allclose(fused[0, 0], (10 * 0.8 + 12 * 0.6) / 1.4)
    np.testing.assert_allclose(fused[1], [200.0, 10.0, 230.0, 60.0, 0.25])
    # the floor applies to the fused score: the one-sided box is gone at 0.3
    assert len(fuse_flipped_detections(direct, mirrored, 0.3, 8)) == 1
    # which pass is "direct" does not matter
    np.testing.assert_allclose(fuse_flipped_detections(mirrored, direct, 0.2, 8), fused)
    # two peaks of one pass on one robot count once: the pass's best
    twice = np.concatenate([direct, [[11.0, 21.0, 51.0, 81.0, 0.7]]])
    np.testing.assert_allclose(fuse_flipped_detections(twice, mirrored, 0.2, 8)[0, 4], 0.7)
    assert fuse_flipped_detections(np.zeros((0, 5)), np.zeros((0, 5)), 0.3, 8).shape == (0, 5)


def test_mirrored_render_gives_mirrored_boxes_with_the_detectors_flip(site_view) -> None:  # type: ignore[no-untyped-def]
    from edge_agent.boxes import box_iou
    from edge_agent.networks import Detector

    image = site_view.image_rgb
    w = image.shape[1]
    mirrored = np.ascontiguousarray(image[:, ::-1])
    det = Detector(default_model_dir() / "detector.onnx", threads=1)
    assert det.flip is True  # the shipped card says so
    boxes = det.detect(image, min_score=0.3)
    boxes_m = det.detect(mirrored, min_score=0.3)
    assert len(boxes) >= 1 and len(boxes) == len(boxes_m)
    want = boxes.copy()
    want[:, 0], want[:, 2] = w - 1 - boxes[:, 2], w - 1 - boxes[:, 0]
    np.testing.assert_allclose(boxes_m, want, atol=1e-3)
    # the box is the robot's
    assert box_iou(boxes[0, :4], np.asarray(site_view.robots[0].bbox_xyxy)) > 0.7
    # without the flip the two orientations differ: the test above is not trivially true
    plain = Detector(default_model_dir() / "detector.onnx", threads=1, flip=False)
    p, p_m = plain.detect(image), plain.detect(mirrored)
    assert np.max(np.abs(p_m[0, [0, 2]] - (w - 1 - p[0, [2, 0]]))) > 1e-3 or abs(
        p_m[0, 4] - p[0, 4]) > 1e-4


def test_the_detector_card_decides_its_flip(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from edge_agent.models import RobotKeypointPipeline
    from edge_agent.networks import Detector

    onnx = _shipped_without_flip_field("detector", tmp_path)
    old = Detector(onnx, threads=1)
    assert old.flip is False and old.card.flip_tta is False
    assert Detector(onnx, threads=1, flip=True).flip is True
    pipe = RobotKeypointPipeline(threads=1, detector_flip=False)
    assert pipe.detector.flip is False and pipe.keypoints.flip is True


def test_the_iou_matrix_is_box_iou_of_every_pair() -> None:
    from edge_agent.boxes import box_iou, iou_matrix

    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 100, (12, 2))
    boxes = np.concatenate([xy, xy + rng.uniform(0, 40, (12, 2))], axis=1)
    boxes[3] = boxes[2]  # identical pair
    boxes[5, 2:] = boxes[5, :2]  # empty box
    m = iou_matrix(boxes)
    want = np.array([[box_iou(a, b) for b in boxes] for a in boxes])
    np.testing.assert_allclose(m, want, atol=1e-12)
    assert m[2, 3] == 1.0 and m[5, 5] == 0.0
