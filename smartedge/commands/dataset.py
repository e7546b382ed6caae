"""``smartedge dataset``: labelled camera frames in COCO keypoints files (:mod:`core.coco`).

- ``capture --recording REC.mcap --out DIR [--camera TOPIC=ID ...] [--rate HZ]``: the frames of
  the ``sensor_msgs/Image`` and ``CompressedImage`` topics of a ROS 2 MCAP (a lab's bag of its
  cameras) as ``DIR/<camera_id>/<stamp_ns>.<png|jpg>``, named by their header stamps, the
  layout ``smartedge edge-agent --capture`` writes; JPEG and PNG messages kept byte for byte;
- ``info DATASET.json``: images, robots, per camera and robot model, where the labels come from,
  keypoints labelled and visible, the time span;
- ``show DATASET.json --out SHEET.png [--images DIR] [--count N]``: a contact sheet, the labels
  drawn over the frames (box, visible keypoints filled, occluded ones hollow), the picture a
  person checks before training on it;
- ``split DATASET.json --val-share 0.2 --train OUT --val OUT [--block-s 10]``: train and
  validation by capture time, never two frames of the same second on both sides;
- ``merge A.json B.json ... --out OUT.json``: one file of several (ids renumbered, file names
  made relative to the merged file);
- ``import EXTERNAL.json --site SITE --robot-model NAME --out OUT.json [--category C]
  [--rename old=new ...] [--allow-missing] [--drop-extra]``: a labelling tool's export (CVAT,
  Label Studio, Roboflow) checked against the site's robot model by keypoint name and written
  in the model's order; what does not match is named.

Exit codes: 0 done, 1 a file that cannot be used (named), 2 usage.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from core.coco import (
    CocoDataset,
    DatasetError,
    conform_to_model,
    merge_datasets,
    read_dataset,
    split_by_time,
    summary,
    write_dataset,
)
from protocol.errors import SmartedgeError


def _info(args: argparse.Namespace) -> int:
    ds = read_dataset(args.dataset)
    s = summary(ds)
    span = f", {s['span_s']:.1f} s of capture" if s["span_s"] is not None else ""
    print(f"{args.dataset}: {s['images']} images ({s['images_without_robot']} without a robot), "
          f"{s['annotations']} robots{span}")
    print(f"  per camera: {s['per_camera']}")
    print(f"  per robot model: {s['per_category']}")
    print(f"  labels from: {s['label_sources']}")
    print(f"  keypoints: {s['keypoints_labelled']} labelled, {s['keypoints_visible']} visible")
    for c in ds.categories:
        print(f"  category {c.id} {c.name!r}: keypoints {list(c.keypoints)}")
    return 0


def _root_for(dataset_file: str | Path, out_file: str | Path) -> str:
    """The folder of ``dataset_file`` relative to ``out_file``'s ("" when the same): what the
    file names of a dataset written elsewhere are prefixed with."""
    rel = Path(os.path.relpath(Path(dataset_file).resolve().parent,
                               Path(out_file).resolve().parent)).as_posix()
    return "" if rel == "." else rel


def _split(args: argparse.Namespace) -> int:
    ds = read_dataset(args.dataset)
    train, val = split_by_time(ds, args.val_share, block_s=args.block_s, seed=args.seed)
    for part, out in ((train, args.train), (val, args.val)):
        moved = merge_datasets([part], roots=[_root_for(args.dataset, out)])
        write_dataset(CocoDataset(moved.images, moved.annotations, moved.categories,
                                  dict(ds.info)), Path(out))
    print(f"train {args.train}: {len(train.images)} images, {len(train.annotations)} robots; "
          f"validation {args.val}: {len(val.images)} images, {len(val.annotations)} robots "
          f"(blocks of {args.block_s:g} s)")
    return 0


def _merge(args: argparse.Namespace) -> int:
    out = Path(args.out)
    datasets = [read_dataset(p) for p in args.datasets]
    merged = merge_datasets(datasets, roots=[_root_for(p, out) for p in args.datasets])
    write_dataset(merged, out)
    print(f"wrote {out}: {len(merged.images)} images, {len(merged.annotations)} robots from "
          f"{len(datasets)} files")
    return 0


def _renames(pairs: Sequence[str]) -> dict[str, str]:
    out = {}
    for pair in pairs:
        old, sep, new = pair.partition("=")
        if not sep or not old.strip() or not new.strip():
            raise DatasetError(f"--rename {pair!r}: give old=new")
        out[old.strip()] = new.strip()
    return out


def _import(args: argparse.Namespace) -> int:
    from core.site import load_site

    site = load_site(args.site)
    if args.robot_model not in site.robot_models:
        raise DatasetError(f"{args.site}: no robot model {args.robot_model!r} (models: "
                           f"{sorted(site.robot_models)})")
    model = site.robot_models[args.robot_model]
    ds = read_dataset(args.external)
    if args.category is None:
        if len(ds.categories) != 1:
            raise DatasetError(f"{args.external}: {len(ds.categories)} categories "
                               f"{[c.name for c in ds.categories]}: name one with --category")
        category = ds.categories[0].name
    else:
        category = args.category
    conformed, match = conform_to_model(
        ds, category, model.name, model.keypoint_names, renames=_renames(args.rename),
        allow_missing=args.allow_missing, drop_extra=args.drop_extra,
        label_source=args.label_source)
    out = Path(args.out)
    moved = merge_datasets([conformed], roots=[_root_for(args.external, out)])
    info = {**dict(ds.info), "imported_from": str(args.external), "robot_model": model.name}
    write_dataset(CocoDataset(moved.images, moved.annotations, moved.categories, info), out)
    print(f"{args.external}: category {category!r} as robot model {model.name!r}: "
          f"{match.describe()}")
    print(f"wrote {out}: {len(moved.images)} images, {len(moved.annotations)} robots")
    return 0


# ------------------------------------------------------------------------------ contact sheet


def draw_labels(image_bgr: np.ndarray, dataset: CocoDataset, image_id: int) -> np.ndarray:
    """``image_bgr`` with the labels of ``image_id`` drawn: box, keypoints (visible filled,
    occluded hollow), the robot and the labels' source."""
    import cv2

    out = image_bgr.copy()
    scale = max(1, round(max(out.shape[:2]) / 640))
    for a in dataset.annotations_of(image_id):
        x, y, w, h = a.bbox
        colour = (0, 200, 255) if a.label_source == "auto" else (80, 255, 80)
        cv2.rectangle(out, (round(x), round(y)), (round(x + w), round(y + h)), colour, scale)
        text = f"{a.robot_id or a.category_id} {a.label_source}"
        cv2.putText(out, text, (round(x), max(12, round(y) - 4)), cv2.FONT_HERSHEY_SIMPLEX,
                    0.45 * scale, colour, scale, cv2.LINE_AA)
        for u, v, vis in a.keypoints:
            if vis == 0:
                continue
            cv2.circle(out, (round(u), round(v)), 3 * scale, (0, 0, 255),
                       -1 if vis == 2 else scale, cv2.LINE_AA)
    return out


def _show(args: argparse.Namespace) -> int:
    import cv2

    ds = read_dataset(args.dataset)
    root = Path(args.images) if args.images else Path(args.dataset).resolve().parent
    if not ds.images:
        raise DatasetError(f"{args.dataset}: no images")
    pick = np.linspace(0, len(ds.images) - 1, min(args.count, len(ds.images))).round()
    tiles, skipped = [], []
    tile_w = 480
    for i in sorted({int(v) for v in pick}):
        im = ds.images[i]
        path = root / im.file_name
        frame = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if frame is None:
            skipped.append(str(path))
            continue
        drawn = draw_labels(frame, ds, im.id)
        h = round(drawn.shape[0] * tile_w / drawn.shape[1])
        tile = cv2.resize(drawn, (tile_w, h), interpolation=cv2.INTER_AREA)
        cv2.putText(tile, f"{im.camera_id or '?'} {im.file_name}"[:60], (4, h - 6),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    for path in skipped:
        print(f"skipped {path}: unreadable or missing", file=sys.stderr)
    if not tiles:
        raise DatasetError(f"{args.dataset}: none of the {len(pick)} images picked could be "
                           f"read under {root}")
    cols = min(4, len(tiles))
    rows = math.ceil(len(tiles) / cols)
    tile_h = max(t.shape[0] for t in tiles)
    sheet = np.zeros((rows * tile_h, cols * tile_w, 3), np.uint8)
    for k, t in enumerate(tiles):
        r, c = divmod(k, cols)
        sheet[r * tile_h:r * tile_h + t.shape[0], c * tile_w:(c + 1) * tile_w] = t
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), sheet):
        raise DatasetError(f"{out}: cannot write the contact sheet")
    print(f"wrote {out}: {len(tiles)} frames with their labels"
          + (f" ({len(skipped)} unreadable, named above)" if skipped else ""))
    return 0


# ------------------------------------------------------------------------------ from a bag


def _topic_camera(topic: str) -> str:
    """A camera id for an image topic nobody named: its tokens joined (``/cam1/image_raw`` ->
    ``cam1_image_raw``)."""
    return "_".join(t for t in topic.replace("-", "_").split("/") if t) or "camera"


def _capture(args: argparse.Namespace) -> int:
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from edge_agent.capture import FrameCapture
    from edge_agent.ros_source import (
        COMPRESSED_IMAGE_TYPE,
        IMAGE_TYPE,
        compressed_to_rgb,
        decode_compressed_image,
        decode_image,
        image_to_rgb,
    )

    named = {}
    for pair in args.camera:
        topic, sep, cam = pair.partition("=")
        if not sep or not topic or not cam:
            raise DatasetError(f"--camera {pair!r}: give TOPIC=CAMERA_ID")
        named[topic] = cam
    path = Path(args.recording)
    if not path.is_file():
        raise DatasetError(f"{path}: no such recording")
    captures: dict[str, FrameCapture] = {}
    bad: dict[str, int] = {}
    read = 0
    try:
        with path.open("rb") as f:
            for schema, channel, message in make_reader(f).iter_messages(log_time_order=True):
                if schema is None or schema.name not in (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE) or (
                        channel.message_encoding != "cdr"):
                    continue
                topic = channel.topic
                if named and topic not in named:
                    continue
                read += 1
                cam = named.get(topic) or _topic_camera(topic)
                if cam not in captures:
                    captures[cam] = FrameCapture(args.out, cam, rate_hz=args.rate,
                                                 budget_mb=args.budget_mb, fmt=args.format)
                capture = captures[cam]
                try:
                    if schema.name == IMAGE_TYPE:
                        img = decode_image(message.data, f"{topic} message {message.sequence}")
                        capture.offer(image_to_rgb(img), img.stamp_ns, wait=True)
                    else:
                        comp = decode_compressed_image(message.data,
                                                       f"{topic} message {message.sequence}")
                        rgb = compressed_to_rgb(comp)  # checks that it decodes
                        fmt = comp.format.lower()
                        ext = "png" if "png" in fmt else "jpg"
                        if args.keep_encoded:
                            capture.offer_encoded(bytes(comp.data), ext, comp.stamp_ns,
                                                  wait=True)
                        else:
                            capture.offer(rgb, comp.stamp_ns, wait=True)
                except SmartedgeError as exc:  # RosImageError: truncated, bad encoding, ...
                    bad[topic] = bad.get(topic, 0) + 1
                    print(f"skipped {topic} message {message.sequence}: {exc}", file=sys.stderr)
                    continue
    except (McapError, ValueError, EOFError, OSError, KeyError) as exc:
        raise DatasetError(f"{path}: not a complete MCAP recording ({type(exc).__name__}: "
                           f"{exc}); {read} image messages read before the damage") from None
    finally:
        for capture in captures.values():
            capture.close()
    if not captures:
        raise DatasetError(f"{path}: no sensor_msgs/Image or CompressedImage topic"
                           + (f" among {sorted(named)}" if named else ""))
    for _cam, capture in sorted(captures.items()):
        print(f"{capture.folder}: {capture.captured} frames"
              + (f"; {capture.status()}" if capture.stopped else ""))
    if bad:
        print(f"{sum(bad.values())} messages skipped (named above): {bad}", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="smartedge dataset",
                                     description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="verb", required=True)
    p = sub.add_parser("capture", help="frames of a ROS 2 MCAP's image topics, as the edge "
                                       "agent's --capture writes them")
    p.add_argument("--recording", required=True, help="MCAP file (a ROS 2 bag's storage)")
    p.add_argument("--out", required=True, help="DIR: frames go to DIR/<camera_id>/")
    p.add_argument("--camera", action="append", default=[], metavar="TOPIC=ID",
                   help="an image topic and its camera id in the site file (default: every "
                   "image topic, named after the topic)")
    p.add_argument("--rate", type=float, default=1000.0, metavar="HZ",
                   help="frames per second of capture time per camera at most (all)")
    p.add_argument("--budget-mb", type=float, default=10000.0, help="disk per camera (10000)")
    p.add_argument("--format", choices=("png", "jpg"), default="png",
                   help="raw images saved as (png: lossless)")
    p.add_argument("--reencode", dest="keep_encoded", action="store_false",
                   help="decode CompressedImage messages and save them in --format (default: "
                   "their JPEG or PNG bytes as they are)")
    p.set_defaults(run=_capture)
    p = sub.add_parser("info", help="counts of a dataset")
    p.add_argument("dataset")
    p.set_defaults(run=_info)
    p = sub.add_parser("show", help="a contact sheet with the labels drawn")
    p.add_argument("dataset")
    p.add_argument("--out", required=True, help="PNG to write")
    p.add_argument("--images", help="folder the file names are relative to (default: the "
                                    "dataset file's folder)")
    p.add_argument("--count", type=int, default=12, help="frames on the sheet (12)")
    p.set_defaults(run=_show)
    p = sub.add_parser("split", help="train / validation by capture time")
    p.add_argument("dataset")
    p.add_argument("--val-share", type=float, default=0.2, help="share of time blocks (0.2)")
    p.add_argument("--block-s", type=float, default=10.0, help="seconds per block (10)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--train", required=True, help="the training part's file")
    p.add_argument("--val", required=True, help="the validation part's file")
    p.set_defaults(run=_split)
    p = sub.add_parser("merge", help="one dataset of several")
    p.add_argument("datasets", nargs="+")
    p.add_argument("--out", required=True)
    p.set_defaults(run=_merge)
    p = sub.add_parser("import", help="a labelling tool's COCO export, checked against a "
                                      "robot model")
    p.add_argument("external")
    p.add_argument("--site", required=True)
    p.add_argument("--robot-model", required=True, help="the site's robot model it labels")
    p.add_argument("--category", help="the file's category to take (default: its only one)")
    p.add_argument("--rename", action="append", default=[], metavar="OLD=NEW",
                   help="a keypoint name of the file and the model's name for it")
    p.add_argument("--allow-missing", action="store_true",
                   help="model keypoints the file lacks are labelled 0 (not labelled)")
    p.add_argument("--drop-extra", action="store_true",
                   help="the file's keypoints the model lacks are dropped")
    p.add_argument("--label-source", default="manual", help="what the labels are (manual)")
    p.add_argument("--out", required=True)
    p.set_defaults(run=_import)
    return parser


def main(argv: Sequence[str]) -> int:
    args = build_parser().parse_args(list(argv))
    if getattr(args, "count", 1) < 1:
        print("smartedge dataset show: --count must be >= 1", file=sys.stderr)
        return 2
    try:
        return int(args.run(args))
    except SmartedgeError as exc:  # DatasetError, a site file that does not load
        print(f"smartedge dataset {args.verb}: {exc}", file=sys.stderr)
        return 1
