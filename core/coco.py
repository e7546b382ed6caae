"""COCO keypoints datasets: the one format of labelled camera frames.

What CVAT, Label Studio and Roboflow export and what ``pycocotools`` reads: ``images`` (``id``,
``file_name``, ``width``, ``height``), ``annotations`` (``id``, ``image_id``, ``category_id``,
``bbox`` ``[x, y, w, h]`` in pixels, ``keypoints`` ``[u, v, visibility] * K``,
``num_keypoints``, ``area``, ``iscrowd``) and ``categories`` (``id``, ``name``, ``keypoints``
names, ``skeleton``). smartedge keeps one category per robot model, named as the site file
names the model, with the model's keypoint names in the model's order.

smartedge's own fields ride along where COCO allows extra keys (other tools ignore them): per
image ``camera_id`` and ``stamp_ns`` (the capture stamp the frame's detections carry); per
annotation ``robot_id``, ``label_source`` (``manual``, ``auto``, ...) and ``sigma_px`` (the
label's expected pixel uncertainty, auto-labels); ``info`` at the top.

Visibility as COCO defines it: 0 not labelled (outside the image, or unknown), 1 labelled but
not visible (occluded), 2 labelled and visible. Pixel coordinates are read and written as the
tools write them (OpenCV's: the centre of the top-left pixel at (0, 0)).

:func:`read_dataset` refuses a file that is not such a dataset with a :class:`DatasetError`
naming the file and the entry (duplicate ids, an annotation of an unknown image or category,
a keypoint list of the wrong length, a visibility other than 0/1/2, a non-finite number, a box
outside its image); :func:`write_dataset` writes atomically (a temporary file renamed over the
target: never half a file after a crash). :func:`match_keypoints` maps an external file's
category onto a robot model by keypoint name (CVAT exports keep the names a person typed, in the
order they were made). :func:`split_by_time` and :func:`merge_datasets` are the tools' verbs;
:func:`labelled_frames` reads a dataset's frames with their labels for scoring and training.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
import os
import tempfile
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from protocol.errors import SmartedgeError

#: how far (px) a box may reach past its image's border before the entry is refused (rounding)
BOX_TOLERANCE_PX: Final = 1.0
VISIBILITIES: Final = (0, 1, 2)


class DatasetError(SmartedgeError, ValueError):
    """A dataset file that cannot be used; the message names the file and the entry."""


@dataclasses.dataclass(frozen=True)
class CocoImage:
    """One frame: ``file_name`` relative to the dataset's image root; ``camera_id`` and
    ``stamp_ns`` (capture stamp, ns) where known."""

    id: int
    file_name: str
    width: int
    height: int
    camera_id: str = ""
    stamp_ns: int | None = None


@dataclasses.dataclass(frozen=True)
class CocoCategory:
    """One robot model: ``name`` as the site file names it, ``keypoints`` its keypoint names in
    order, ``skeleton`` pairs of 1-based keypoint indices (drawing only)."""

    id: int
    name: str
    keypoints: tuple[str, ...]
    skeleton: tuple[tuple[int, int], ...] = ()


@dataclasses.dataclass(frozen=True, eq=False)
class CocoAnnotation:
    """One robot in one frame: ``bbox`` (x, y, w, h) px; ``keypoints`` (K, 3) of (u, v,
    visibility); ``sigma_px`` the label's expected pixel uncertainty (``None``: not stated)."""

    id: int
    image_id: int
    category_id: int
    bbox: tuple[float, float, float, float]
    keypoints: np.ndarray
    robot_id: str = ""
    label_source: str = "manual"
    sigma_px: float | None = None
    iscrowd: int = 0

    @property
    def bbox_xyxy(self) -> np.ndarray:
        """(4,) the box as edges (x0, y0, x1, y1)."""
        x, y, w, h = self.bbox
        return np.array([x, y, x + w, y + h])

    @property
    def num_visible(self) -> int:
        """Keypoints labelled visible (visibility 2)."""
        return int((self.keypoints[:, 2] == 2).sum())

    @property
    def num_labelled(self) -> int:
        """Keypoints with a label (visibility 1 or 2): COCO's ``num_keypoints``."""
        return int((self.keypoints[:, 2] > 0).sum())


@dataclasses.dataclass(frozen=True, eq=False)
class CocoDataset:
    """A whole dataset; ids are unique within their list (checked on reading)."""

    images: tuple[CocoImage, ...]
    annotations: tuple[CocoAnnotation, ...]
    categories: tuple[CocoCategory, ...]
    info: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def category(self, name: str) -> CocoCategory:
        for c in self.categories:
            if c.name == name:
                return c
        raise DatasetError(f"no category {name!r} (categories: "
                           f"{[c.name for c in self.categories]})")

    @functools.cached_property
    def _by_image(self) -> dict[int, list[CocoAnnotation]]:
        index: dict[int, list[CocoAnnotation]] = {}
        for a in self.annotations:
            index.setdefault(a.image_id, []).append(a)
        return index

    def annotations_of(self, image_id: int) -> list[CocoAnnotation]:
        return list(self._by_image.get(image_id, ()))

    def to_json(self) -> dict[str, Any]:
        """The COCO document (plain JSON types)."""
        images = []
        for im in self.images:
            d: dict[str, Any] = {"id": im.id, "file_name": im.file_name, "width": im.width,
                                 "height": im.height}
            if im.camera_id:
                d["camera_id"] = im.camera_id
            if im.stamp_ns is not None:
                d["stamp_ns"] = int(im.stamp_ns)
            images.append(d)
        annotations = []
        for a in self.annotations:
            x, y, w, h = (float(v) for v in a.bbox)
            d = {"id": a.id, "image_id": a.image_id, "category_id": a.category_id,
                 "bbox": [x, y, w, h], "area": w * h, "iscrowd": int(a.iscrowd),
                 "keypoints": [float(v) if i % 3 < 2 else int(v)
                               for i, v in enumerate(np.asarray(a.keypoints).reshape(-1))],
                 "num_keypoints": a.num_labelled, "label_source": a.label_source}
            if a.robot_id:
                d["robot_id"] = a.robot_id
            if a.sigma_px is not None:
                d["sigma_px"] = float(a.sigma_px)
            annotations.append(d)
        categories = [{"id": c.id, "name": c.name, "supercategory": "robot",
                       "keypoints": list(c.keypoints),
                       "skeleton": [list(p) for p in c.skeleton]} for c in self.categories]
        return {"info": dict(self.info), "images": images, "annotations": annotations,
                "categories": categories}


# ------------------------------------------------------------------------------ reading


class _Entry:
    """Names the entry a check is about: ``FILE: annotations[3] (id 17): ...``."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, where: str, why: str) -> DatasetError:
        return DatasetError(f"{self.source}: {where}: {why}")


def _number(entry: _Entry, where: str, value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise entry.fail(where, f"{what} is not a number ({value!r})")
    if not math.isfinite(float(value)):
        raise entry.fail(where, f"{what} is not finite ({value!r})")
    return float(value)


def _integer(entry: _Entry, where: str, value: object, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise entry.fail(where, f"{what} is not an integer ({value!r})")
    return value


def _list(entry: _Entry, doc: Mapping[str, Any], key: str) -> list[Any]:
    value = doc.get(key, [] if key != "categories" else None)
    if not isinstance(value, list):
        raise entry.fail(key, "missing or not a list")
    return value


def _mapping(entry: _Entry, where: str, value: object) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise entry.fail(where, f"not an object ({type(value).__name__})")
    return value


def _image(entry: _Entry, i: int, raw: object) -> CocoImage:
    d = _mapping(entry, f"images[{i}]", raw)
    where = f"images[{i}] (id {d.get('id')!r})"
    file_name = d.get("file_name")
    if not isinstance(file_name, str) or not file_name:
        raise entry.fail(where, "file_name missing")
    width = _integer(entry, where, d.get("width"), "width")
    height = _integer(entry, where, d.get("height"), "height")
    if width <= 0 or height <= 0:
        raise entry.fail(where, f"size {width} x {height}")
    stamp = d.get("stamp_ns")
    if stamp is not None:
        stamp = _integer(entry, where, stamp, "stamp_ns")
        if stamp < 0:
            raise entry.fail(where, f"stamp_ns {stamp} < 0")
    camera_id = d.get("camera_id", "")
    if not isinstance(camera_id, str):
        raise entry.fail(where, f"camera_id is not a string ({camera_id!r})")
    return CocoImage(_integer(entry, where, d.get("id"), "id"), file_name, width, height,
                     camera_id, stamp)


def _category(entry: _Entry, i: int, raw: object) -> CocoCategory:
    d = _mapping(entry, f"categories[{i}]", raw)
    where = f"categories[{i}] (id {d.get('id')!r})"
    name = d.get("name")
    if not isinstance(name, str) or not name:
        raise entry.fail(where, "name missing")
    names = d.get("keypoints")
    if not isinstance(names, list) or not names or not all(
            isinstance(n, str) and n for n in names):
        raise entry.fail(where, "keypoints is not a list of keypoint names")
    dup = [n for n, k in Counter(names).items() if k > 1]
    if dup:
        raise entry.fail(where, f"keypoint names twice: {dup}")
    skeleton = []
    for pair in d.get("skeleton") or []:
        if (not isinstance(pair, list) or len(pair) != 2
                or not all(isinstance(v, int) and 1 <= v <= len(names) for v in pair)):
            raise entry.fail(where, f"skeleton entry {pair!r} is not a pair of 1-based "
                                    f"keypoint indices")
        skeleton.append((pair[0], pair[1]))
    return CocoCategory(_integer(entry, where, d.get("id"), "id"), name, tuple(names),
                        tuple(skeleton))


def _annotation(entry: _Entry, i: int, raw: object, images: Mapping[int, CocoImage],
                categories: Mapping[int, CocoCategory]) -> CocoAnnotation:
    d = _mapping(entry, f"annotations[{i}]", raw)
    where = f"annotations[{i}] (id {d.get('id')!r})"
    image_id = _integer(entry, where, d.get("image_id"), "image_id")
    category_id = _integer(entry, where, d.get("category_id"), "category_id")
    if image_id not in images:
        raise entry.fail(where, f"image_id {image_id} is no image of the file")
    if category_id not in categories:
        raise entry.fail(where, f"category_id {category_id} is no category of the file")
    image, category = images[image_id], categories[category_id]
    bbox = d.get("bbox")
    if not isinstance(bbox, list) or len(bbox) != 4:
        raise entry.fail(where, f"bbox is not [x, y, w, h] ({bbox!r})")
    x, y, w, h = (_number(entry, where, v, "bbox") for v in bbox)
    tol = BOX_TOLERANCE_PX
    if w <= 0 or h <= 0 or x < -tol or y < -tol or x + w > image.width + tol or (
            y + h > image.height + tol):
        raise entry.fail(where, f"bbox [{x:g}, {y:g}, {w:g}, {h:g}] is not inside its image "
                                f"{image.file_name!r} ({image.width} x {image.height})")
    raw_kp = d.get("keypoints")
    k = len(category.keypoints)
    if not isinstance(raw_kp, list) or len(raw_kp) != 3 * k:
        raise entry.fail(where, f"keypoints has {len(raw_kp) if isinstance(raw_kp, list) else 0}"
                                f" values; category {category.name!r} has {k} keypoints (3 "
                                f"values each: u, v, visibility)")
    kp = np.array([_number(entry, where, v, "keypoints") for v in raw_kp]).reshape(k, 3)
    bad = [int(v) for v in kp[:, 2] if v not in VISIBILITIES]
    if bad:
        raise entry.fail(where, f"visibility {bad[0]} (COCO's are 0, 1, 2)")
    sigma = d.get("sigma_px")
    if sigma is not None:
        sigma = _number(entry, where, sigma, "sigma_px")
    source = d.get("label_source", "manual")
    robot_id = d.get("robot_id", "")
    return CocoAnnotation(_integer(entry, where, d.get("id"), "id"), image_id, category_id,
                          (x, y, w, h), kp, str(robot_id), str(source), sigma,
                          int(d.get("iscrowd", 0) or 0))


def _unique(entry: _Entry, key: str, ids: Iterable[int]) -> None:
    dup = sorted(i for i, n in Counter(ids).items() if n > 1)
    if dup:
        raise entry.fail(key, f"ids used twice: {dup[:10]}")


def dataset_from_json(doc: object, source: str = "dataset") -> CocoDataset:
    """A :class:`CocoDataset` from a parsed COCO document; ``source`` names it in errors."""
    entry = _Entry(source)
    doc = _mapping(entry, "the document", doc)
    images = tuple(_image(entry, i, raw) for i, raw in enumerate(_list(entry, doc, "images")))
    categories = tuple(_category(entry, i, raw)
                       for i, raw in enumerate(_list(entry, doc, "categories")))
    _unique(entry, "images", (im.id for im in images))
    _unique(entry, "categories", (c.id for c in categories))
    by_image = {im.id: im for im in images}
    by_category = {c.id: c for c in categories}
    annotations = tuple(_annotation(entry, i, raw, by_image, by_category)
                        for i, raw in enumerate(_list(entry, doc, "annotations")))
    _unique(entry, "annotations", (a.id for a in annotations))
    info = doc.get("info") or {}
    return CocoDataset(images, annotations, categories, dict(_mapping(entry, "info", info)))


def read_dataset(path: str | Path) -> CocoDataset:
    """Read and check a COCO keypoints file (:class:`DatasetError` names the file and entry)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not JSON ({exc})") from exc
    return dataset_from_json(doc, str(path))


def write_dataset(dataset: CocoDataset, path: str | Path) -> Path:
    """Write ``dataset`` to ``path`` atomically (a temporary file beside it, renamed over it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(dataset.to_json(), f, separators=(",", ":"))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


# ------------------------------------------------------------------------------ robot models


@dataclasses.dataclass(frozen=True)
class KeypointMatch:
    """How an external category's keypoints map onto a robot model's: ``index[j]`` is the
    external keypoint that model keypoint ``j`` takes (-1: none, labelled 0); ``missing`` model
    keypoints the file lacks, ``extra`` keypoints of the file the model lacks (dropped)."""

    index: tuple[int, ...]
    missing: tuple[str, ...]
    extra: tuple[str, ...]

    def describe(self) -> str:
        parts = []
        if self.missing:
            parts.append(f"the model's keypoints not in the file: {list(self.missing)}")
        if self.extra:
            parts.append(f"the file's keypoints the model lacks: {list(self.extra)}")
        return "; ".join(parts) or "every keypoint matches by name"


def match_keypoints(external: Sequence[str], model: Sequence[str],
                    renames: Mapping[str, str] | None = None) -> KeypointMatch:
    """Match an external category's keypoint names onto a model's, by name after ``renames``
    (external name -> model name); case and surrounding spaces do not matter."""
    renames = {k.strip().lower(): v for k, v in (renames or {}).items()}

    def norm(name: str) -> str:
        n = name.strip().lower()
        return renames.get(n, n).strip().lower()

    ext = [norm(n) for n in external]
    pos = {n: i for i, n in enumerate(ext)}
    index = tuple(pos.get(n.strip().lower(), -1) for n in model)
    used = {i for i in index if i >= 0}
    missing = tuple(m for m, i in zip(model, index, strict=True) if i < 0)
    extra = tuple(external[i] for i in range(len(external)) if i not in used)
    return KeypointMatch(index, missing, extra)


def conform_to_model(dataset: CocoDataset, category_name: str, model_name: str,
                     model_keypoints: Sequence[str], *, renames: Mapping[str, str] | None = None,
                     allow_missing: bool = False, drop_extra: bool = False,
                     label_source: str = "manual") -> tuple[CocoDataset, KeypointMatch]:
    """``dataset``'s category ``category_name`` as the robot model ``model_name`` (its keypoint
    names in its order; the other categories and their annotations are left out). Refused
    (:class:`DatasetError`, saying what does not match) when a model keypoint is missing unless
    ``allow_missing`` (then labelled 0) or the file has keypoints the model lacks unless
    ``drop_extra``."""
    category = dataset.category(category_name)
    match = match_keypoints(category.keypoints, model_keypoints, renames)
    if (match.missing and not allow_missing) or (match.extra and not drop_extra):
        raise DatasetError(f"category {category_name!r} does not match robot model "
                           f"{model_name!r}: {match.describe()} (rename with old=new, or allow "
                           f"missing / drop extra keypoints)")
    index = np.array(match.index)
    annotations = []
    for a in dataset.annotations:
        if a.category_id != category.id:
            continue
        kp = np.zeros((len(model_keypoints), 3))
        have = index >= 0
        kp[have] = a.keypoints[index[have]]
        annotations.append(dataclasses.replace(
            a, category_id=1, keypoints=kp,
            label_source=a.label_source if a.label_source != "manual" else label_source))
    cat = CocoCategory(1, model_name, tuple(model_keypoints))
    used = {a.image_id for a in annotations}
    annotated = {a.image_id for a in dataset.annotations}
    images = tuple(im for im in dataset.images if im.id in used or im.id not in annotated)
    return CocoDataset(images, tuple(annotations), (cat,), dict(dataset.info)), match


# ------------------------------------------------------------------------------ frames


@dataclasses.dataclass(frozen=True, eq=False)
class RobotLabels:
    """One robot's labels as the networks' code reads them (the fields of a rendered sample's
    robot): ``bbox_xyxy`` box edges (``None``: no robot in the frame), ``keypoints_px`` (K, 2),
    ``visible`` (K,) labelled visible, ``in_image`` (K,) labelled at all."""

    bbox_xyxy: np.ndarray | None
    keypoints_px: np.ndarray
    visible: np.ndarray
    in_image: np.ndarray

    @classmethod
    def of(cls, annotation: CocoAnnotation | None, num_keypoints: int) -> RobotLabels:
        if annotation is None:
            k = num_keypoints
            return cls(None, np.zeros((k, 2)), np.zeros(k, bool), np.zeros(k, bool))
        kp = annotation.keypoints
        return cls(annotation.bbox_xyxy, kp[:, :2].copy(), kp[:, 2] == 2, kp[:, 2] > 0)


@dataclasses.dataclass(frozen=True, eq=False)
class LabelledFrame:
    """A dataset frame read for scoring or training, shaped as a rendered sample (``mode``
    ``"real"``; no simulated ``camera`` or ``robot_pose``): the image, its robot's labels
    (one: none or one robot), and the COCO entries it came from."""

    image: CocoImage
    image_rgb: np.ndarray
    robots: list[RobotLabels]
    annotation: CocoAnnotation | None
    mode: str = "real"
    camera: Any = None
    robot_pose: Any = None


def labelled_frames(dataset: CocoDataset, category: CocoCategory, image_root: Path,
                    read_rgb: Callable[[Path], np.ndarray | None]
                    ) -> tuple[list[LabelledFrame], dict[str, list[str]]]:
    """The frames of ``dataset`` with at most one robot of ``category`` each, read with
    ``read_rgb(path)`` (an (H, W, 3) RGB image or ``None``), and what was left out, named:
    ``several robots`` (the scorers and trainers here take one robot per frame) and
    ``unreadable`` images."""
    skipped: dict[str, list[str]] = {"several robots": [], "unreadable": []}
    frames = []
    k = len(category.keypoints)
    for im in dataset.images:
        anns = [a for a in dataset.annotations_of(im.id) if a.category_id == category.id]
        if len(anns) > 1:
            skipped["several robots"].append(im.file_name)
            continue
        path = image_root / im.file_name
        rgb = read_rgb(path)
        if rgb is None:
            skipped["unreadable"].append(str(path))
            continue
        ann = anns[0] if anns else None
        frames.append(LabelledFrame(im, rgb, [RobotLabels.of(ann, k)], ann))
    return frames, skipped


# ------------------------------------------------------------------------------ verbs


def split_by_time(dataset: CocoDataset, validation_share: float, *, block_s: float = 10.0,
                  seed: int = 0) -> tuple[CocoDataset, CocoDataset]:
    """(train, validation): the frames cut into blocks of ``block_s`` seconds of capture time
    (images without a stamp: each its own block), about ``validation_share`` of the blocks
    (seeded) to validation, so two frames of the same second are never on both sides."""
    if not 0.0 < validation_share < 1.0:
        raise DatasetError(f"validation share {validation_share} is not between 0 and 1")
    if block_s < 1.0:
        raise DatasetError(f"block of {block_s} s: at least 1 s (frames of one second stay "
                           f"on one side)")
    block_ns = round(block_s) * 1_000_000_000

    def block(im: CocoImage) -> tuple[int, int]:
        return (0, im.stamp_ns // block_ns) if im.stamp_ns is not None else (1, im.id)

    blocks = sorted({block(im) for im in dataset.images})
    rng = np.random.default_rng(seed)
    n_val = min(max(1, round(validation_share * len(blocks))), max(len(blocks) - 1, 0))
    chosen = set(rng.choice(len(blocks), size=n_val, replace=False).tolist()) if n_val else set()
    val_blocks = {blocks[i] for i in chosen}
    val_ids = {im.id for im in dataset.images if block(im) in val_blocks}

    def part(keep_val: bool) -> CocoDataset:
        ids = {im.id for im in dataset.images if (im.id in val_ids) == keep_val}
        return CocoDataset(tuple(im for im in dataset.images if im.id in ids),
                           tuple(a for a in dataset.annotations if a.image_id in ids),
                           dataset.categories, dict(dataset.info))

    return part(False), part(True)


def merge_datasets(datasets: Sequence[CocoDataset], *, roots: Sequence[str] | None = None
                   ) -> CocoDataset:
    """One dataset of several with the same categories (by name and keypoint names); image and
    annotation ids renumbered from 1; ``roots`` (one per dataset) prefixes each one's file
    names (its folder relative to the merged file)."""
    if not datasets:
        raise DatasetError("nothing to merge")
    cats = {c.name: c for c in datasets[0].categories}
    for n, d in enumerate(datasets[1:], start=2):
        for c in d.categories:
            if c.name in cats and cats[c.name].keypoints != c.keypoints:
                raise DatasetError(f"dataset {n}: category {c.name!r} has keypoints "
                                   f"{list(c.keypoints)}, dataset 1 {list(cats[c.name].keypoints)}")
            cats.setdefault(c.name, c)
    categories = tuple(dataclasses.replace(c, id=i) for i, c in enumerate(cats.values(), 1))
    cat_id = {c.name: c.id for c in categories}
    images: list[CocoImage] = []
    annotations: list[CocoAnnotation] = []
    for n, d in enumerate(datasets):
        root = (roots[n].rstrip("/") + "/") if roots and roots[n] else ""
        old_cat = {c.id: c.name for c in d.categories}
        new_image = {}
        for im in d.images:
            new_image[im.id] = len(images) + 1
            images.append(dataclasses.replace(im, id=new_image[im.id],
                                              file_name=root + im.file_name))
        for a in d.annotations:
            annotations.append(dataclasses.replace(
                a, id=len(annotations) + 1, image_id=new_image[a.image_id],
                category_id=cat_id[old_cat[a.category_id]]))
    return CocoDataset(tuple(images), tuple(annotations), categories,
                       {"merged_from": len(datasets)})


def summary(dataset: CocoDataset) -> dict[str, Any]:
    """Counts a person checks before training: images, robots, per camera and category, labels'
    sources, keypoints labelled and visible, images without a robot, the time span."""
    stamps = [im.stamp_ns for im in dataset.images if im.stamp_ns is not None]
    annotated = {a.image_id for a in dataset.annotations}
    names = {c.id: c.name for c in dataset.categories}
    return {
        "images": len(dataset.images),
        "annotations": len(dataset.annotations),
        "images_without_robot": len(dataset.images) - len(annotated),
        "per_camera": dict(Counter(im.camera_id or "?" for im in dataset.images)),
        "per_category": dict(Counter(names[a.category_id] for a in dataset.annotations)),
        "label_sources": dict(Counter(a.label_source for a in dataset.annotations)),
        "keypoints_labelled": sum(a.num_labelled for a in dataset.annotations),
        "keypoints_visible": sum(a.num_visible for a in dataset.annotations),
        "span_s": (max(stamps) - min(stamps)) / 1e9 if stamps else None,
    }


__all__ = ["BOX_TOLERANCE_PX", "VISIBILITIES", "CocoAnnotation", "CocoCategory", "CocoDataset",
           "CocoImage", "DatasetError", "KeypointMatch", "LabelledFrame", "RobotLabels",
           "conform_to_model", "dataset_from_json", "labelled_frames", "match_keypoints",
           "merge_datasets", "read_dataset", "split_by_time", "summary", "write_dataset"]
