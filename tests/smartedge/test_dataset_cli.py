"""``smartedge dataset``: info, a contact sheet with the labels drawn, the split and merge with
file names that still resolve, and a labelling tool's export imported against the site's robot
model (what does not match named, exit 1)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from core.coco import CocoAnnotation, CocoCategory, CocoDataset, CocoImage, read_dataset
from core.coco import write_dataset as write_coco
from smartedge.commands.dataset import main


def _frames(tmp_path: Path, names: tuple[str, ...], n: int = 8) -> Path:
    """``n`` frames of two cameras 0.5 s apart under ``tmp_path/frames`` with their labels."""
    root = tmp_path / "frames"
    images, annotations = [], []
    for i in range(n):
        cam = f"cam{i % 2}"
        stamp = 1_700_000_000_000_000_000 + i * 500_000_000
        rel = f"{cam}/{stamp}.png"
        (root / cam).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / rel), np.full((240, 320, 3), 60 + 10 * i, np.uint8))
        images.append(CocoImage(i + 1, rel, 320, 240, cam, stamp))
        kp = np.array([[100.0 + j * 10, 120.0, 2] for j in range(len(names))])
        annotations.append(CocoAnnotation(i + 1, i + 1, 1, (80.0, 90.0, 160.0, 80.0), kp,
                                          "hsr1", "auto", 0.5))
    path = root / "labels.json"
    write_coco(CocoDataset(tuple(images), tuple(annotations), (CocoCategory(1, "hsr", names),)),
               path)
    return path


def test_info_show_split_merge(tmp_path: Path, example_site, capsys) -> None:
    names = example_site.robot_model("hsr").keypoint_names
    labels = _frames(tmp_path, names)
    assert main(["info", str(labels)]) == 0
    out = capsys.readouterr().out
    assert "8 images (0 without a robot), 8 robots, 3.5 s of capture" in out
    assert "'auto': 8" in out

    # the contact sheet: every frame drawn, a keypoint filled red where the label says
    (labels.parent / "cam0" / "1700000001000000000.png").write_bytes(b"not a png")
    sheet = tmp_path / "sheet.png"
    assert main(["show", str(labels), "--out", str(sheet), "--count", "4"]) == 0
    captured = capsys.readouterr()
    assert "1 unreadable" in captured.out and "1700000001000000000.png" in captured.err
    img = cv2.imread(str(sheet))
    assert img is not None and img.shape[1] == 3 * 480  # three readable tiles in a row
    scale = 480 / 320
    b, g, r = img[round(120 * scale), round(100 * scale)]
    assert r > 200 and g < 60 and b < 60  # the first keypoint of the first frame

    # split by time into another folder: file names rewritten to resolve from there
    out = tmp_path / "split"
    assert main(["split", str(labels), "--val-share", "0.5", "--block-s", "1",
                 "--train", str(out / "train.json"), "--val", str(out / "val.json")]) == 0
    train, val = read_dataset(out / "train.json"), read_dataset(out / "val.json")
    assert len(train.images) + len(val.images) == 8 and val.images
    for part in (train, val):
        assert all((out / im.file_name).resolve().exists() for im in part.images)
    merged = tmp_path / "merged.json"
    assert main(["merge", str(out / "train.json"), str(out / "val.json"), "--out",
                 str(merged)]) == 0
    m = read_dataset(merged)
    assert len(m.images) == 8 and all((tmp_path / im.file_name).resolve().exists()
                                      for im in m.images)


def test_import_matches_a_cvat_export_to_the_robot_model(tmp_path: Path, example_site_path,
                                                         example_site, capsys) -> None:
    names = list(example_site.robot_model("hsr").keypoint_names)
    typed = [n.upper() for n in names[::-1]]  # another order, another case
    typed[0] = "Right (bottom)"  # what a person typed for the model's last keypoint
    kp = []
    for j in range(len(typed)):
        kp += [10.0 + j, 20.0, 2]
    doc = {"images": [{"id": 3, "file_name": "a.jpg", "width": 320, "height": 240}],
           "annotations": [{"id": 9, "image_id": 3, "category_id": 1,
                            "bbox": [5, 5, 100, 50], "keypoints": kp}],
           "categories": [{"id": 1, "name": "robot", "keypoints": typed}]}
    ext = tmp_path / "cvat" / "annotations.json"
    ext.parent.mkdir()
    ext.write_text(json.dumps(doc))
    out = tmp_path / "imported.json"
    argv = ["import", str(ext), "--site", str(example_site_path), "--robot-model", "hsr",
            "--out", str(out)]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert names[-1] in err and "Right (bottom)" in err and not out.exists()
    assert main([*argv, "--rename", f"Right (bottom)={names[-1]}"]) == 0
    ds = read_dataset(out)
    assert ds.categories[0].keypoints == tuple(names)
    got = ds.annotations[0].keypoints
    np.testing.assert_array_equal(got[:, 0], [10.0 + len(names) - 1 - j for j in range(len(names))])
    assert ds.images[0].file_name == "cvat/a.jpg"
    assert main(["import", str(ext), "--site", str(example_site_path), "--robot-model", "nope",
                 "--out", str(out)]) == 1
    assert "no robot model 'nope'" in capsys.readouterr().err


def test_usage_errors_exit_2(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["split", "x.json"])
    assert exc.value.code == 2
    assert main(["show", "x.json", "--out", "y.png", "--count", "0"]) == 2
