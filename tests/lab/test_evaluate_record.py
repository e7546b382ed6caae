"""``smartedge evaluate keypoints --record``: the figures of a real evaluation (rendered views,
onnxruntime) land in the evaluated models' cards, detector figures in the detector's card and
keypoint figures in the keypoint network's, named by what ran; the same run again replaces its
entry, and the cards of other model folders are not touched."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

pytest.importorskip("onnxruntime")
pytest.importorskip("moderngl")

from edge_agent.model_cards import DetectorCard, KeypointCard, card_machine, default_model_dir
from lab.evaluate import main

SHIPPED_CARDS = ("detector.json", "detector.md", "keypoints.json", "keypoints.md")


def _models(tmp_path: Path) -> Path:
    folder = tmp_path / "models"
    shutil.copytree(default_model_dir(), folder)
    return folder


def test_record_writes_each_network_its_own_figures(tmp_path: Path, capsys) -> None:
    shipped = {n: (default_model_dir() / n).read_bytes() for n in SHIPPED_CARDS}
    folder = _models(tmp_path)
    args = ["keypoints", "--model", str(folder), "--count", "3", "--seed", "5", "--record"]
    assert main(args) == 0
    out = capsys.readouterr().out
    name = "randomized and site views, seed 5"
    assert f"recorded as {name!r} in {folder / 'detector.json'}" in out
    det = DetectorCard.read(folder / "detector.json")
    kp = KeypointCard.read(folder / "keypoints.json")
    entry = det.evaluations[name]
    assert entry["command"] == ("smartedge evaluate keypoints --model DIR --seed 5 --count 3 "
                                "--record")
    assert entry["views"] == 6 and entry["date"].count("-") == 2
    assert entry["machine"] == card_machine()  # as a training names where it ran
    assert set(entry["figures"]) == {"randomized", "site"}
    site_det = entry["figures"]["site"]
    site_kp = kp.evaluations[name]["figures"]["site"]
    assert "AP@0.5" in site_det and "detector ms" in site_det
    assert "pipeline median error px" in site_kp and "keypoints ms" in site_kp
    assert not any(k.startswith("pipeline") for k in site_det)
    assert not any(k.startswith(("AP@", "recall")) for k in site_kp)
    # the figures printed are the figures recorded
    printed = {line.split(" AP@0.5 ")[0]: line.rsplit(" ", 1)[1]
               for line in out.splitlines() if " AP@0.5 " in line and "(" not in line}
    assert float(printed["site"]) == pytest.approx(site_det["AP@0.5"], abs=1e-3)
    md = (folder / "detector.md").read_text()
    assert "## Through the deployed pipeline" in md and name in md
    assert md.index("## Far band") < md.index("## Through the deployed pipeline")
    # the same run again: one entry, replaced; a held-out run adds its own
    assert main(args) == 0
    assert main(["keypoints", "--model", str(folder), "--count", "2", "--seed", "5",
                 "--held-out-variations", "--far-band", "--record"]) == 0
    doc = json.loads((folder / "detector.json").read_text())
    shipped_entries = list(json.loads(shipped["detector.json"])["evaluations"])
    assert list(doc["evaluations"]) == [
        *shipped_entries, name, "held-out renderer variations, seed 5, with the far band"]
    # the shipped models' cards are untouched
    assert {n: (default_model_dir() / n).read_bytes() for n in SHIPPED_CARDS} == shipped


def test_record_refuses_with_calibrate_and_names_a_missing_card(tmp_path: Path,
                                                               capsys) -> None:
    folder = _models(tmp_path)
    assert main(["keypoints", "--model", str(folder), "--count", "2", "--calibrate",
                 "--record"]) == 2
    assert "--record writes evaluation figures" in capsys.readouterr().err
    (folder / "keypoints.json").rename(folder / "keypoints.json.bak")
    code = main(["keypoints", "--model", str(folder), "--count", "2", "--record"])
    assert code == 1
    assert "keypoints.json" in capsys.readouterr().err


def test_a_card_with_malformed_evaluations_is_refused_by_name(tmp_path: Path) -> None:
    from edge_agent.model_cards import ModelError

    folder = _models(tmp_path)
    doc = json.loads((folder / "detector.json").read_text())
    doc["evaluations"] = ["not", "a", "mapping"]
    (folder / "detector.json").write_text(json.dumps(doc))
    with pytest.raises(ModelError, match=r"detector\.json: bad model card: 'evaluations'"):
        DetectorCard.read(folder / "detector.json")
