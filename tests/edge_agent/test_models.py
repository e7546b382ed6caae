"""The edge's networks at run time (onnxruntime, no torch): the pipeline loads a trained model
folder and returns well-formed observations, onnxruntime reproduces the torch reference outputs
stored beside each model, it runs with torch unimportable, and every broken model folder or
card gives a ``ModelError`` that names the file (bad images a ``ValueError``)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from edge_agent.crop import to_nchw
from edge_agent.model_cards import (
    DetectorCard,
    KeypointCard,
    ModelError,
    card_path,
    default_model_dir,
    export_differences,
    model_files,
    reference_path,
)
from edge_agent.models import RobotKeypointPipeline
from edge_agent.networks import Detector, KeypointEstimator, RobotObservation
from protocol.errors import SmartedgeError

REPO_ROOT = Path(__file__).resolve().parents[2]
K = 12  # the paper robot's keypoints


@pytest.fixture
def model_copy(tiny_models: Path, tmp_path: Path) -> Path:
    """A private copy of the tiny models' ONNX files and cards, free to break."""
    folder = tmp_path / "models"
    folder.mkdir()
    for kind in ("detector", "keypoints"):
        for suffix in (".onnx", ".json"):
            shutil.copy(tiny_models / f"{kind}{suffix}", folder / f"{kind}{suffix}")
    return folder


@pytest.fixture(scope="module")
def frame() -> np.ndarray:
    """A rendered 256x192 view of the paper lab with the robot in it."""
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    gen = SampleGenerator(load_scenario(), "randomized", seed=7, width=256, height=192)
    for i in range(8):
        sample = gen(i)
        if sample.robots[0].bbox_xyxy is not None:
            return sample.image_rgb
    pytest.fail("no randomized view with the robot among the first 8")


def _edit_card(path: Path, **changes: object) -> None:
    doc = json.loads(path.read_text(encoding="utf-8"))
    doc.update(changes)
    path.write_text(json.dumps(doc), encoding="utf-8")


# --------------------------------------------------------------------------------------------
# a working model folder
# --------------------------------------------------------------------------------------------


def test_pipeline_from_folder_returns_well_formed_observations(tiny_models: Path,
                                                               frame: np.ndarray) -> None:
    """The pipeline loads both models and their cards from a folder; with every detection
    admitted it returns up to ``max_robots`` observations, best first: a box, a score, K
    keypoints in frame pixels and K confidences in [0, 1]; stage timings are recorded."""
    pipe = RobotKeypointPipeline.from_folder(tiny_models, threads=1)
    assert isinstance(pipe.detector.card, DetectorCard)
    assert isinstance(pipe.keypoints.card, KeypointCard)
    assert pipe.keypoints.num_keypoints == K
    assert pipe.model_id == f"hsr/{tiny_models.name}"
    obs = pipe(frame, min_score=0.0, max_robots=3)
    assert len(obs) == 3
    scores = [o.score for o in obs]
    assert scores == sorted(scores, reverse=True)
    for o in obs:
        assert isinstance(o, RobotObservation) and isinstance(o.score, float)
        assert o.bbox_xyxy.shape == (4,)
        assert o.keypoints_px.shape == (K, 2) and np.all(np.isfinite(o.keypoints_px))
        assert o.confidence.shape == (K,)
        assert np.all((o.confidence >= 0.0) & (o.confidence <= 1.0))
        assert 0.0 <= o.score <= 1.0
    assert pipe.times.detector_ms > 0 and pipe.times.keypoints_ms > 0
    # a threshold no detection reaches: nothing
    assert pipe(frame, min_score=1.01) == []


def test_pipeline_with_explicit_files_and_matching_names(tiny_models: Path) -> None:
    """Explicit ONNX paths work; the site's keypoint names equal to the card's are accepted."""
    names = KeypointCard.read(tiny_models / "keypoints.json").keypoint_names
    pipe = RobotKeypointPipeline(tiny_models / "detector.onnx", tiny_models / "keypoints.onnx",
                                 threads=1, keypoint_names=tuple(names))
    assert pipe.folder == tiny_models
    assert model_files(tiny_models) == (tiny_models / "detector.onnx",
                                        tiny_models / "keypoints.onnx")


def test_stages_map_back_to_frame_pixels(tiny_models: Path, frame: np.ndarray) -> None:
    """Detector boxes come back in the frame's pixels whatever its size (a frame and the same
    frame at twice the size give boxes twice as large, in edge coordinates); keypoint
    estimates for several boxes keep their order and shapes; no boxes give empty arrays."""
    import cv2

    det = Detector(tiny_models / "detector.onnx", threads=1)
    boxes = det.detect(frame, min_score=0.0, max_detections=2)
    assert boxes.shape == (2, 5)
    big = cv2.resize(frame, (512, 384), interpolation=cv2.INTER_NEAREST)
    boxes_big = det.detect(big, min_score=0.0, max_detections=2)
    np.testing.assert_allclose(boxes_big[:, :4] + 0.5, 2 * (boxes[:, :4] + 0.5), atol=1e-3)
    kp = KeypointEstimator(tiny_models / "keypoints.onnx", threads=1)
    pts, conf = kp.estimate(frame, boxes)
    assert pts.shape == (2, K, 2) and conf.shape == (2, K) and conf.dtype == np.float64
    one, _ = kp.estimate(frame, boxes[1:])
    np.testing.assert_allclose(one[0], pts[1], atol=1e-4)
    empty_pts, empty_conf = kp.estimate(frame, np.zeros((0, 5)))
    assert empty_pts.shape == (0, K, 2) and empty_conf.shape == (0, K)


def test_frames_in_one_batch_get_what_they_get_alone(tiny_models: Path,
                                                     frame: np.ndarray) -> None:
    """:meth:`RobotKeypointPipeline.run_many` (several frames, e.g. the cameras of one
    capture, each network run once) returns per frame what a call with that frame alone
    returns, in order; frames of other sizes and frames without robots take part.
    (On one machine the numbers are the same; a batch may sum in another order elsewhere,
    hence the tolerance, as for several boxes of one frame above.)"""
    import cv2

    pipe = RobotKeypointPipeline.from_folder(tiny_models, threads=1)
    frames = [frame, frame[:, ::-1].copy(),
              cv2.resize(frame, (512, 384), interpolation=cv2.INTER_LINEAR), frame]
    batch = pipe.run_many(frames, min_score=0.0, max_robots=2)
    alone = [pipe(f, min_score=0.0, max_robots=2) for f in frames]
    assert [len(b) for b in batch] == [len(a) for a in alone] == [2, 2, 2, 2]
    for b_obs, a_obs in zip(batch, alone, strict=True):
        for b, a in zip(b_obs, a_obs, strict=True):
            np.testing.assert_allclose(b.bbox_xyxy, a.bbox_xyxy, atol=1e-4)
            assert b.score == pytest.approx(a.score, abs=1e-5)
            np.testing.assert_allclose(b.keypoints_px, a.keypoints_px, atol=1e-4)
            np.testing.assert_allclose(b.confidence, a.confidence, atol=1e-5)
    assert pipe.run_many([]) == []
    nothing = pipe.run_many([frame, frame], min_score=1.01)
    assert nothing == [[], []]


def test_edge_pipelines_of_several_cameras_share_one_batch(tiny_models: Path,
                                                          frame: np.ndarray) -> None:
    """:func:`edge_agent.pipeline.process_batch`: the frames of several cameras (one
    :class:`EdgePipeline` each, shared models) give each camera's own message, as
    :meth:`EdgePipeline.process` makes it; pipelines on other models are refused."""
    from edge_agent.frames import Frame
    from edge_agent.pipeline import EdgePipeline, process_batch

    pipe = RobotKeypointPipeline.from_folder(tiny_models, threads=1)
    cams = [EdgePipeline(c, pipe, min_score=0.0, max_robots=2) for c in ("cam1", "cam2")]
    frames = [Frame(frame, 1_000, 3), Frame(frame[::-1].copy(), 2_000, 4)]
    batch = process_batch(list(zip(cams, frames, strict=True)))
    alone = [p.process(f)[0] for p, f in zip(cams, frames, strict=True)]
    for (msg, latency), ref in zip(batch, alone, strict=True):
        assert (msg.camera_id, msg.stamp_ns, msg.seq, msg.model_id) == (
            ref.camera_id, ref.stamp_ns, ref.seq, ref.model_id)
        assert len(msg.detections) == len(ref.detections) == 2
        for d, r in zip(msg.detections, ref.detections, strict=True):
            np.testing.assert_allclose(d.keypoints_px, r.keypoints_px, atol=1e-4)
            np.testing.assert_allclose(d.bbox_xyxy, r.bbox_xyxy, atol=1e-4)
        assert latency.detector_s > 0 and latency.keypoints_s > 0
    assert process_batch([]) == []
    other = RobotKeypointPipeline.from_folder(tiny_models, threads=1)
    with pytest.raises(ValueError, match="share"):
        process_batch([(cams[0], frames[0]), (EdgePipeline("cam3", other), frames[1])])


@pytest.mark.parametrize("kind", ["detector", "keypoints"])
def test_onnxruntime_reproduces_the_stored_reference(tiny_models: Path, kind: str) -> None:
    """onnxruntime on the reference inputs stored by training (uint8 NHWC, through the edge's
    own ``to_nchw``) matches torch's stored outputs within the export tolerances."""
    onnx = tiny_models / f"{kind}.onnx"
    model = (Detector if kind == "detector" else KeypointEstimator)(onnx, threads=1)
    with np.load(reference_path(onnx)) as ref:
        inputs = ref["inputs"]
        expected = {name: ref[name] for name in ref.files if name != "inputs"}
    session = model.session
    got = session.run(None, {session.get_inputs()[0].name: to_nchw(inputs)})
    names = [o.name for o in session.get_outputs()]
    assert set(names) | ({"peaks_ambiguous"} if kind == "detector" else set()) == set(expected)
    ratios = export_differences(expected, dict(zip(names, got, strict=True)))
    assert set(ratios) == set(names)
    assert max(ratios.values()) <= 1.0, f"{kind}: differences / tolerance {ratios}"


def test_pipeline_runs_without_torch(tiny_models: Path) -> None:
    """In a fresh interpreter where importing torch fails, the pipeline loads the folder and
    runs on a frame (the edge board installs no torch)."""
    code = f"""
import sys

class BlockTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError(f"{{name}} is blocked in this test")
        return None

sys.meta_path.insert(0, BlockTorch())
import numpy as np
from edge_agent.models import RobotKeypointPipeline
pipe = RobotKeypointPipeline.from_folder({str(tiny_models)!r}, threads=1)
frame = np.random.default_rng(0).integers(0, 256, (192, 256, 3), dtype=np.uint8)
obs = pipe(frame, min_score=0.0, max_robots=2)
assert len(obs) == 2 and obs[0].keypoints_px.shape == ({K}, 2), obs
assert "torch" not in sys.modules
try:
    import torch
except ImportError:
    print("ok")
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "ok"


def test_default_model_dir_is_the_package_folder() -> None:
    """The shipped models live in ``edge_agent/models`` inside the package."""
    assert default_model_dir() == REPO_ROOT / "edge_agent" / "models"


# --------------------------------------------------------------------------------------------
# broken model folders and cards
# --------------------------------------------------------------------------------------------


def _raises_naming(path: Path, fn, *args, **kwargs) -> ModelError:  # type: ignore[no-untyped-def]
    """``fn(*args, **kwargs)`` raises ModelError (a SmartedgeError) whose message names
    ``path``."""
    with pytest.raises(ModelError) as exc:
        fn(*args, **kwargs)
    assert isinstance(exc.value, SmartedgeError)
    assert str(path) in str(exc.value), str(exc.value)
    return exc.value


@pytest.mark.parametrize("kind", ["detector", "keypoints"])
def test_corrupted_onnx_file(model_copy: Path, kind: str) -> None:
    """Garbage bytes in place of the ONNX file: onnxruntime's error becomes a ModelError."""
    onnx = model_copy / f"{kind}.onnx"
    onnx.write_bytes(b"this is not an onnx model\x00\xff" * 50)
    err = _raises_naming(onnx, RobotKeypointPipeline.from_folder, model_copy, threads=1)
    assert "cannot load" in str(err)


def test_truncated_onnx_file(model_copy: Path) -> None:
    """A half-written ONNX file is refused the same way."""
    onnx = model_copy / "keypoints.onnx"
    onnx.write_bytes(onnx.read_bytes()[: onnx.stat().st_size // 2])
    _raises_naming(onnx, KeypointEstimator, onnx, threads=1)


@pytest.mark.parametrize("kind", ["detector", "keypoints"])
def test_missing_onnx_file(model_copy: Path, kind: str) -> None:
    """A folder without one of the ONNX files."""
    onnx = model_copy / f"{kind}.onnx"
    onnx.unlink()
    err = _raises_naming(onnx, RobotKeypointPipeline.from_folder, model_copy, threads=1)
    assert "not found" in str(err)


@pytest.mark.parametrize("kind", ["detector", "keypoints"])
def test_missing_card(model_copy: Path, kind: str) -> None:
    """An ONNX file without its card beside it; the message says how to get one."""
    card = card_path(model_copy / f"{kind}.onnx")
    card.unlink()
    err = _raises_naming(card, RobotKeypointPipeline.from_folder, model_copy, threads=1)
    assert f"smartedge train {kind}" in str(err)


def test_card_of_the_wrong_kind(model_copy: Path) -> None:
    """The keypoint card copied over the detector's (and the reverse) is refused."""
    det_card, kp_card = model_copy / "detector.json", model_copy / "keypoints.json"
    det_text = det_card.read_text(encoding="utf-8")
    shutil.copy(kp_card, det_card)
    err = _raises_naming(det_card, Detector, model_copy / "detector.onnx", threads=1)
    assert "not a detector model card" in str(err)
    kp_card.write_text(det_text, encoding="utf-8")
    err = _raises_naming(kp_card, KeypointEstimator, model_copy / "keypoints.onnx", threads=1)
    assert "not a keypoints model card" in str(err)


@pytest.mark.parametrize("version", [2, 0, None, "1"])
def test_card_with_a_wrong_version(model_copy: Path, version: object) -> None:
    """A card of another format version is refused, naming both versions."""
    card = model_copy / "keypoints.json"
    _edit_card(card, version=version)
    err = _raises_naming(card, RobotKeypointPipeline.from_folder, model_copy, threads=1)
    assert repr(version) in str(err)


def test_card_that_is_not_json_or_lacks_fields(model_copy: Path) -> None:
    """Unreadable JSON, a JSON list and a card missing a field are refused."""
    card = model_copy / "detector.json"
    onnx = model_copy / "detector.onnx"
    original = card.read_text(encoding="utf-8")
    card.write_text("{not json", encoding="utf-8")
    assert "cannot read" in str(_raises_naming(card, Detector, onnx, threads=1))
    card.write_text("[1, 2]", encoding="utf-8")
    _raises_naming(card, Detector, onnx, threads=1)
    doc = json.loads(original)
    del doc["input_w"]
    card.write_text(json.dumps(doc), encoding="utf-8")
    assert "input_w" in str(_raises_naming(card, Detector, onnx, threads=1))


def test_card_whose_input_size_does_not_match_the_model(model_copy: Path) -> None:
    """A card claiming another input size than the ONNX graph's is refused."""
    _edit_card(model_copy / "keypoints.json", input_w=128)
    onnx = model_copy / "keypoints.onnx"
    assert "do not match the card" in str(_raises_naming(onnx, KeypointEstimator, onnx,
                                                          threads=1))


def test_model_with_other_keypoint_names(model_copy: Path) -> None:
    """The site's robot model has 3 keypoints, the model 12: refused, naming the keypoint
    model and both counts."""
    onnx = model_copy / "keypoints.onnx"
    err = _raises_naming(onnx, RobotKeypointPipeline.from_folder, model_copy, threads=1,
                         keypoint_names=["base", "head", "hand"])
    assert "12 keypoints" in str(err) and "has 3" in str(err)


def test_renamed_keypoints_in_the_card(model_copy: Path) -> None:
    """Same count, other names (the card edited): also refused."""
    names = KeypointCard.read(model_copy / "keypoints.json").keypoint_names
    _edit_card(model_copy / "keypoints.json", keypoint_names=[*names[:-1], "elsewhere"])
    _raises_naming(model_copy / "keypoints.onnx", RobotKeypointPipeline.from_folder,
                   model_copy, threads=1, keypoint_names=names)


def test_missing_folder(tmp_path: Path) -> None:
    """``from_folder`` of a folder that does not exist."""
    missing = tmp_path / "no-such-models"
    err = _raises_naming(missing, RobotKeypointPipeline.from_folder, missing)
    assert "model folder not found" in str(err)


@pytest.mark.parametrize("image", [
    np.zeros((192, 256, 3), np.float32),
    np.zeros((192, 256, 3), np.uint16),
    np.zeros((192, 256), np.uint8),
    np.zeros((192, 256, 4), np.uint8),
    np.zeros((1, 192, 256, 3), np.uint8),
], ids=["float32", "uint16", "gray", "rgba", "batch"])
def test_invalid_image_input(tiny_models: Path, image: np.ndarray) -> None:
    """Anything but an (H, W, 3) uint8 RGB image is a ValueError naming what it got."""
    pipe = RobotKeypointPipeline.from_folder(tiny_models, threads=1)
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
        pipe(image)


def test_export_differences_allow_a_window_shift_only_where_the_best_bins_tie() -> None:
    """A keypoint may move by up to half a bin where its decode window moved (its confidence
    differs beyond float noise); everywhere else the tight tolerance holds."""
    rng = np.random.default_rng(0)
    want = {"keypoints": rng.uniform(0, 192, (2, K, 2)).astype(np.float32),
            "confidence": rng.uniform(0.8, 1.0, (2, K)).astype(np.float32)}
    same = {k: v.copy() for k, v in want.items()}
    assert max(export_differences(want, same).values()) == 0.0
    moved = {k: v.copy() for k, v in want.items()}
    moved["keypoints"][1, 1, 1] += 0.06  # past 0.05 with the window where it was: fails
    assert export_differences(want, moved)["keypoints"] > 1.0
    moved["confidence"][1, 1] -= 0.001  # the window moved by a bin: half a bin allowed
    assert max(export_differences(want, moved).values()) <= 1.0
    moved["keypoints"][1, 1, 1] += 0.3  # more than half a bin: fails even with a tie
    assert export_differences(want, moved)["keypoints"] > 1.0
    peaks = {"peaks": np.zeros((1, 4)), "peaks_ambiguous": np.array([[True, False, False, False]])}
    assert export_differences(peaks, {"peaks": np.array([[1.0, 0, 0, 0]])})["peaks"] == 0.0
    assert export_differences(peaks, {"peaks": np.array([[0, 1.0, 0, 0]])})["peaks"] > 1.0
