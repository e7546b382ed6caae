"""COCO keypoints files (core.coco): a round trip, what pycocotools makes of them, a CVAT-style
export with other keypoint names and order matched to a robot model, the entries a bad file is
refused for, atomic writes, the split by time and the merge."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from core.coco import (
    CocoAnnotation,
    CocoCategory,
    CocoDataset,
    CocoImage,
    DatasetError,
    conform_to_model,
    dataset_from_json,
    match_keypoints,
    merge_datasets,
    read_dataset,
    split_by_time,
    summary,
    write_dataset,
)

NAMES = ("base_front", "base_left", "base_right", "head_top")


def _dataset(n_images: int = 6, seconds_apart: float = 0.5) -> CocoDataset:
    rng = np.random.default_rng(0)
    images, annotations = [], []
    for i in range(n_images):
        stamp = 1_700_000_000_000_000_000 + int(i * seconds_apart * 1e9)
        images.append(CocoImage(i + 1, f"cam{i % 2}/{stamp}.png", 640, 480, f"cam{i % 2}", stamp))
        if i == n_images - 1:
            continue  # a frame without a robot
        kp = np.column_stack([rng.uniform(100, 500, 4), rng.uniform(100, 400, 4),
                              [2, 2, 1, 0]])
        annotations.append(CocoAnnotation(len(annotations) + 1, i + 1, 1,
                                          (90.0, 80.0, 420.0, 330.0), kp, "hsr1", "auto", 0.6))
    return CocoDataset(tuple(images), tuple(annotations), (CocoCategory(1, "hsr", NAMES),),
                       {"description": "test"})


def test_round_trip_keeps_everything(tmp_path: Path) -> None:
    ds = _dataset()
    path = write_dataset(ds, tmp_path / "d.json")
    back = read_dataset(path)
    assert back.images == ds.images and back.categories == ds.categories
    for a, b in zip(ds.annotations, back.annotations, strict=True):
        np.testing.assert_array_equal(a.keypoints, b.keypoints)
        assert (a.id, a.image_id, a.bbox, a.robot_id, a.label_source, a.sigma_px) == (
            b.id, b.image_id, b.bbox, b.robot_id, b.label_source, b.sigma_px)
    doc = json.loads(path.read_text())
    assert doc["annotations"][0]["num_keypoints"] == 3  # visibility 1 and 2 count, 0 not
    assert summary(back)["keypoints_visible"] == 2 * len(ds.annotations)
    assert summary(back)["images_without_robot"] == 1


def test_pycocotools_reads_the_file_and_scores_it_against_itself(tmp_path: Path,
                                                                 capsys) -> None:
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    ds = _dataset()
    path = write_dataset(ds, tmp_path / "d.json")
    gt = COCO(str(path))
    assert gt.getCatIds(catNms=["hsr"]) == [1]
    assert len(gt.getAnnIds()) == len(ds.annotations)
    assert gt.loadCats(1)[0]["keypoints"] == list(NAMES)
    dets = [{"image_id": a.image_id, "category_id": 1, "bbox": list(a.bbox), "score": 0.9,
             "keypoints": a.keypoints.reshape(-1).tolist()} for a in ds.annotations]
    ev = COCOeval(gt, gt.loadRes(dets), "keypoints")
    ev.params.kpt_oks_sigmas = np.full(len(NAMES), 0.05)
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    assert ev.stats[0] == pytest.approx(1.0)  # our labels as detections: AP 1


def test_a_cvat_export_with_other_names_and_order_is_matched_by_name() -> None:
    # as a person typed them in CVAT, in the order they were made, one the model lacks
    cvat_names = ["Head_Top", "base right", "BASE_FRONT", "base_left", "antenna"]
    doc = {"images": [{"id": 7, "file_name": "f.jpg", "width": 640, "height": 480}],
           "annotations": [{"id": 1, "image_id": 7, "category_id": 3, "bbox": [10, 10, 50, 60],
                            "keypoints": [1, 2, 2, 3, 4, 2, 5, 6, 2, 7, 8, 1, 9, 9, 2]}],
           "categories": [{"id": 3, "name": "robot", "keypoints": cvat_names}]}
    ds = dataset_from_json(doc, "cvat.json")
    m = match_keypoints(cvat_names, NAMES, {"base right": "base_right"})
    assert m.missing == () and m.extra == ("antenna",)
    with pytest.raises(DatasetError, match="antenna"):
        conform_to_model(ds, "robot", "hsr", NAMES, renames={"base right": "base_right"})
    with pytest.raises(DatasetError, match="base_right"):
        conform_to_model(ds, "robot", "hsr", NAMES, drop_extra=True)
    out, _ = conform_to_model(ds, "robot", "hsr", NAMES, renames={"base right": "base_right"},
                              drop_extra=True)
    kp = out.annotations[0].keypoints
    # the model's order: base_front, base_left, base_right, head_top
    np.testing.assert_array_equal(kp, [[5, 6, 2], [7, 8, 1], [3, 4, 2], [1, 2, 2]])
    assert out.categories == (CocoCategory(1, "hsr", NAMES),)
    missing, m2 = conform_to_model(ds, "robot", "hsr", NAMES, drop_extra=True,
                                   allow_missing=True)
    assert m2.missing == ("base_right",)
    np.testing.assert_array_equal(missing.annotations[0].keypoints[2], [0, 0, 0])


@pytest.mark.parametrize(("mutate", "named"), [
    (lambda d: d["images"].append(dict(d["images"][0])), "images: ids used twice"),
    (lambda d: d["annotations"][0].update(image_id=99), "image_id 99"),
    (lambda d: d["annotations"][0].update(category_id=5), "category_id 5"),
    (lambda d: d["annotations"][0].update(keypoints=[1, 2, 2]), "keypoints has 3 values"),
    (lambda d: d["annotations"][0]["keypoints"].__setitem__(2, 3), "visibility 3"),
    (lambda d: d["annotations"][0]["keypoints"].__setitem__(0, float("nan")), "not finite"),
    (lambda d: d["annotations"][0].update(bbox=[600, 10, 100, 20]), "not inside its image"),
    (lambda d: d["annotations"][0].update(bbox=[1, 2, 3]), "bbox is not"),
    (lambda d: d["categories"][0].update(keypoints=["a", "a", "b", "c"]), "names twice"),
    (lambda d: d.pop("categories"), "categories: missing"),
    (lambda d: d["images"][0].update(width="640"), "width is not an integer"),
])
def test_a_bad_file_is_refused_with_the_entry_named(tmp_path: Path, mutate, named) -> None:
    doc = _dataset().to_json()
    mutate(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(DatasetError, match=named) as exc:
        read_dataset(path)
    assert str(path) in str(exc.value)


def test_unreadable_and_truncated_files_are_named(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="cannot read"):
        read_dataset(tmp_path / "absent.json")
    half = tmp_path / "half.json"
    half.write_text(json.dumps(_dataset().to_json())[:200])
    with pytest.raises(DatasetError, match=r"half\.json: not JSON"):
        read_dataset(half)


def test_a_failed_write_leaves_the_old_file_whole(tmp_path: Path, monkeypatch) -> None:
    path = write_dataset(_dataset(3), tmp_path / "d.json")
    before = path.read_bytes()

    def boom(*_args, **_kwargs) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", boom)
    with pytest.raises(OSError, match="disk full"):
        write_dataset(_dataset(6), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["d.json"]  # no temporary left behind


def test_split_by_time_never_puts_one_second_on_both_sides() -> None:
    ds = _dataset(n_images=120, seconds_apart=0.25)  # 30 s of frames, four per second
    train, val = split_by_time(ds, 0.3, block_s=5, seed=1)
    assert len(train.images) + len(val.images) == 120 and len(val.images) > 0
    sec = {im.stamp_ns // 1_000_000_000 for im in train.images}
    assert not sec & {im.stamp_ns // 1_000_000_000 for im in val.images}
    assert {a.image_id for a in val.annotations} <= {im.id for im in val.images}
    again = split_by_time(ds, 0.3, block_s=5, seed=1)[1]
    assert [im.id for im in again.images] == [im.id for im in val.images]  # seeded
    with pytest.raises(DatasetError, match="at least 1 s"):
        split_by_time(ds, 0.3, block_s=0.5)


def test_merge_renumbers_and_refuses_other_keypoints() -> None:
    a, b = _dataset(4), _dataset(5)
    m = merge_datasets([a, b], roots=["", "drive2"])
    assert [im.id for im in m.images] == list(range(1, 10))
    assert len({x.id for x in m.annotations}) == len(a.annotations) + len(b.annotations)
    assert m.images[4].file_name.startswith("drive2/")
    assert all(m.images[x.image_id - 1] for x in m.annotations)
    other = CocoDataset(b.images, (), (CocoCategory(1, "hsr", NAMES[::-1]),))
    with pytest.raises(DatasetError, match="category 'hsr' has keypoints"):
        merge_datasets([a, other])
