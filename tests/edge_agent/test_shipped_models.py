"""The shipped detector + keypoint + segmentation models (``edge_agent/models/``): they are
there, small, fit the paper site's robot and smartedge's class legend, reproduce torch's outputs
with onnxruntime alone (torch unimportable), and meet measured accuracy floors on a small
held-out set rendered here (seeds, textures, scenes and robot poses the models never saw in
training)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from edge_agent.model_cards import DetectorCard, KeypointCard, SegmentationCard, default_model_dir
from edge_agent.models import RobotKeypointPipeline
from edge_agent.networks import SemanticSegmenter
from protocol.semantic_classes import NUM_SEMANTIC_CLASSES, SEMANTIC_CLASSES

REPO_ROOT = Path(__file__).resolve().parents[2]
#: held-out seed for the accuracy test (training used 1-2, validation 1001-1002, the
#: ``smartedge evaluate keypoints`` default is 4242)
SEED = 777
#: floors measured on the shipped models with this test's set, with margin
#: (measured figures: see docs/models.md)
#: measured on this set (2026-11-26, keypoint network trained on a GPU with mirrored crops,
#: flip test-time augmentation): randomized AP@0.5 0.856, median 0.49 px, PCK@2px 0.913;
#: site AP@0.5 0.854, median 0.30 px, PCK@2px 0.980 (seed 778: 0.65 / 0.890 and 0.35 / 0.964).
#: The keypoint model before (CPU-trained) fails the keypoint floors: randomized median
#: 0.81 px, PCK@2px 0.840; site 0.52 px, 0.863
FLOORS = {
    "randomized": {"AP@0.5": 0.75, "median error px": 0.7, "PCK@2px": 0.87},
    "site": {"AP@0.5": 0.75, "median error px": 0.45, "PCK@2px": 0.93},
}


def test_shipped_models_are_there_small_and_for_the_paper_robot() -> None:
    from core.site import load_site

    folder = default_model_dir()
    det = DetectorCard.read(folder / "detector.json")
    kp = KeypointCard.read(folder / "keypoints.json")
    site = load_site(REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml")
    model = site.robot_model("hsr")
    assert det.robot_model == kp.robot_model == model.name
    assert kp.keypoint_names == list(model.keypoint_names)
    total = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
    assert total <= 13e6, f"shipped models take {total / 1e6:.1f} MB (limit 13 MB)"
    for card in (det, kp):
        assert card.training["steps"] > 0 and card.training["device"] in ("cpu", "cuda")
        assert card.metrics, "the card records held-out metrics"
        assert (folder / card.onnx.replace(".onnx", ".md")).is_file()


def test_shipped_models_match_torch_without_torch() -> None:
    """In an interpreter where importing torch fails, onnxruntime reproduces the torch outputs
    stored beside each shipped model (export tolerances)."""
    code = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("torch is blocked in this test")
sys.meta_path.insert(0, Block())
import numpy as np
from edge_agent.crop import to_nchw
from edge_agent.model_cards import default_model_dir, export_differences, reference_path
from edge_agent.networks import Detector, KeypointEstimator, SemanticSegmenter
for cls, name in ((Detector, "detector"), (KeypointEstimator, "keypoints"),
                  (SemanticSegmenter, "segmentation")):
    onnx = default_model_dir() / f"{name}.onnx"
    model = cls(onnx, threads=1)
    with np.load(reference_path(onnx)) as ref:
        want = {k: ref[k] for k in ref.files}
    got = model.session.run(None, {model.session.get_inputs()[0].name: to_nchw(want["inputs"])})
    ratios = export_differences(want, dict(zip([o.name for o in model.session.get_outputs()],
                                               got)))
    assert max(ratios.values()) <= 1.0, (name, ratios)
assert "torch" not in sys.modules
print("ok")
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().endswith("ok")


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["randomized", "site"])
def test_shipped_models_meet_accuracy_floors_on_held_out_renders(mode: str) -> None:
    """Rendered 848x480 views from a seed never trained on: the detector's AP@0.5 and the
    whole pipeline's median keypoint error (robots the detector found) meet the floors."""
    pytest.importorskip("moderngl")
    from lab.evaluation.keypoints import evaluate_set
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    model = scenario.site.robot_model(scenario.robot_id)
    pipeline = RobotKeypointPipeline.for_robot(model, threads=2)
    gen = SampleGenerator(scenario, mode, seed=SEED)
    samples = []
    i = 0
    while sum(s.robots[0].bbox_xyxy is not None for s in samples) < 30 and i < 200:
        samples.append(gen(i))
        i += 1
    figures = evaluate_set(pipeline, samples)
    floors = FLOORS[mode]
    assert figures["AP@0.5"] >= floors["AP@0.5"], figures
    assert figures["pipeline median error px"] <= floors["median error px"], figures
    assert figures["pipeline PCK@2px"] >= floors["PCK@2px"], figures
    assert np.isfinite(figures["pipeline mean error px"])


# --------------------------------------------------------------------------------------------
# the segmentation network
# --------------------------------------------------------------------------------------------

#: floors for the shipped segmentation network on SEG_VIEWS site views of seed SEED at 848x480
#: (textures, people and robot poses never trained on), set with margin below the measured
#: figures: seed 777 pixel accuracy 0.990, floor IoU 0.993, wall IoU 0.979 (before the
#: robot-view fine-tune 0.992, 0.994, 0.984; seeds 778/779 then: 0.983-0.992, 0.981-0.992,
#: 0.980-0.987; the demo site's textures, seed 0: 0.977, 0.979, 0.962)
SEG_VIEWS = 24
SEG_FLOORS = {"pixel accuracy": 0.95, "IoU floor": 0.93, "IoU wall": 0.92}
#: floors on SEG_VIEWS robot head-camera views of seed SEED at 640x480, set with margin below
#: the measured figures (2026-11-25): pixel accuracy 0.939, mean IoU 0.673, floor IoU 0.991,
#: wall IoU 0.911, furniture accuracy 0.722 (seed 778: 0.890, 0.637, 0.878, 0.803, 0.637; the
#: demo's textures, seed 0, trained on: 0.919, 0.614, 0.970, 0.952, 0.633). The model before
#: the robot-view fine-tune fails them: 0.759, 0.343, 0.971, 0.459, 0.000
ROBOT_VIEW_FLOORS = {"pixel accuracy": 0.88, "mean IoU": 0.58, "IoU floor": 0.93,
                     "IoU wall": 0.83, "furniture accuracy": 0.6}


def test_shipped_segmentation_model_is_there_small_and_of_the_legend() -> None:
    """The card lists smartedge's class legend, the runtime loads the default model, and the
    ONNX file stays under 3 MB; a frame gives (h, w) classes at the card's output size."""
    folder = default_model_dir()
    card = SegmentationCard.read(folder / "segmentation.json")
    assert card.classes == list(SEMANTIC_CLASSES)
    assert (card.input_w, card.input_h) == (424, 240)
    assert (card.output_w, card.output_h) == (212, 120)
    assert (folder / "segmentation.onnx").stat().st_size < 3e6
    assert card.training["steps"] > 0 and card.metrics
    seg = SemanticSegmenter(threads=1)
    assert seg.path == folder / "segmentation.onnx"
    assert seg.model_id == "segmentation/models"
    out = seg(np.zeros((480, 848, 3), np.uint8))
    assert out.class_ids.shape == (120, 212) and out.confidence.shape == (120, 212)
    assert (out.image_width, out.image_height) == (848, 480)


def _segmentation_figures(mode: str) -> dict[str, float]:
    """The shipped network's figures on SEG_VIEWS views of ``mode`` from seed SEED at the
    cameras' own sizes (site: 848x480, robot head: 640x480) against the renderer's classes
    (nearest-centre label images at the output size); ``furniture accuracy``: the share of
    table/shelf/cabinet/box pixels labelled with their own class."""
    pytest.importorskip("moderngl")
    from edge_agent.crop import downscale_labels
    from edge_agent.metrics import confusion_matrix, segmentation_metrics
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    seg = SemanticSegmenter(threads=2)
    gen = SampleGenerator(load_scenario(), mode, seed=SEED)
    cm = np.zeros((NUM_SEMANTIC_CLASSES, NUM_SEMANTIC_CLASSES), np.int64)
    for i in range(SEG_VIEWS):
        sample = gen(i)
        out = seg(sample.image_rgb)
        h, w = out.class_ids.shape
        cm += confusion_matrix(downscale_labels(sample.class_id, w, h), out.class_ids,
                               NUM_SEMANTIC_CLASSES)
    figures = segmentation_metrics(cm, SEMANTIC_CLASSES)
    furniture = [SEMANTIC_CLASSES.index(c) for c in ("table", "shelf", "cabinet", "box")]
    figures["furniture accuracy"] = float(np.trace(cm[np.ix_(furniture, furniture)])
                                          / max(int(cm[furniture].sum()), 1))
    return figures


def test_shipped_segmentation_meets_accuracy_floors_on_held_out_site_views() -> None:
    """Site views from a seed never trained on (other textures, people and robot poses): the
    shipped network's pixel accuracy and floor and wall IoU meet the floors."""
    figures = _segmentation_figures("site")
    for name, floor in SEG_FLOORS.items():
        assert figures[name] >= floor, (name, figures)


def test_shipped_segmentation_meets_accuracy_floors_on_held_out_robot_head_views() -> None:
    """What the robot's own head camera sees (about 1 m up, tilted down; textures, poses and
    people never trained on): furniture seen from that low viewpoint is labelled as furniture,
    not as a randomized scene's distractor, and walls and floor are right."""
    figures = _segmentation_figures("robot")
    for name, floor in ROBOT_VIEW_FLOORS.items():
        assert figures[name] >= floor, (name, figures)


def test_boxes_without_the_robots_keypoints_are_not_reported() -> None:
    """The shipped detector boxes a wall corner of one site camera (site textures of seed 4242,
    score 0.3-0.57 in half the views without the robot); the keypoint network finds no robot
    there (mean confidence 0.20-0.24), so the pipeline drops the box and counts it. Views with
    the robot keep theirs. With the floor at 0 the wall corner is reported: the test can fail.
    The detector's own test-time flip already removes that box (it is boxed in one orientation
    only), so the floor is tested without it, and the flip on the same views."""
    pytest.importorskip("moderngl")
    from edge_agent.boxes import box_iou
    from edge_agent.models import MIN_KEYPOINT_CONFIDENCE, RobotKeypointPipeline
    from simulation.dataset import SampleGenerator
    from simulation.scenario import PAPER_SCENARIO, load_scenario

    gen = SampleGenerator(load_scenario(PAPER_SCENARIO), "site", seed=4242)
    samples = gen.samples(list(range(12)))
    empty = [s for s in samples if not s.robots or s.robots[0].bbox_xyxy is None]
    seen = [s for s in samples if s.robots and s.robots[0].bbox_xyxy is not None
            and int(np.sum(s.robots[0].visible)) >= 8]
    assert len(empty) >= 4 and seen
    unfiltered = RobotKeypointPipeline(threads=1, min_keypoint_confidence=0.0,
                                       detector_flip=False)
    pipeline = RobotKeypointPipeline(threads=1, detector_flip=False)
    assert pipeline.min_keypoint_confidence == MIN_KEYPOINT_CONFIDENCE
    false_boxes = sum(len(unfiltered(s.image_rgb)) for s in empty)
    assert false_boxes >= 2  # what the floor is for
    assert sum(len(pipeline(s.image_rgb)) for s in empty) == 0
    assert pipeline.unconfirmed >= false_boxes
    for s in seen:
        truth = np.asarray(s.robots[0].bbox_xyxy)
        assert any(box_iou(o.bbox_xyxy, truth) >= 0.5 for o in pipeline(s.image_rgb))
    # the deployed default, the detector's flip on: no box at the wall corner in the first
    # place, and the robot's views keep theirs
    flipped = RobotKeypointPipeline(threads=1, min_keypoint_confidence=0.0)
    assert flipped.detector.flip
    assert sum(len(flipped(s.image_rgb)) for s in empty) == 0
    for s in seen:
        truth = np.asarray(s.robots[0].bbox_xyxy)
        assert any(box_iou(o.bbox_xyxy, truth) >= 0.5 for o in flipped(s.image_rgb))
    with pytest.raises(ValueError, match="min_keypoint_confidence"):
        RobotKeypointPipeline(threads=1, min_keypoint_confidence=1.0)


def test_boxes_without_keypoints_are_counted_in_the_agents_status() -> None:
    """The boxes the keypoint floor drops reach the edge agent's status counters
    (``boxes_without_keypoints``), through the same path as every per-frame figure."""
    pytest.importorskip("moderngl")
    from core.runtime import Stats
    from edge_agent.frames import Frame
    from edge_agent.models import RobotKeypointPipeline
    from edge_agent.pipeline import EdgePipeline
    from edge_agent.sources import PipelineSource
    from simulation.dataset import SampleGenerator
    from simulation.scenario import PAPER_SCENARIO, load_scenario

    gen = SampleGenerator(load_scenario(PAPER_SCENARIO), "site", seed=4242)
    empty = [s for s in gen.samples(list(range(12)))
             if not s.robots or s.robots[0].bbox_xyxy is None]
    models = RobotKeypointPipeline(threads=1, detector_flip=False)  # else no box to drop
    source = PipelineSource(EdgePipeline("cam1", models))
    stats = Stats()
    source.bind_stats(stats)
    for k, s in enumerate(empty):
        msg = source.process(Frame(s.image_rgb, 1_000 + k, k), 1_000 + k, 0)
        assert msg.detections == ()
    counted = stats.snapshot_counters().get("boxes_without_keypoints", 0)
    assert counted == models.unconfirmed >= 2
