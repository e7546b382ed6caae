"""Keypoint sigmas at the edge: the confidence → pixel-error table
(:func:`edge_agent.metrics.sigma_calibration` / :func:`sigma_from_confidence`) recovers a known
error model from synthetic data; the keypoint card validates its table; the shipped keypoint
model is calibrated and its observations on a rendered view carry sigmas; the edge pipeline
puts them into :attr:`protocol.messages.Detection.keypoint_sigmas_px`."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from edge_agent.metrics import sigma_calibration, sigma_from_confidence
from edge_agent.model_cards import KeypointCard, ModelError, default_model_dir

K = 12  # the paper robot's keypoints


def _true_sigma(c: np.ndarray) -> np.ndarray:
    return 10.0 * (1.0 - c) + 0.5


def _synthetic(n: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(errors, confidences): confidence uniform in [0, 1], u and v errors each ~ N(0, sigma(c));
    the error is their 2-D distance, as the calibration measures it (per-axis sigma out)."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(0.0, 1.0, n)
    s = _true_sigma(c)
    e = np.hypot(rng.normal(0.0, s), rng.normal(0.0, s))
    return e, c


# --------------------------------------------------------------------------------------------
# sigma_calibration / sigma_from_confidence
# --------------------------------------------------------------------------------------------


def test_calibration_recovers_a_known_error_model() -> None:
    e, c = _synthetic()
    table = sigma_calibration(e, c, bins=8, min_per_bin=20)
    conf = np.array(table["confidence"])
    sig = np.array(table["sigma_crop_px"])
    assert conf.shape == sig.shape == (8,)
    assert np.all(np.diff(conf) > 0), conf
    assert np.all(np.diff(sig) <= 0), sig
    assert conf[0] < 0.15 and conf[-1] > 0.85  # bin medians span the confidence range
    # truth per bin: the RMS of sigma(c) over the same confidence-quantile bins
    order = np.argsort(c, kind="stable")
    truth = np.array([math.sqrt(float(np.mean(_true_sigma(c[part]) ** 2)))
                      for part in np.array_split(order, 8)])
    # 15 %: the seeded estimate is within 5 %; a mean |error| instead of the RMS is 20 % low
    np.testing.assert_allclose(sig, truth, rtol=0.15)
    # the bin medians are the medians of those bins
    medians = np.array([np.median(c[part]) for part in np.array_split(order, 8)])
    np.testing.assert_allclose(conf, medians)


def test_sigma_from_confidence_interpolates_the_known_model() -> None:
    e, c = _synthetic(n=8000, seed=1)
    table = sigma_calibration(e, c, bins=8, min_per_bin=20)
    query = np.array([0.2, 0.35, 0.5, 0.65, 0.8])
    got = sigma_from_confidence(query, table)
    assert got is not None and got.shape == query.shape
    np.testing.assert_allclose(got, _true_sigma(query), rtol=0.2)
    # held flat outside the table: the end bins' sigmas
    lo_hi = sigma_from_confidence(np.array([-1.0, 0.0, 1.0, 2.0]), table)
    assert lo_hi is not None
    assert lo_hi[0] == lo_hi[1] == table["sigma_crop_px"][0]
    assert lo_hi[2] == lo_hi[3] == table["sigma_crop_px"][-1]
    # keeps the input's shape (the edge asks for (n, K) at once)
    grid = sigma_from_confidence(np.full((3, K), 0.5), table)
    assert grid is not None and grid.shape == (3, K)


def test_sigma_from_confidence_is_linear_between_bin_medians() -> None:
    table = {"confidence": [0.2, 0.6, 0.9], "sigma_crop_px": [8.0, 4.0, 1.0]}
    got = sigma_from_confidence(np.array([0.2, 0.4, 0.6, 0.75, 0.9]), table)
    np.testing.assert_allclose(got, [8.0, 6.0, 4.0, 2.5, 1.0])


def test_a_more_confident_bin_is_never_less_certain() -> None:
    """Errors that *grow* with confidence (a badly behaved network): the table is flattened
    to the least confident bin's RMS rather than reporting confident keypoints as worse."""
    rng = np.random.default_rng(2)
    c = rng.uniform(0.0, 1.0, 3000)
    e = np.abs(rng.normal(0.0, 1.0 + 9.0 * c))
    table = sigma_calibration(e, c, bins=6)
    sig = np.array(table["sigma_crop_px"])
    assert sig.shape == (6,)
    np.testing.assert_array_equal(sig, np.full(6, sig[0]))
    order = np.argsort(c)
    first = order[: len(order) // 6 + (len(order) % 6 > 0)]
    assert sig[0] == pytest.approx(math.sqrt(float(np.mean(e[first] ** 2)) / 2.0))


def test_too_few_points_give_an_empty_table() -> None:
    e, c = _synthetic(n=19)
    table = sigma_calibration(e, c, bins=8, min_per_bin=20)
    assert table == {"confidence": [], "sigma_crop_px": []}
    assert sigma_from_confidence(np.array([0.5, 0.9]), table) is None
    assert sigma_calibration(np.zeros(0), np.zeros(0)) == {"confidence": [],
                                                           "sigma_crop_px": []}


def test_the_bin_count_shrinks_to_keep_min_per_bin() -> None:
    e, c = _synthetic(n=45)
    table = sigma_calibration(e, c, bins=8, min_per_bin=20)
    assert len(table["confidence"]) == len(table["sigma_crop_px"]) == 2
    e, c = _synthetic(n=20)
    assert len(sigma_calibration(e, c, bins=8, min_per_bin=20)["confidence"]) == 1


def test_nans_are_ignored() -> None:
    e, c = _synthetic(n=2000, seed=3)
    clean = sigma_calibration(e, c)
    rng = np.random.default_rng(4)
    e_bad = e.copy()
    c_bad = c.copy()
    e_bad[rng.choice(len(e), 50, replace=False)] = np.nan
    c_bad[rng.choice(len(c), 50, replace=False)] = np.nan
    ok = np.isfinite(e_bad) & np.isfinite(c_bad)
    with_nans = sigma_calibration(e_bad, c_bad)
    assert with_nans == sigma_calibration(e_bad[ok], c_bad[ok])
    assert all(math.isfinite(v) for v in with_nans["confidence"] + with_nans["sigma_crop_px"])
    np.testing.assert_allclose(with_nans["sigma_crop_px"], clean["sigma_crop_px"], rtol=0.1)
    # NaNs do not count towards the minimum: 19 finite points are still too few
    e19, c19 = _synthetic(n=19)
    e_pad = np.concatenate([e19, np.full(100, np.nan)])
    c_pad = np.concatenate([c19, rng.uniform(size=100)])
    assert sigma_calibration(e_pad, c_pad, min_per_bin=20)["confidence"] == []


@pytest.mark.parametrize("table", [
    {},
    {"confidence": [], "sigma_crop_px": []},
    {"confidence": [0.5, 0.9], "sigma_crop_px": [2.0]},
])
def test_sigma_from_an_unusable_table_is_none(table: dict) -> None:
    assert sigma_from_confidence(np.array([0.5]), table) is None


# --------------------------------------------------------------------------------------------
# KeypointCard
# --------------------------------------------------------------------------------------------


def _shipped_card_doc() -> dict:
    return json.loads((default_model_dir() / "keypoints.json").read_text(encoding="utf-8"))


def _write_card(folder: Path, doc: dict) -> Path:
    path = folder / "keypoints.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    return path


@pytest.mark.parametrize(("calibration", "what"), [
    ({"confidence": [0.5, 0.8, 0.9], "sigma_crop_px": [3.0, 2.0]}, "unequal lengths"),
    ({"confidence": [0.9, 0.8, 0.5], "sigma_crop_px": [3.0, 2.0, 1.0]}, "descending"),
    ({"confidence": [0.5, 0.8, 0.9], "sigma_crop_px": [3.0, 0.0, 1.0]}, "zero sigma"),
    ({"confidence": [0.5, 0.8, 0.9], "sigma_crop_px": [3.0, 2.0, -1.0]}, "negative sigma"),
    ({"confidence": [0.5, 0.8, 0.9], "sigma_crop_px": [3.0, float("nan"), 1.0]}, "NaN"),
    ({"confidence": [0.5, 0.8], "sigma_crop_px": [3.0, float("inf")]}, "infinite sigma"),
    ({"confidence": [0.5, 0.8]}, "no sigmas"),
    ({"sigma_crop_px": [3.0, 2.0]}, "no confidences"),
    ({"confidence": [[0.5, 0.8]], "sigma_crop_px": [[3.0, 2.0]]}, "2-D"),
    ({"confidence": ["a", "b"], "sigma_crop_px": [3.0, 2.0]}, "strings"),
    ([0.5, 3.0], "not a map"),
])
def test_card_with_a_bad_calibration_is_a_model_error(tmp_path: Path, calibration: object,
                                                      what: str) -> None:
    doc = _shipped_card_doc()
    doc["sigma_calibration"] = calibration
    path = _write_card(tmp_path, doc)
    with pytest.raises(ModelError, match="sigma_calibration") as info:
        KeypointCard.read(path)
    assert str(path) in str(info.value), what


def test_card_without_a_calibration_reads_as_uncalibrated(tmp_path: Path) -> None:
    doc = _shipped_card_doc()
    doc.pop("sigma_calibration", None)
    card = KeypointCard.read(_write_card(tmp_path, doc))
    assert card.sigma_calibration == {}
    assert "Not calibrated" in card.markdown()


def test_card_calibration_survives_write_and_read(tmp_path: Path) -> None:
    doc = _shipped_card_doc()
    table = {"confidence": [0.4, 0.7, 0.8, 0.95], "sigma_crop_px": [9.0, 3.0, 3.0, 0.8]}
    doc["sigma_calibration"] = table
    card = KeypointCard.read(_write_card(tmp_path, doc))
    assert card.sigma_calibration == table
    out = tmp_path / "out"
    out.mkdir()
    card.write(out)
    again = KeypointCard.read(out / "keypoints.json")
    assert again.sigma_calibration == table
    md = (out / "keypoints.md").read_text(encoding="utf-8")
    assert "Keypoint uncertainty" in md and "| 0.950 | 0.80 |" in md


# --------------------------------------------------------------------------------------------
# the shipped model and the edge pipeline
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def shipped():
    pytest.importorskip("onnxruntime")
    from edge_agent.models import RobotKeypointPipeline

    return RobotKeypointPipeline.from_folder(None, threads=1)


@pytest.fixture(scope="module")
def views() -> list:
    """Four rendered site views (848x480) with the robot fully in the image, and their
    labels."""
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    gen = SampleGenerator(load_scenario(), "site", seed=5)
    out = []
    for i in range(24):
        sample = gen(i)
        r = sample.robots[0]
        if r.bbox_xyxy is not None and r.in_image.all():
            out.append(sample)
        if len(out) == 4:
            return out
    pytest.fail("fewer than 4 site views with the whole robot in the image among 24")


def test_shipped_keypoint_model_is_calibrated(shipped) -> None:
    assert shipped.keypoints.calibrated
    cal = shipped.keypoints.card.sigma_calibration
    conf, sig = np.array(cal["confidence"]), np.array(cal["sigma_crop_px"])
    assert len(conf) >= 2 and conf.shape == sig.shape
    assert np.all(np.diff(conf) >= 0) and np.all(np.diff(sig) <= 0) and np.all(sig > 0)
    assert np.all((conf >= 0) & (conf <= 1))


def test_shipped_observations_carry_calibrated_sigmas(shipped, views: list) -> None:
    """On rendered views: sigma_px (K,), finite, > 0; sigma times the crop scale is the card's
    table at the keypoint's confidence; the sigmas are of the size of the real errors."""
    from edge_agent.crop import crop_transform

    card = shipped.keypoints.card
    ratios = []
    for sample in views:
        found = shipped(sample.image_rgb, max_robots=1)
        assert len(found) == 1, sample.index
        obs = found[0]
        assert obs.sigma_px is not None and obs.sigma_px.shape == (K,)
        assert np.all(np.isfinite(obs.sigma_px)) and np.all(obs.sigma_px > 0)
        tf = crop_transform(obs.bbox_xyxy, card.input_w, card.input_h,
                            padding=card.crop_padding)
        want = sigma_from_confidence(obs.confidence, card.sigma_calibration) / tf.scale
        np.testing.assert_allclose(obs.sigma_px, want, rtol=1e-6)
        # lower confidence, larger sigma (within one crop)
        order = np.argsort(obs.confidence)
        assert np.all(np.diff(obs.sigma_px[order]) <= 1e-9)
        err = np.linalg.norm(obs.keypoints_px - sample.robots[0].keypoints_px, axis=1)
        ratios.append(err / obs.sigma_px)
    ratio = np.concatenate(ratios)
    # a calibration off by an order of magnitude either way would fail this
    assert 0.1 < float(np.median(ratio)) < 3.0, np.median(ratio)
    assert float(np.mean(ratio <= 3.0)) >= 0.9, ratio


def test_edge_pipeline_puts_the_sigmas_into_the_detection(shipped, views: list) -> None:
    from edge_agent.frames import Frame
    from edge_agent.pipeline import SIGMA_MAX_PX, SIGMA_MIN_PX, EdgePipeline
    from protocol import codec
    from protocol.messages import RobotDetections

    sample = views[0]
    pipe = EdgePipeline(sample.camera.camera_id, shipped, min_score=0.3, max_robots=1)
    msg, _ = pipe.process(Frame(sample.image_rgb, 123_456, 7))
    assert len(msg.detections) == 1
    det = msg.detections[0]
    assert det.keypoint_sigmas_px is not None and det.keypoint_sigmas_px.shape == (K,)
    obs = shipped(sample.image_rgb, min_score=0.3, max_robots=1)[0]
    np.testing.assert_allclose(det.keypoint_sigmas_px,
                               np.clip(obs.sigma_px, SIGMA_MIN_PX, SIGMA_MAX_PX))
    np.testing.assert_allclose(det.keypoints_px, obs.keypoints_px)
    back = codec.decode(codec.encode(msg), RobotDetections)
    np.testing.assert_array_equal(back.detections[0].keypoint_sigmas_px, det.keypoint_sigmas_px)


def test_uncalibrated_keypoint_model_sends_no_sigmas(tmp_path: Path, views: list) -> None:
    """The shipped networks with a card that has no table: observations and detections carry
    no sigmas (the backend then weights by confidence)."""
    pytest.importorskip("onnxruntime")
    from edge_agent.frames import Frame
    from edge_agent.models import RobotKeypointPipeline
    from edge_agent.pipeline import EdgePipeline

    src = default_model_dir()
    for name in ("detector.onnx", "detector.json", "keypoints.onnx"):
        shutil.copy(src / name, tmp_path / name)
    doc = _shipped_card_doc()
    doc.pop("sigma_calibration", None)
    _write_card(tmp_path, doc)
    models = RobotKeypointPipeline.from_folder(tmp_path, threads=1)
    assert not models.keypoints.calibrated
    sample = views[0]
    found = models(sample.image_rgb, max_robots=1)
    assert len(found) == 1 and found[0].sigma_px is None
    msg, _ = EdgePipeline("cam1", models, max_robots=1).process(Frame(sample.image_rgb, 1, 0))
    assert len(msg.detections) == 1 and msg.detections[0].keypoint_sigmas_px is None
    # no boxes: an empty (0, K) sigma array only when calibrated
    kp, conf, sig = models.keypoints.estimate_with_sigma(sample.image_rgb, np.zeros((0, 5)))
    assert kp.shape == (0, K, 2) and conf.shape == (0, K) and sig is None


class _StubModels:
    """A stand-in for :class:`RobotKeypointPipeline` returning fixed observations."""

    model_id = "hsr/stub"

    def __init__(self, observations: list) -> None:
        from edge_agent.networks import StageTimes

        self.observations = observations
        self.times = StageTimes(1.0, 1.0)

    def __call__(self, image_rgb: np.ndarray, *, min_score: float, max_robots: int) -> list:
        return self.observations


def test_edge_pipeline_keeps_unusable_sigmas_from_invalidating_the_message() -> None:
    """NaN / infinite / zero / huge sigmas become [SIGMA_MIN_PX, SIGMA_MAX_PX]: the keypoint is
    uncertain, the message stays valid."""
    from edge_agent.frames import Frame
    from edge_agent.networks import RobotObservation
    from edge_agent.pipeline import SIGMA_MAX_PX, SIGMA_MIN_PX, EdgePipeline

    sig = np.array([1.0, np.nan, np.inf, 0.0, 1e9, 2.5])
    obs = RobotObservation(np.array([10.0, 10.0, 50.0, 60.0]), 0.9,
                           np.tile([[20.0, 30.0]], (6, 1)), np.full(6, 0.8), sig)
    msg, _ = EdgePipeline("cam1", _StubModels([obs])).process(
        Frame(np.zeros((80, 100, 3), np.uint8), 5, 1))
    got = msg.detections[0].keypoint_sigmas_px
    np.testing.assert_array_equal(got, [1.0, SIGMA_MAX_PX, SIGMA_MAX_PX, SIGMA_MIN_PX,
                                        SIGMA_MAX_PX, 2.5])
