"""The semantic segmentation network: its label images, metrics and loss weights, the tiny
``smartedge train segmentation`` run (card, reference outputs, cache, checkpoint), the
onnxruntime runtime :class:`SemanticSegmenter` (shapes, pixel mapping, resizing inside) and every
broken model or card it must refuse with a ``ModelError`` naming the file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from edge_agent.crop import downscale_labels, to_nchw
from edge_agent.metrics import confusion_matrix, segmentation_metrics
from edge_agent.model_cards import (
    CARD_VERSION,
    ModelError,
    SegmentationCard,
    card_path,
    export_differences,
    reference_path,
)
from edge_agent.networks import Segmentation, SemanticSegmenter
from protocol.errors import SmartedgeError
from protocol.semantic_classes import NUM_SEMANTIC_CLASSES, SEMANTIC_CLASSES

IN_W, IN_H = 128, 96  # the --tiny input
OUT_W, OUT_H = 64, 48


# --------------------------------------------------------------------------------------------
# labels, metrics, loss weights (no torch)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("size", [(48, 64, 12, 16), (50, 70, 20, 30), (480, 848, 120, 212),
                                  (10, 10, 10, 10)])
def test_downscale_labels_takes_the_pixel_at_each_output_centre(size: tuple[int, ...]) -> None:
    """Output pixel (i, j) holds the class of the image pixel nearest to its centre
    ((j + 0.5) W / w - 0.5, (i + 0.5) H / h - 0.5), for integer and fractional ratios."""
    h, w, oh, ow = size
    labels = np.random.default_rng(h * w).integers(0, NUM_SEMANTIC_CLASSES, (h, w))
    got = downscale_labels(labels.astype(np.int32), ow, oh)
    assert got.shape == (oh, ow) and got.dtype == np.uint8
    rows = np.floor((np.arange(oh) + 0.5) * h / oh).astype(int)
    cols = np.floor((np.arange(ow) + 0.5) * w / ow).astype(int)
    np.testing.assert_array_equal(got, labels[rows][:, cols])


def test_downscale_labels_refuses_a_colour_image() -> None:
    with pytest.raises(ValueError, match=r"\(H, W\) class image"):
        downscale_labels(np.zeros((8, 8, 3), np.uint8), 4, 4)


def test_segmentation_metrics_of_a_known_confusion() -> None:
    """Pixel accuracy, per-class IoU (only classes with true pixels) and their mean, counted
    by hand on a 2x4 example."""
    true = np.array([[1, 1, 2, 2], [1, 1, 2, 12]])
    pred = np.array([[1, 1, 2, 1], [1, 2, 2, 12]])
    cm = confusion_matrix(true, pred, NUM_SEMANTIC_CLASSES)
    assert cm.shape == (NUM_SEMANTIC_CLASSES,) * 2 and cm.sum() == 8
    assert cm[1, 1] == 3 and cm[1, 2] == 1 and cm[2, 1] == 1 and cm[2, 2] == 2
    m = segmentation_metrics(cm, SEMANTIC_CLASSES)
    assert m["pixel accuracy"] == pytest.approx(6 / 8)
    # floor: 3 right, 4 true, 4 predicted → 3 / 5; wall: 2 / (3 + 3 - 2); robot 1 / 1
    assert m["IoU floor"] == pytest.approx(3 / 5)
    assert m["IoU wall"] == pytest.approx(2 / 4)
    assert m["IoU robot"] == pytest.approx(1.0)
    assert m["mean IoU"] == pytest.approx((3 / 5 + 2 / 4 + 1) / 3)
    assert "IoU person" not in m and m["pixels"] == 8
    with pytest.raises(ValueError, match="outside"):
        confusion_matrix(true, pred + 20, NUM_SEMANTIC_CLASSES)


def test_export_differences_for_segmentation() -> None:
    """Class ids may differ on at most 0.1 % of the pixels (near-ties), the confidence by 1e-3
    everywhere; the keypoints' tie allowance does not apply to the segmentation's
    confidence."""
    rng = np.random.default_rng(0)
    want = {"class_ids": rng.integers(0, 14, (2, 100, 100)).astype(np.uint8),
            "confidence": rng.uniform(0.1, 1.0, (2, 100, 100)).astype(np.float32)}
    got = {k: v.copy() for k, v in want.items()}
    assert max(export_differences(want, got).values()) == 0.0
    got["class_ids"].reshape(-1)[:20] += 1  # 20 of 20,000 pixels: 0.1 %
    assert export_differences(want, got)["class_ids"] == pytest.approx(1.0)
    got["class_ids"].reshape(-1)[20:25] += 1  # 25 pixels: too many
    assert export_differences(want, got)["class_ids"] > 1.0
    got = {k: v.copy() for k, v in want.items()}
    got["confidence"][1, 5, 5] += 0.005
    assert export_differences(want, got)["confidence"] > 1.0


# --------------------------------------------------------------------------------------------
# training (torch)
# --------------------------------------------------------------------------------------------


def test_class_weights_balance_rare_classes() -> None:
    """sqrt(median frequency / frequency) over the present classes, clipped to [0.2, 5]; absent
    classes weigh 0."""
    pytest.importorskip("torch")
    from training.targets import class_weights

    # floor 70 %, wall 20 %, robot 9 %, person 1 % (of 1000 pixels)
    labels = np.repeat([1, 2, 12, 11], [700, 200, 90, 10]).reshape(1, 10, 100)
    w = class_weights(labels, NUM_SEMANTIC_CLASSES)
    assert w.shape == (NUM_SEMANTIC_CLASSES,) and w.dtype == np.float32
    median = np.median([0.7, 0.2, 0.09, 0.01])
    np.testing.assert_allclose(w[[1, 2, 12]], np.sqrt(median / np.array([0.7, 0.2, 0.09])),
                               rtol=1e-6)
    assert w[11] == pytest.approx(np.sqrt(median / 0.01))
    assert np.all(w[[0, 3, 4, 5, 6, 7, 8, 9, 10, 13]] == 0)
    assert w[1] < w[2] < w[12] < w[11]
    extreme = np.repeat([1, 2], [99_999, 1]).reshape(1, 1, -1)
    assert class_weights(extreme, NUM_SEMANTIC_CLASSES)[[1, 2]].tolist() == pytest.approx(
        [np.sqrt(0.5), 5.0], rel=1e-4)


def test_train_config_checks_the_segmentation_label_size() -> None:
    pytest.importorskip("torch")
    from training.data import Geometry, SetSpec
    from training.train import TrainConfig, TrainingError

    sets = (SetSpec("randomized", 1, 8),), (SetSpec("site", 1001, 8),)
    TrainConfig("segmentation", *sets, Geometry(seg_w=212, seg_h=120))
    with pytest.raises(TrainingError, match="212x120"):
        TrainConfig("segmentation", *sets, Geometry())  # no labels
    with pytest.raises(TrainingError, match="multiples of 4"):
        TrainConfig("segmentation", *sets, Geometry(det_w=426, seg_w=213, seg_h=120))


def test_detector_and_keypoint_checkpoints_keep_their_identity() -> None:
    """The segmentation label size is not part of a detector or keypoint checkpoint's
    geometry (checkpoints written before it existed still resume); it is for segmentation."""
    pytest.importorskip("torch")
    from training.data import Geometry
    from training.train import _geometry_identity

    before = {"det_w", "det_h", "crop_w", "crop_h", "crops_per_robot", "crop_jitter",
              "frame_w", "frame_h"}
    assert set(_geometry_identity(Geometry())) == before
    assert set(_geometry_identity(Geometry(seg_w=212, seg_h=120))) == before | {"seg_w", "seg_h"}


def test_tiny_run_writes_the_segmentation_card_and_reference(tiny_segmentation: Path) -> None:
    """The tiny run wrote the ONNX file, a card the runtime reads (the legend's classes, input
    and output sizes, held-out pixel accuracy / mean IoU / per-class IoU per set, the class
    weights, the export check), the Markdown card, the torch reference outputs, a 5-step
    checkpoint and label shards in the render cache."""
    torch = pytest.importorskip("torch")
    onnx = tiny_segmentation / "segmentation.onnx"
    assert onnx.is_file() and onnx.stat().st_size > 100_000
    card = SegmentationCard.read(card_path(onnx))
    assert card.version == CARD_VERSION and card.onnx == "segmentation.onnx"
    assert card.classes == list(SEMANTIC_CLASSES)
    assert (card.input_w, card.input_h, card.output_w, card.output_h) == (IN_W, IN_H, OUT_W,
                                                                          OUT_H)
    assert card.training["steps"] == 5
    assert set(card.metrics) == {"randomized-s1001", "site-s1002"}
    for figures in card.metrics.values():
        assert 0.0 <= figures["pixel accuracy"] <= 1.0 and 0.0 <= figures["mean IoU"] <= 1.0
        assert figures["pixels"] == 8 * OUT_W * OUT_H
        assert "IoU floor" in figures and "IoU wall" in figures
    weights = card.training["class_weights"]
    assert len(weights) == NUM_SEMANTIC_CLASSES and weights[1] > 0 and weights[3] == 0
    assert set(card.onnx_check) == {"class_ids", "confidence"}
    assert card.onnx_check["class_ids"] <= 1e-3 and card.onnx_check["confidence"] < 1e-3
    md = (tiny_segmentation / "segmentation.md").read_text(encoding="utf-8")
    assert md.startswith("# segmentation model card") and "## Held-out metrics" in md
    assert ", ".join(SEMANTIC_CLASSES) in md and "IoU floor" in md
    with np.load(reference_path(onnx)) as ref:
        assert set(ref.files) == {"inputs", "class_ids", "confidence"}
        assert ref["inputs"].shape[1:] == (IN_H, IN_W, 3) and ref["inputs"].dtype == np.uint8
        assert ref["class_ids"].shape[1:] == (OUT_H, OUT_W)
        assert ref["class_ids"].dtype == np.uint8
    ckpt = torch.load(tiny_segmentation / "segmentation.ckpt", map_location="cpu",
                      weights_only=False)
    assert ckpt["state"]["step"] == 5 and ckpt["state"]["identity"]["kind"] == "segmentation"
    shards = sorted((tiny_segmentation / "cache").glob("site-s2-*.npz"))
    assert shards and all(p.name.endswith(f"-s{OUT_W}x{OUT_H}.npz") for p in shards)


def test_segmentation_shards_hold_labels_and_old_shards_still_load(
        tiny_segmentation: Path, tmp_path: Path) -> None:
    """A segmentation shard holds one (h, w) label image per view, with the rendered classes
    (floor and wall at least); a shard written before labels existed (no ``seg_labels``)
    loads with empty label images."""
    pytest.importorskip("torch")
    from training.data import RenderedSet

    shard = next((tiny_segmentation / "cache").glob("site-s2-*.npz"))
    data = RenderedSet.load(shard)
    assert data.seg_labels.shape == (len(data.det_images), OUT_H, OUT_W)
    assert data.seg_labels.dtype == np.uint8 and len(data.crops) == 0
    assert {1, 2} <= set(np.unique(data.seg_labels).tolist())
    assert data.seg_labels.max() < NUM_SEMANTIC_CLASSES
    with np.load(shard) as z:
        old = {k: z[k] for k in z.files if k != "seg_labels"}
    np.savez(tmp_path / "old.npz", **old)
    loaded = RenderedSet.load(tmp_path / "old.npz")
    assert loaded.seg_labels.shape == (len(data.det_images), 0, 0)
    np.testing.assert_array_equal(loaded.det_images, data.det_images)


def test_fine_tuning_from_a_checkpoint_of_another_kind_is_refused(tiny_segmentation: Path,
                                                                  tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]
                                                                  ) -> None:
    """``--init-from`` a detector checkpoint for a segmentation run fails, naming the file."""
    torch = pytest.importorskip("torch")
    from smartedge.cli import main
    from tests.edge_agent.conftest import TINY_ARGS
    from training.nets import RobotDetector

    ckpt = tmp_path / "detector.ckpt"
    torch.save({"model": RobotDetector().state_dict(), "opt": {},
                "state": {"step": 3, "identity": {"kind": "detector", "geometry": {}}}}, ckpt)
    out = tmp_path / "run"
    shutil.copytree(tiny_segmentation / "cache", out / "cache")
    code = main(["train", "segmentation", "--out", str(out), *TINY_ARGS,
                 "--init-from", str(ckpt)])
    assert code == 1
    err = capsys.readouterr().err
    assert str(ckpt) in err and "another configuration" in err


def test_check_onnxruntime_catches_a_segmentation_mismatch(tmp_path: Path) -> None:
    """An exported segmentation network passes the check against itself and fails against a
    differently initialised one, naming the file."""
    torch = pytest.importorskip("torch")
    from training.data import Geometry, SetSpec
    from training.nets import SemanticSegNet
    from training.train import TrainConfig, TrainingError, check_onnxruntime, export_onnx

    geom = Geometry(det_w=IN_W, det_h=IN_H, crops_per_robot=0, seg_w=OUT_W, seg_h=OUT_H)
    cfg = TrainConfig("segmentation", (SetSpec("site", 2, 8),), (SetSpec("site", 1002, 8),),
                      geom, threads=1)
    torch.manual_seed(1)
    exported = SemanticSegNet(NUM_SEMANTIC_CLASSES)
    torch.manual_seed(2)
    other = SemanticSegNet(NUM_SEMANTIC_CLASSES)
    path = tmp_path / "segmentation.onnx"
    export_onnx(cfg, exported, path)
    samples = np.random.default_rng(0).integers(0, 256, (2, IN_H, IN_W, 3), dtype=np.uint8)
    diffs = check_onnxruntime(cfg, exported, path, samples)
    assert diffs["class_ids"] <= 1e-3 and diffs["confidence"] < 1e-3
    with pytest.raises(TrainingError, match="onnxruntime differs from torch") as exc:
        check_onnxruntime(cfg, other, path, samples)
    assert str(path) in str(exc.value)


# --------------------------------------------------------------------------------------------
# the runtime (onnxruntime only)
# --------------------------------------------------------------------------------------------


@pytest.fixture
def seg_copy(tiny_segmentation: Path, tmp_path: Path) -> Path:
    """A private copy of the tiny segmentation model and its card, free to break; returns the
    ONNX path."""
    folder = tmp_path / "models"
    folder.mkdir()
    for suffix in (".onnx", ".json"):
        shutil.copy(tiny_segmentation / f"segmentation{suffix}", folder / f"segmentation{suffix}")
    return folder / "segmentation.onnx"


def _edit_card(path: Path, **changes: object) -> None:
    doc = json.loads(path.read_text(encoding="utf-8"))
    doc.update(changes)
    path.write_text(json.dumps(doc), encoding="utf-8")


def test_segmenter_output_shapes_and_mapping(tiny_segmentation: Path) -> None:
    """Any (H, W, 3) uint8 image gives (h, w) uint8 class ids of the legend and float32
    confidences in [0, 1] at the card's output size, the image's size, a timing and the
    documented pixel mapping; a frame and the same frame at twice the size (pixels repeated)
    get the same classes."""
    import cv2

    seg = SemanticSegmenter(tiny_segmentation / "segmentation.onnx", threads=1)
    assert seg.model_id == f"segmentation/{tiny_segmentation.name}"
    frame = np.random.default_rng(3).integers(0, 256, (192, 256, 3), dtype=np.uint8)
    frame = cv2.GaussianBlur(frame, (9, 9), 3)
    for image in (frame, frame[:150, :211], np.zeros((IN_H, IN_W, 3), np.uint8)):
        out = seg(image)
        assert isinstance(out, Segmentation)
        assert out.class_ids.shape == out.confidence.shape == (OUT_H, OUT_W)
        assert out.class_ids.dtype == np.uint8 and out.confidence.dtype == np.float32
        assert out.class_ids.max() < NUM_SEMANTIC_CLASSES
        assert np.all((out.confidence >= 1.0 / NUM_SEMANTIC_CLASSES - 1e-6)
                      & (out.confidence <= 1.0))
        assert (out.image_width, out.image_height) == (image.shape[1], image.shape[0])
        assert out.infer_ms > 0
    x, y = seg(frame).image_pixels()
    assert x.shape == y.shape == (OUT_H, OUT_W)
    assert x[0, 0] == pytest.approx(0.5 * 256 / OUT_W - 0.5)
    assert y[-1, 0] == pytest.approx((OUT_H - 0.5) * 192 / OUT_H - 0.5)
    assert x[0, -1] == pytest.approx((OUT_W - 0.5) * 256 / OUT_W - 0.5)
    big = cv2.resize(frame, (512, 384), interpolation=cv2.INTER_NEAREST)
    same = np.mean(seg(big).class_ids == seg(frame).class_ids)
    assert same >= 0.99, same


def test_segmenter_reproduces_the_torch_reference(tiny_segmentation: Path) -> None:
    """On the reference inputs stored by training (already at the input size), the runtime's
    class ids and confidences match torch's within the export tolerances."""
    onnx = tiny_segmentation / "segmentation.onnx"
    seg = SemanticSegmenter(onnx, threads=1)
    with np.load(reference_path(onnx)) as ref:
        want = {k: ref[k] for k in ref.files}
    outs = [seg(image) for image in want["inputs"]]
    got = {"class_ids": np.stack([o.class_ids for o in outs]),
           "confidence": np.stack([o.confidence for o in outs])}
    ratios = export_differences(want, got)
    assert set(ratios) == {"class_ids", "confidence"}
    assert max(ratios.values()) <= 1.0, ratios
    raw = seg.session.run(None, {"image": to_nchw(want["inputs"])})
    assert max(export_differences(want, dict(zip(["class_ids", "confidence"], raw,
                                                 strict=True))).values()) <= 1.0


@pytest.mark.parametrize("image", [
    np.zeros((96, 128, 3), np.float32),
    np.zeros((96, 128, 3), np.uint16),
    np.zeros((96, 128), np.uint8),
    np.zeros((96, 128, 4), np.uint8),
    np.zeros((1, 96, 128, 3), np.uint8),
    np.zeros((0, 128, 3), np.uint8),
], ids=["float32", "uint16", "gray", "rgba", "batch", "empty"])
def test_segmenter_refuses_bad_images(tiny_segmentation: Path, image: np.ndarray) -> None:
    seg = SemanticSegmenter(tiny_segmentation / "segmentation.onnx", threads=1)
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
        seg(image)


def _raises_naming(path: Path, onnx: Path) -> ModelError:
    with pytest.raises(ModelError) as exc:
        SemanticSegmenter(onnx, threads=1)
    assert isinstance(exc.value, SmartedgeError)
    assert str(path) in str(exc.value), str(exc.value)
    return exc.value


def test_missing_corrupt_and_truncated_model(seg_copy: Path) -> None:
    data = seg_copy.read_bytes()
    seg_copy.unlink()
    assert "not found" in str(_raises_naming(seg_copy, seg_copy))
    seg_copy.write_bytes(b"not an onnx model\x00\xff" * 50)
    assert "cannot load" in str(_raises_naming(seg_copy, seg_copy))
    seg_copy.write_bytes(data[: len(data) // 2])
    _raises_naming(seg_copy, seg_copy)


def test_missing_or_foreign_card(seg_copy: Path) -> None:
    """No card (the message says how to get one), a card of another kind, a card of another
    version."""
    card = card_path(seg_copy)
    text = card.read_text(encoding="utf-8")
    card.unlink()
    assert "smartedge train segmentation" in str(_raises_naming(card, seg_copy))
    card.write_text(text, encoding="utf-8")
    _edit_card(card, kind="detector")
    assert "not a segmentation model card" in str(_raises_naming(card, seg_copy))
    card.write_text(text, encoding="utf-8")
    _edit_card(card, version=2)
    _raises_naming(card, seg_copy)


def test_card_without_classes_or_with_other_classes(seg_copy: Path) -> None:
    card = card_path(seg_copy)
    doc = json.loads(card.read_text(encoding="utf-8"))
    del doc["classes"]
    card.write_text(json.dumps(doc), encoding="utf-8")
    assert "classes" in str(_raises_naming(card, seg_copy))
    _edit_card(card, classes=[*SEMANTIC_CLASSES[:-1], "plant"])
    assert "plant" in str(_raises_naming(card, seg_copy))
    _edit_card(card, classes=list(SEMANTIC_CLASSES[:-1]))
    _raises_naming(card, seg_copy)
    _edit_card(card, classes=list(SEMANTIC_CLASSES))
    SemanticSegmenter(seg_copy, threads=1)  # restored: fine


@pytest.mark.parametrize("change", [{"input_w": 256}, {"input_h": 120}, {"output_w": 128},
                                    {"output_h": 24}])
def test_card_whose_sizes_do_not_match_the_graph(seg_copy: Path, change: dict[str, int]) -> None:
    _edit_card(card_path(seg_copy), **change)
    _raises_naming(seg_copy, seg_copy)
