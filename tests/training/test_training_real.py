"""``smartedge train --real``: a lab's labelled frames (a COCO keypoints file) trained on beside
the renders and validated on, the model card saying what they were; a file whose keypoints are
not the robot model's is refused with both named. Tiny runs (a few steps) on rendered frames
written as such a dataset."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("torch", reason="training needs torch (train extra)")
pytest.importorskip("moderngl", reason="rendering needs moderngl")

from lab.coco_renders import samples_to_coco
from smartedge.cli import main
from tests.edge_agent.conftest import TINY_ARGS


def _labelled(tmp_path: Path, seed: int, n: int = 6) -> Path:
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    model = scenario.site.robot_model(scenario.robot_id)
    gen = SampleGenerator(scenario, "site", seed=seed)
    return samples_to_coco([gen(i) for i in range(n)], tmp_path / f"frames_{seed}", model.name,
                           model.keypoint_names)


def test_labelled_frames_beside_the_renders_and_in_the_card(tmp_path: Path, capsys) -> None:
    train, val = _labelled(tmp_path, 101), _labelled(tmp_path, 202)
    out = tmp_path / "model"
    assert main(["train", "detector", "--out", str(out), *TINY_ARGS, "--real", str(train),
                 "--real-val", str(val), "--real-weight", "2"]) == 0
    card = json.loads((out / "detector.json").read_text())
    real = card["training"]["real_data"]
    assert real["train"]["frames"] == 6 and real["train"]["weight"] == 2
    assert real["train"]["path"] == str(train) and len(real["train"]["sha256"]) == 64
    assert real["train"]["label_sources"].get("render", 0) >= 1
    assert real["val"]["frames"] == 6
    assert "real" in card["metrics"]  # validated on the labelled frames too
    assert card["training"]["selected"]["step"] == 5  # scored on them at the (only) checkpoint
    # the checkpoint resumes only with the same labelled frames
    assert main(["train", "detector", "--out", str(out), *TINY_ARGS, "--real", str(val),
                 "--real-val", str(val)]) == 1
    assert "checkpoint trained on other labelled frames" in capsys.readouterr().err


def test_a_file_of_other_keypoints_is_refused(tmp_path: Path, capsys) -> None:
    path = _labelled(tmp_path, 303, n=2)
    doc = json.loads(path.read_text())
    doc["categories"][0]["keypoints"] = doc["categories"][0]["keypoints"][::-1]
    path.write_text(json.dumps(doc))
    assert main(["train", "keypoints", "--out", str(tmp_path / "m"), *TINY_ARGS,
                 "--real", str(path)]) == 1
    err = capsys.readouterr().err
    assert "no category with the robot model's keypoints" in err
    assert "smartedge dataset import" in err
    assert main(["train", "segmentation", "--out", str(tmp_path / "s"), *TINY_ARGS,
                 "--real", str(path)]) == 1
    assert "segmentation network needs class images" in capsys.readouterr().err
