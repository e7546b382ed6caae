"""Training side (torch): the detector's target encoding decodes back to the box, SimCC labels
and the exported keypoint decode agree, the focal loss prefers good predictions, the config
refuses leaky held-out sets, and a tiny ``smartedge train`` run of each kind produces a model,
its cards and the export reference, resumes from its checkpoint and catches an ONNX file that
does not match the torch model."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs torch (train extra)")

import torch.nn.functional as F  # noqa: E402

from edge_agent.model_cards import CARD_VERSION, DetectorCard, KeypointCard, reference_path  # noqa: E402
from edge_agent.networks import decode_detections  # noqa: E402
from tests.edge_agent.conftest import train_tiny  # noqa: E402
from training.data import Geometry, SetSpec, render_set  # noqa: E402
from training.nets import KeypointNet, KeypointOutput, RobotDetector  # noqa: E402
from training.targets import (  # noqa: E402
    detector_targets,
    focal_loss,
    frame_to_input,
    keypoint_weights,
    simcc_targets,
)
from training.train import TrainConfig, TrainingError, check_onnxruntime, export_onnx  # noqa: E402

STRIDE = RobotDetector.stride
DET_W, DET_H = 128, 96  # the --tiny detector input
OUT_W, OUT_H = DET_W // STRIDE, DET_H // STRIDE
TINY = Geometry(det_w=DET_W, det_h=DET_H, crop_w=64, crop_h=96, frame_w=256, frame_h=192)
TRAIN = (SetSpec("randomized", 1, 16), SetSpec("site", 2, 8))
VAL = (SetSpec("randomized", 1001, 8), SetSpec("site", 1002, 8))


def _peaks(heat: np.ndarray) -> np.ndarray:
    """The exported graph's peak extraction: heat where it is a 3x3 local maximum, else 0."""
    t = torch.from_numpy(heat)
    return (t * (F.max_pool2d(t, 3, 1, 1) == t).to(t.dtype)).numpy()


# --------------------------------------------------------------------------------------------
# detector targets ↔ decoding
# --------------------------------------------------------------------------------------------

BOXES_IN = np.array([
    [20.0, 10.0, 60.0, 90.0],  # cell-aligned
    [33.3, 17.8, 71.9, 52.1],  # arbitrary sub-pixel edges
    [-0.5, -0.5, 12.2, 30.7],  # touching the top-left image edge
    [100.4, 60.6, 127.5, 95.5],  # touching the bottom-right image edge
    [64.0, 40.0, 66.5, 43.0],  # a few pixels
])


@pytest.mark.parametrize("box", BOXES_IN)
def test_detector_targets_decode_back_to_the_box(box: np.ndarray) -> None:
    """heat/log-size/offset targets of a known box, read as the exported graph's outputs
    (peaks = 3x3 maxima of the heat, size = exp(log-size)), decode to one box within 0.5 px
    with score 1."""
    heat, logsize, off, mask = detector_targets(box[None], OUT_W, OUT_H, STRIDE)
    assert heat.shape == mask.shape == (1, 1, OUT_H, OUT_W)
    assert logsize.shape == off.shape == (1, 2, OUT_H, OUT_W)
    assert mask.sum() == 1.0 and heat.max() == 1.0
    assert np.all((heat >= 0) & (heat <= 1))
    size = np.exp(logsize)
    boxes = decode_detections(_peaks(heat)[0], size[0], off[0], STRIDE, min_score=0.3)
    assert boxes.shape == (1, 5)
    np.testing.assert_allclose(boxes[0, :4], box, atol=0.5)
    assert boxes[0, 4] == pytest.approx(1.0)


def test_detector_targets_batch_and_missing_robot() -> None:
    """A batch keeps each image's target in its own row; a NaN row (no robot) is all zero and
    decodes to no detection."""
    boxes = np.stack([BOXES_IN[1], np.full(4, np.nan), BOXES_IN[0]])
    heat, logsize, off, mask = detector_targets(boxes, OUT_W, OUT_H, STRIDE)
    assert heat.shape[0] == 3
    assert not heat[1].any() and not mask[1].any() and not logsize[1].any() and not off[1].any()
    assert len(decode_detections(_peaks(heat)[1], np.exp(logsize[1]), off[1], STRIDE)) == 0
    for i in (0, 2):
        got = decode_detections(_peaks(heat)[i], np.exp(logsize[i]), off[i], STRIDE)
        np.testing.assert_allclose(got[0, :4], boxes[i], atol=0.5)


def test_frame_to_input_scales_box_edges() -> None:
    """Frame → detector input keeps edge coordinates exact: the whole-frame box maps to the
    whole-input box, and a box's centre maps like any pixel position."""
    frame = np.array([848, 480])
    whole = np.array([-0.5, -0.5, 847.5, 479.5])
    np.testing.assert_allclose(frame_to_input(whole, frame, DET_W, DET_H),
                               [-0.5, -0.5, DET_W - 0.5, DET_H - 0.5])
    box = np.array([[100.0, 50.0, 300.0, 400.0]])
    got = frame_to_input(box, frame[None], DET_W, DET_H)
    np.testing.assert_allclose(got[0, 2] - got[0, 0], 200.0 * DET_W / 848)
    np.testing.assert_allclose(got[0, 3] - got[0, 1], 350.0 * DET_H / 480)


def test_focal_loss_prefers_the_right_heatmap() -> None:
    """The loss of logits matching the target heat is far below that of an empty, an inverted
    or a shifted prediction; it is finite and non-negative."""
    heat, *_ = detector_targets(BOXES_IN[:2], OUT_W, OUT_H, STRIDE)
    target = torch.from_numpy(heat)
    good = torch.logit(target.clamp(1e-3, 1 - 1e-3))
    empty = torch.full_like(target, -6.0)
    inverted = torch.logit((1 - target).clamp(1e-3, 1 - 1e-3))
    shifted = torch.roll(good, shifts=(5, 7), dims=(2, 3))
    losses = {name: float(focal_loss(x, target))
              for name, x in [("good", good), ("empty", empty), ("inverted", inverted),
                              ("shifted", shifted)]}
    assert all(np.isfinite(v) and v >= 0 for v in losses.values())
    for bad in ("empty", "inverted", "shifted"):
        assert losses["good"] < 0.5 * losses[bad], losses


# --------------------------------------------------------------------------------------------
# SimCC labels ↔ the exported keypoint decode
# --------------------------------------------------------------------------------------------


def test_simcc_targets_peak_at_the_right_bin_and_sum_to_one() -> None:
    """Each label is a distribution over bins (sum 1) peaking at the bin nearest
    ``coordinate * split``, with its mean at the coordinate away from the borders."""
    split, bins = 2, 64 * 2
    kp = torch.tensor([[7.0, 10.3, 31.74], [0.0, 50.5, 63.0]], dtype=torch.float64)
    t = simcc_targets(kp, bins, split, sigma_px=1.5)
    assert t.shape == (2, 3, bins)
    torch.testing.assert_close(t.sum(-1), torch.ones(2, 3, dtype=torch.float64))
    expected_bin = torch.round(kp * split).long()
    assert torch.equal(t.argmax(-1), expected_bin)
    centres = torch.arange(bins, dtype=torch.float64) / split
    mean = (t * centres).sum(-1)
    torch.testing.assert_close(mean[0], kp[0], atol=1e-3, rtol=0)


def test_keypoint_decode_of_a_sharp_label_returns_the_coordinate() -> None:
    """The exported graph's decode (soft-argmax in a window around the best bin) of logits
    built from a sharp SimCC label returns the labelled crop coordinate within 0.05 px, with a
    confidence near 1."""
    net = KeypointNet(3, 64, 96).eval()
    kp = torch.tensor([[[10.3, 20.7], [31.75, 3.0], [58.6, 91.25]]])  # (1, K, 2) x, y
    lx = torch.log(simcc_targets(kp[..., 0], 64 * net.split, net.split, 0.5).clamp_min(1e-30))
    ly = torch.log(simcc_targets(kp[..., 1], 96 * net.split, net.split, 0.5).clamp_min(1e-30))
    net.forward_train = lambda x: KeypointOutput(lx, ly)  # type: ignore[method-assign]
    with torch.no_grad():
        coords, conf = net(torch.zeros(1, 3, 96, 64))
    assert coords.shape == (1, 3, 2) and conf.shape == (1, 3)
    torch.testing.assert_close(coords, kp, atol=0.05, rtol=0)
    assert torch.all(conf > 0.99) and torch.all(conf <= 1.0 + 1e-6)


def test_keypoint_weights_keep_keypoints_inside_the_crop_and_image() -> None:
    """Weight 1 only for keypoints inside the crop's pixel area and in the frame."""
    kp = np.array([[[0.0, 0.0], [-0.6, 5.0], [63.4, 95.4], [63.6, 10.0], [30.0, 40.0]]])
    in_image = np.array([[True, True, True, True, False]])
    np.testing.assert_array_equal(keypoint_weights(kp, in_image, 64, 96), [[1, 0, 1, 0, 0]])


# --------------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------------


def test_train_config_rejects_leaky_or_unknown_settings() -> None:
    """Held-out sets on a training seed, an unknown kind and zero steps are refused."""
    TrainConfig("detector", TRAIN, VAL)  # fine
    with pytest.raises(TrainingError, match=r"reuse training seed\(s\) \[2\]"):
        TrainConfig("keypoints", TRAIN, (SetSpec("site", 2, 8),))
    with pytest.raises(TrainingError, match=r"reuse training seed\(s\) \[1\]"):
        TrainConfig("detector", TRAIN, (SetSpec("site", 1, 8),))  # another mode, same seed
    with pytest.raises(TrainingError, match="segmenter"):
        TrainConfig("segmenter", TRAIN, VAL)
    with pytest.raises(TrainingError, match="steps 0"):
        TrainConfig("detector", TRAIN, VAL, steps=0)


# --------------------------------------------------------------------------------------------
# the tiny end-to-end run
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["detector", "keypoints"])
def test_tiny_run_writes_model_cards_and_reference(tiny_models: Path, kind: str) -> None:
    """The run wrote the ONNX file, the JSON card (readable by the edge pipeline: held-out
    metrics per set, 5 steps, the export check), the Markdown card and the torch reference
    outputs on fixed inputs; the checkpoint records 5 steps."""
    onnx = tiny_models / f"{kind}.onnx"
    assert onnx.is_file() and onnx.stat().st_size > 100_000
    card_cls = DetectorCard if kind == "detector" else KeypointCard
    card = card_cls.read(tiny_models / f"{kind}.json")
    assert card.version == CARD_VERSION and card.onnx == f"{kind}.onnx"
    assert card.robot_model == "hsr" and len(card.keypoint_names) == 12
    assert card.training["steps"] == 5
    assert card.training["train_sets"] == [{"mode": "randomized", "seed": 1, "count": 16},
                                           {"mode": "site", "seed": 2, "count": 8}]
    assert set(card.metrics) == {"randomized-s1001", "site-s1002"}
    key = "AP@0.5" if kind == "detector" else "median error px"
    assert all(key in figures for figures in card.metrics.values())
    if kind == "detector":
        assert (card.input_w, card.input_h, card.stride) == (DET_W, DET_H, STRIDE)
        assert set(card.onnx_check) == {"peaks", "size", "offset"}
        # a free input size: the edge runs a camera's far band at its own size
        from edge_agent.far_band import FarBand
        from edge_agent.networks import Detector

        det = Detector(onnx, threads=1)
        assert det.runs_far_band and det.spatial_dims == ("height", "width")
        frame = np.zeros((2 * DET_H, 2 * DET_W, 3), np.uint8)
        band = FarBand(0, DET_H, 2 * DET_W, 2 * DET_H, 1.0)  # input 2 x DET_W wide
        assert det.detect_many([frame], 0.3, 8, [band])[0].shape[1] == 5
    else:
        assert (card.input_w, card.input_h) == (TINY.crop_w, TINY.crop_h)
        assert set(card.onnx_check) == {"keypoints", "confidence"}
    assert all(v < 0.05 for v in card.onnx_check.values())
    md = (tiny_models / f"{kind}.md").read_text(encoding="utf-8")
    assert md.startswith(f"# {kind} model card") and "## Held-out metrics" in md
    assert "steps: 5 x batch" in md
    with np.load(reference_path(onnx)) as ref:
        inputs = ref["inputs"]
        assert inputs.dtype == np.uint8 and inputs.ndim == 4 and inputs.shape[-1] == 3
        assert inputs.shape[1:3] == (card.input_h, card.input_w)
        extra = {"peaks_ambiguous"} if kind == "detector" else set()
        assert set(ref.files) == {"inputs", *card.onnx_check, *extra}
    ckpt = torch.load(tiny_models / f"{kind}.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["state"]["step"] == 5
    assert any((tiny_models / "cache").glob("randomized-s1-*.npz"))


def test_running_the_command_again_resumes(tiny_models: Path, tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """The same command in a finished run's folder reuses the rendered cache (no rendering)
    and resumes from the checkpoint at step 5 (no further steps); it still exports and writes
    the card."""
    folder = tmp_path / "run"
    shutil.copytree(tiny_models, folder)
    card_before = json.loads((folder / "keypoints.json").read_text(encoding="utf-8"))
    capsys.readouterr()
    t0 = time.perf_counter()
    assert train_tiny("keypoints", folder) == 0
    elapsed = time.perf_counter() - t0
    out = capsys.readouterr().out
    assert "resuming from" in out and "at step 5/5" in out
    assert "rendering" not in out and "step 5/5 loss" not in out
    assert elapsed < 30.0
    ckpt = torch.load(folder / "keypoints.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["state"]["step"] == 5
    card = KeypointCard.read(folder / "keypoints.json")
    assert card.training["steps"] == 5
    assert card.metrics == card_before["metrics"]  # same weights, same held-out figures


def test_a_detector_fine_tuned_at_another_input_size(tiny_models: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """``--detector-input WxH --init-from`` a checkpoint of another input size: the fully
    convolutional detector starts from those weights, its card records the new input, the
    resize and the test-time flip; the keypoint network (crops) and a malformed size are
    refused with the reason."""
    from smartedge.cli import main
    from tests.edge_agent.conftest import TINY_ARGS

    out = tmp_path / "wide"
    w, h = DET_W + 32, DET_H + 24
    code = main(["train", "detector", "--out", str(out), *TINY_ARGS, "--detector-input",
                 f"{w}x{h}", "--init-from", str(tiny_models / "detector.ckpt")])
    assert code == 0
    said = capsys.readouterr().out
    assert f"input {DET_W}x{DET_H} -> {w}x{h}" in said
    card = DetectorCard.read(out / "detector.json")
    assert (card.input_w, card.input_h) == (w, h) and card.flip_tta is True
    assert any(f"{DET_W}x{DET_H} -> {w}x{h}" in line for line in card.training["history"])
    assert main(["train", "keypoints", "--out", str(tmp_path / "kp"), *TINY_ARGS,
                 "--detector-input", "640x360"]) == 1
    assert "--detector-input is for the detector" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["train", "detector", "--out", str(tmp_path / "bad"), "--detector-input", "641x360"])
    assert "multiples of 8" in capsys.readouterr().err


def test_shards_load_into_one_allocation_as_concatenated(tiny_models: Path,
                                                        tmp_path: Path) -> None:
    """``RenderedSet.load_many`` gives exactly what loading every shard and concatenating
    them gives (crop rows still point at their own views), and names a broken shard."""
    import dataclasses

    from training.data import RenderedSet

    paths = sorted((tiny_models / "cache").glob("*.npz"))
    assert len(paths) >= 2
    want = RenderedSet.concatenate([RenderedSet.load(p) for p in paths])
    got = RenderedSet.load_many(paths)
    for f in dataclasses.fields(RenderedSet):
        a, b = getattr(want, f.name), getattr(got, f.name)
        assert a.dtype == b.dtype and a.shape == b.shape, f.name
        np.testing.assert_array_equal(a, b, err_msg=f.name)
    assert got.crop_view.max() >= len(RenderedSet.load(paths[0]).det_images)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"bad\.npz: not a readable render shard"):
        RenderedSet.load_many([paths[0], bad])


def test_check_onnxruntime_catches_a_model_mismatch(tmp_path: Path) -> None:
    """An ONNX file checked against the torch model it came from passes (and writes the
    reference outputs); checked against a differently initialised model it raises
    TrainingError naming the file."""
    cfg = TrainConfig("keypoints", TRAIN, VAL, TINY, threads=1)
    torch.manual_seed(1)
    exported = KeypointNet(12, TINY.crop_w, TINY.crop_h)
    torch.manual_seed(2)
    other = KeypointNet(12, TINY.crop_w, TINY.crop_h)
    path = tmp_path / "keypoints.onnx"
    export_onnx(cfg, exported, path)
    samples = np.random.default_rng(0).integers(0, 256, (3, TINY.crop_h, TINY.crop_w, 3),
                                                dtype=np.uint8)
    diffs = check_onnxruntime(cfg, exported, path, samples)
    assert set(diffs) == {"keypoints", "confidence"}
    assert diffs["keypoints"] < 0.05 and diffs["confidence"] < 1e-3
    with np.load(reference_path(path)) as ref:
        np.testing.assert_array_equal(ref["inputs"], samples)
    with pytest.raises(TrainingError, match="onnxruntime differs from torch") as exc:
        check_onnxruntime(cfg, other, path, samples)
    assert str(path) in str(exc.value)


def test_untrained_detector_export_check_passes(tmp_path: Path) -> None:
    """Freshly initialised detectors, exported and checked on random frames, all pass the
    onnxruntime export check (the peak test tolerates float noise on near-ties, which used to
    flip between torch and onnxruntime for half of the seeds)."""
    cfg = TrainConfig("detector", TRAIN, VAL, TINY, threads=1)
    samples = np.random.default_rng(0).integers(0, 256, (4, DET_H, DET_W, 3), dtype=np.uint8)
    path = tmp_path / "detector.onnx"
    failed = []
    for seed in range(6):
        torch.manual_seed(seed)
        model = RobotDetector()
        export_onnx(cfg, model, path)
        try:
            check_onnxruntime(cfg, model, path, samples)
        except TrainingError as exc:
            failed.append((seed, str(exc).rsplit(": ", 1)[-1]))
    assert not failed, failed


def test_render_cache_refuses_another_robot(tiny_models: Path, tmp_path: Path) -> None:
    """A render cache records its robot (cache.json); rendering into it for a robot with other
    keypoints is refused with an error naming the manifest, not silently mixed."""
    import dataclasses

    from lab.training_views import SimulationViews
    from protocol.errors import UsageError
    from simulation.scenario import load_scenario

    cache = tmp_path / "cache"
    shutil.copytree(tiny_models / "cache", cache)
    scenario = load_scenario()
    model = scenario.site.robot_model(scenario.robot_id)
    other = dataclasses.replace(model, name="other", keypoints_base_m=model.keypoints_base_m * 2)
    with pytest.raises(UsageError, match=r"cache\.json"):
        render_set(SimulationViews(str(scenario.source_path), other), [TRAIN[0]], TINY, cache,
                   workers=1)
