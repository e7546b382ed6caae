"""``smartedge evaluate keypoints --dataset``: the shipped networks scored on a COCO keypoints
dataset. Rendered views written as such a dataset (``lab.coco_renders``, the renderer's exact
labels) give the same figures as the same views scored directly, so a lab's own labelled frames
are scored exactly as the renders are; an unreadable frame and a frame with two robots are named
and left out."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("moderngl", reason="rendering needs moderngl")

from core.coco import read_dataset
from edge_agent.models import RobotKeypointPipeline
from lab.coco_renders import samples_to_coco
from lab.evaluate import main as evaluate_main
from lab.evaluation.keypoints import evaluate_on_dataset, evaluate_set


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory):
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    model = scenario.site.robot_model(scenario.robot_id)
    gen = SampleGenerator(scenario, "site", seed=77)
    with_robot, without = [], []
    for i in range(40):
        sample = gen(i)
        (with_robot if sample.robots[0].bbox_xyxy is not None else without).append(sample)
        if len(with_robot) >= 5 and without:
            break
    samples = [without[0], *with_robot[:5]]  # the last frames have a robot
    out = tmp_path_factory.mktemp("coco_renders")
    path = samples_to_coco(samples, out, model.name, model.keypoint_names)
    return samples, path, model


def test_the_dataset_path_scores_as_the_renders_do(rendered) -> None:
    samples, path, model = rendered
    ds = read_dataset(path)
    assert len(ds.images) == 6 and len(ds.annotations) == 5
    assert ds.annotations[0].label_source == "render"
    figures, skipped, frames = evaluate_on_dataset(path, threads=1)
    assert frames == 6 and not any(skipped.values())
    pipeline = RobotKeypointPipeline.from_folder(None, threads=1,
                                                 keypoint_names=model.keypoint_names)
    direct = evaluate_set(pipeline, samples)
    for name in ("AP@0.5", "pipeline median error px", "true-box median error px",
                 "true-box PCK@5px"):
        assert figures[name] == pytest.approx(direct[name], abs=1e-6), name
    assert not any(k.startswith("recall") for k in figures)  # no simulated distance here
    assert figures["images with robot"] == 5 and figures["AP@0.5"] > 0.5


def test_cli_names_what_it_left_out(rendered, tmp_path: Path, capsys) -> None:
    _, path, _ = rendered
    doc = json.loads(Path(path).read_text())
    doc["images"][1]["file_name"] = "missing/1.png"
    two = dict(doc["annotations"][-1], id=999)  # a second robot on the last image
    doc["annotations"].append(two)
    edited = Path(path).parent / "edited.json"
    edited.write_text(json.dumps(doc))
    assert evaluate_main(["keypoints", "--dataset", str(edited), "--count", "0",
                          "--threads", "1"]) == 0
    captured = capsys.readouterr()
    assert "skipped (unreadable):" in captured.err and "missing/1.png" in captured.err
    assert "skipped (several robots):" in captured.err
    assert "AP@0.5" in captured.out and "(4 dataset frames, 2 left out" in captured.out
    assert evaluate_main(["keypoints", "--dataset", str(tmp_path / "none.json"),
                          "--count", "0"]) == 1
    assert "cannot read" in capsys.readouterr().err
