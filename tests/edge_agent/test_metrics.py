"""Held-out metrics on hand-made cases: box IoU values, detection AP (perfect, a mix computed
by hand, false positives on empty images), keypoint error figures and the confidence
calibration's sign."""

from __future__ import annotations

import math

import numpy as np
import pytest

from edge_agent.boxes import box_iou
from edge_agent.metrics import detection_ap, keypoint_metrics, spearman

NO_BOX = np.full(4, np.nan)
AP = "AP@0.5"
FP_RATE = "false positive rate (no robot, score >= 0.3)"


def _det(*rows: tuple[float, ...]) -> np.ndarray:
    """(n, 5) detections x0, y0, x1, y1, score (best first as given)."""
    return np.array(rows, float).reshape(-1, 5)


@pytest.mark.parametrize(("a", "b", "iou"), [
    ((0, 0, 10, 10), (0, 0, 10, 10), 1.0),
    ((0, 0, 10, 10), (5, 0, 15, 10), 50 / 150),
    ((0, 0, 10, 10), (2, 2, 7, 7), 25 / 100),
    ((0, 0, 10, 10), (10, 0, 20, 10), 0.0),  # touching edges
    ((0, 0, 10, 10), (20, 20, 30, 30), 0.0),
    ((0, 0, 4, 2), (2, 1, 6, 3), 2 / 14),
    ((0, 0, 0, 0), (0, 0, 0, 0), 0.0),  # empty boxes: no division by zero
])
def test_box_iou_known_values(a: tuple, b: tuple, iou: float) -> None:
    """IoU of edge-coordinate boxes, symmetric."""
    assert box_iou(np.array(a, float), np.array(b, float)) == pytest.approx(iou)
    assert box_iou(np.array(b, float), np.array(a, float)) == pytest.approx(iou)


def test_detection_ap_is_one_for_perfect_detections() -> None:
    """Every robot found exactly, nothing on empty images: AP 1, mean IoU 1, no false
    positives; the image counts are reported."""
    gt = np.array([[10, 10, 50, 80], [0, 0, 20, 20], NO_BOX, [30, 5, 60, 45]], float)
    dets = [_det((*gt[0], 0.9)), _det((*gt[1], 0.4)), _det(), _det((*gt[3], 0.7))]
    out = detection_ap(dets, gt)
    assert out[AP] == pytest.approx(1.0)
    assert out["mean IoU"] == pytest.approx(1.0)
    assert out[FP_RATE] == 0.0
    assert out["images with robot"] == 3.0


def test_detection_ap_of_a_known_mix() -> None:
    """Two robots; ranked by score: a hit (0.9), a miss (0.8, IoU 0 with its robot) and
    nothing else. Precision/recall: (1, 1/2), (1/2, 1/2); the all-point interpolated AP is
    1 * 1/2 = 0.5. The mean IoU is that of each image's best detection."""
    gt = np.array([[0, 0, 10, 10], [100, 100, 120, 140]], float)
    dets = [_det((0, 0, 10, 10, 0.9)), _det((0, 0, 10, 10, 0.8))]
    out = detection_ap(dets, gt)
    assert out[AP] == pytest.approx(0.5)
    assert out["mean IoU"] == pytest.approx(0.5)


def test_detection_ap_of_a_longer_ranking_by_hand() -> None:
    """Four robots, detections by score: TP 0.95, FP 0.9 (a duplicate on the same robot),
    TP 0.6, FP 0.5 (poor box, IoU 1/3), robot 4 missed. Recall/precision after each:
    (1/4, 1), (1/4, 1/2), (2/4, 2/3), (2/4, 1/2). Envelope: 1 up to recall 1/4, 2/3 up to
    1/2, then 0: AP = 1/4 * 1 + 1/4 * 2/3 = 5/12."""
    gt = np.array([[0, 0, 10, 10], [0, 0, 10, 10], [0, 0, 10, 10], [0, 0, 10, 10]], float)
    dets = [
        _det((0, 0, 10, 10, 0.95), (0, 0, 10, 9, 0.9)),  # second: duplicate, not a hit
        _det((0, 0, 10, 10, 0.6)),
        _det((0, 0, 10, 10 / 3, 0.5)),  # IoU 1/3: a false positive
        _det(),
    ]
    out = detection_ap(dets, gt)
    assert out[AP] == pytest.approx(5 / 12)
    # best detection per robot image: 1, 1, 1/3, none (0)
    assert out["mean IoU"] == pytest.approx((1 + 1 + 1 / 3 + 0) / 4)
    # an IoU of exactly the threshold is a hit
    assert detection_ap([_det((0, 0, 5, 10, 0.5))], gt[:1])[AP] == pytest.approx(1.0)


def test_false_positives_on_empty_images_lower_the_ap() -> None:
    """A confident detection on an image without a robot, ranked above the true ones, lowers
    the AP and shows in the false-positive rate; one below 0.3 does not count in that rate."""
    gt = np.array([[0, 0, 10, 10], [20, 20, 40, 40], NO_BOX, NO_BOX], float)
    hits = [_det((0, 0, 10, 10, 0.8)), _det((20, 20, 40, 40, 0.7))]
    clean = detection_ap([*hits, _det(), _det()], gt)
    assert clean[AP] == pytest.approx(1.0) and clean[FP_RATE] == 0.0
    noisy = detection_ap([*hits, _det((5, 5, 9, 9, 0.95)), _det((1, 1, 2, 2, 0.2))], gt)
    # ranking FP(0.95), TP, TP, FP(0.2): precision at recall 1/2 and 1 is 1/2 and 2/3
    assert noisy[AP] == pytest.approx(0.5 * 2 / 3 + 0.5 * 2 / 3)
    assert noisy[AP] < clean[AP]
    assert noisy[FP_RATE] == pytest.approx(0.5)
    assert noisy["images with robot"] == 2.0


def test_detection_ap_without_any_robot() -> None:
    """No image with a robot: AP and mean IoU are undefined (NaN), the FP rate still counts."""
    out = detection_ap([_det((0, 0, 5, 5, 0.5)), _det()], np.array([NO_BOX, NO_BOX]))
    assert math.isnan(out[AP]) and math.isnan(out["mean IoU"])
    assert out[FP_RATE] == pytest.approx(0.5)


def test_ignored_robots_are_neither_asked_for_nor_false() -> None:
    """A robot marked ignore (too hidden to measure): missing it costs nothing, finding it
    neither helps nor counts as a false positive, and another detection in its image is still a
    false positive. Robots A, B found (0.9, 0.5); robot C ignored."""
    gt = np.array([[0, 0, 10, 10], [20, 20, 40, 40], [50, 50, 60, 70]], float)
    ignore = [False, False, True]
    a, b = _det((0, 0, 10, 10, 0.9)), _det((20, 20, 40, 40, 0.5))
    missed = detection_ap([a, b, _det()], gt, ignore=ignore)
    assert missed[AP] == pytest.approx(1.0)
    assert missed["images with robot"] == 2.0 and missed["robots ignored"] == 1.0
    # the same miss without the ignore flag: recall stops at 2/3
    assert detection_ap([a, b, _det()], gt)[AP] == pytest.approx(2 / 3)
    found = detection_ap([a, b, _det((50, 50, 60, 70, 0.95))], gt, ignore=ignore)
    assert found[AP] == pytest.approx(1.0)
    # a box beside C ranked first is false: FP(0.99), TP, TP -> precision 2/3 at recall 1
    stray = detection_ap([a, b, _det((50, 50, 60, 70, 0.95), (0, 200, 9, 240, 0.99))], gt,
                         ignore=ignore)
    assert stray[AP] == pytest.approx(2 / 3)
    # an ignore flag on an image without a robot changes nothing
    assert detection_ap([a, _det()], np.array([gt[0], NO_BOX]), ignore=[False, True])[
        "robots ignored"] == 0.0
    with pytest.raises(ValueError, match="2 flags for 3 images"):
        detection_ap([a, b, _det()], gt, ignore=[False, True])


def _synthetic_keypoints(n: int = 300, k: int = 6, seed: int = 0
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Errors that grow as the confidence falls; every third keypoint occluded with twice
    the error; a few invalid ones with huge errors that must be ignored."""
    rng = np.random.default_rng(seed)
    conf = rng.uniform(0.05, 1.0, (n, k))
    err = 8.0 * (1.0 - conf) + rng.uniform(0, 0.2, (n, k))
    visible = np.ones((n, k), bool)
    visible[:, ::3] = False
    err = np.where(visible, err, 2.0 * err)
    valid = np.ones((n, k), bool)
    valid[:10] = False
    err[:10] = 1e6
    return err, conf, valid, visible


def test_keypoint_metrics_figures() -> None:
    """Median/mean error, PCK, the occluded split and the calibration thirds match numpy
    computed directly on the valid keypoints; invalid keypoints do not count."""
    err, conf, valid, visible = _synthetic_keypoints()
    out = keypoint_metrics(err, conf, valid, visible)
    e, c = err[valid], conf[valid]
    occ = err[valid & ~visible]
    assert out["keypoints"] == float(valid.sum())
    assert out["median error px"] == pytest.approx(np.median(e))
    assert out["mean error px"] == pytest.approx(np.mean(e))
    assert out["PCK@2px"] == pytest.approx(np.mean(e <= 2.0))
    assert out["PCK@5px"] == pytest.approx(np.mean(e <= 5.0))
    assert 0.0 < out["PCK@2px"] < out["PCK@5px"] < 1.0
    assert out["occluded share"] == pytest.approx(1 / 3)
    assert out["occluded median error px"] == pytest.approx(np.median(occ))
    assert out["occluded PCK@5px"] == pytest.approx(np.mean(occ <= 5.0))
    assert out["occluded median error px"] > out["visible median error px"]
    assert out["median error px, low-confidence third"] > out[
        "median error px, high-confidence third"]
    lo = np.quantile(c, 1 / 3)
    assert out["median error px, low-confidence third"] == pytest.approx(np.median(e[c <= lo]))


def test_keypoint_metrics_exact_small_case() -> None:
    """Four keypoints by hand: errors 1, 3, 6, 10 px, the 6 px one occluded."""
    err = np.array([[1.0, 3.0, 6.0, 10.0]])
    conf = np.array([[0.9, 0.7, 0.5, 0.1]])
    valid = np.ones((1, 4), bool)
    visible = np.array([[True, True, False, True]])
    out = keypoint_metrics(err, conf, valid, visible)
    assert out["median error px"] == pytest.approx(4.5)
    assert out["mean error px"] == pytest.approx(5.0)
    assert out["PCK@2px"] == pytest.approx(0.25)
    assert out["PCK@5px"] == pytest.approx(0.5)
    assert out["visible median error px"] == pytest.approx(3.0)
    assert out["occluded median error px"] == pytest.approx(6.0)
    assert out["occluded PCK@5px"] == 0.0
    assert out["occluded share"] == pytest.approx(0.25)
    assert out["confidence-error Spearman"] == pytest.approx(-1.0)


def test_keypoint_metrics_spearman_sign() -> None:
    """Error growing as confidence falls gives a clearly negative Spearman correlation; the
    reverse (confident keypoints worse) a positive one."""
    err, conf, valid, visible = _synthetic_keypoints()
    good = keypoint_metrics(err, conf, valid, visible)["confidence-error Spearman"]
    bad = keypoint_metrics(err, 1.0 - conf, valid, visible)["confidence-error Spearman"]
    assert good < -0.8
    assert bad > 0.8


def test_keypoint_metrics_without_valid_keypoints() -> None:
    """Nothing valid: only the count (0) is reported; no occluded keypoints gives NaN figures."""
    err = np.ones((2, 3))
    assert keypoint_metrics(err, err, np.zeros((2, 3), bool), np.ones((2, 3), bool)) == {
        "keypoints": 0.0}
    out = keypoint_metrics(err, np.linspace(0, 1, 6).reshape(2, 3), np.ones((2, 3), bool),
                           np.ones((2, 3), bool))
    assert math.isnan(out["occluded median error px"]) and out["occluded share"] == 0.0


def test_spearman_known_values() -> None:
    """Monotone up: 1; monotone down: -1; invariant to monotone transforms; fewer than three
    points: NaN."""
    x = np.array([0.1, 0.4, 0.2, 0.9, 0.5])
    assert spearman(x, x ** 3) == pytest.approx(1.0)
    assert spearman(x, -np.exp(x)) == pytest.approx(-1.0)
    assert spearman(np.array([1.0, 2.0, 3.0, 4.0]), np.array([1.0, 3.0, 2.0, 4.0])) == \
        pytest.approx(0.8)  # 1 - 6 * 2 / (4 * 15)
    assert math.isnan(spearman(np.array([1.0, 2.0]), np.array([2.0, 1.0])))


def test_spearman_handles_ties() -> None:
    """Tied values share their average rank (as scipy.stats.spearmanr): a constant input has
    no defined correlation (NaN), and tied confidences do not invent a correlation."""
    assert math.isnan(spearman(np.ones(6), np.arange(6.0)))
    a = np.array([5.0, 5.0, 5.0, 5.0, 1.0, 1.0])
    b = np.arange(1.0, 7.0)
    assert spearman(a, b) == pytest.approx(-0.8280786712108251)  # scipy's value
