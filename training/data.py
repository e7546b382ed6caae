"""Training data: labelled renders from a :class:`ViewSource` (the simulation's renderer,
provided by the top floor: :class:`lab.training_views.SimulationViews`; this package
never imports the simulation), turned into the networks' inputs with the deployed
pre-processing (:mod:`edge_agent.crop`).

Rendering is the expensive part on a CPU, so :func:`render_set` renders a set of views once,
in parallel worker processes, into compact shards (detector-sized frames, keypoint crops with
their labels, and for the segmentation network the per-pixel class images at its output size)
under a cache folder; training then runs epochs over them with on-the-fly
augmentation. Shards are written as they complete, so an interrupted run resumes where it
stopped. The same seed always gives the same set.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import multiprocessing
import time
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from edge_agent.crop import crop_transform, downscale_labels, extract_crop, resize_for_detector
from protocol.errors import UsageError

log = logging.getLogger(__name__)

SHARD = 200  # views per shard file


@dataclasses.dataclass(frozen=True)
class SetSpec:
    """One rendered set: ``count`` views of ``mode`` (``site``/``randomized``/``robot``: the
    robot's own head camera) from ``seed``."""

    mode: str
    seed: int
    count: int

    @property
    def name(self) -> str:
        return f"{self.mode}-s{self.seed}"


@dataclasses.dataclass(frozen=True)
class Geometry:
    """Network input sizes and crop sampling: detector input (also the segmentation network's),
    keypoint crop, and how many jittered crops of each visible robot to keep (``crop_jitter``:
    False = the deployed crop only, as for evaluation; ``crops_per_robot`` 0: no crops, for a
    segmentation set); ``seg_w`` x ``seg_h``: the size of the per-pixel class labels (the
    segmentation network's output; 0: none stored)."""

    det_w: int = 424
    det_h: int = 240
    crop_w: int = 192
    crop_h: int = 256
    crops_per_robot: int = 2
    crop_jitter: bool = True
    frame_w: int | None = None  # render size (None: 848x480 / the site cameras' own)
    frame_h: int | None = None
    seg_w: int = 0
    seg_h: int = 0


@dataclasses.dataclass
class RenderedSet:
    """Arrays of a rendered set. Detector part, one row per view: ``det_images`` (N, h, w, 3)
    uint8, ``boxes`` (N, 4) robot box in *frame* pixels (NaN: none visible), ``frame_size``
    (N, 2) frame width, height. Keypoint part, one row per crop: ``crops`` (M, ch, cw, 3),
    ``crop_kp`` (M, K, 2) crop pixels, ``crop_in_image`` / ``crop_visible`` (M, K),
    ``crop_scale`` (M,) crop pixels per frame pixel, ``crop_view`` (M,) row of the view.
    Segmentation part, one row per view: ``seg_labels`` (N, seg_h, seg_w) uint8 class ids of
    :data:`protocol.semantic_classes.SEMANTIC_CLASSES` (``downscale_labels`` of the render's
    class image; (N, 0, 0) when the geometry asks for none)."""

    det_images: np.ndarray
    boxes: np.ndarray
    frame_size: np.ndarray
    crops: np.ndarray
    crop_kp: np.ndarray
    crop_in_image: np.ndarray
    crop_visible: np.ndarray
    crop_scale: np.ndarray
    crop_view: np.ndarray
    seg_labels: np.ndarray

    @staticmethod
    def concatenate(parts: Sequence[RenderedSet]) -> RenderedSet:
        out: dict[str, np.ndarray] = {}
        offset = 0
        views = []
        for p in parts:
            views.append(p.crop_view + offset)
            offset += len(p.det_images)
        for f in dataclasses.fields(RenderedSet):
            if f.name == "crop_view":
                out[f.name] = np.concatenate(views) if views else np.zeros(0, np.int64)
            else:
                out[f.name] = np.concatenate([getattr(p, f.name) for p in parts])
        return RenderedSet(**out)

    def save(self, path: Path) -> None:
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **dataclasses.asdict(self))
        tmp.replace(path)

    @staticmethod
    def load_many(paths: Sequence[Path]) -> RenderedSet:
        """The shards ``paths`` concatenated, read one array at a time into arrays allocated
        once from the shards' headers: memory is the set's size plus one shard's array, not
        twice the set (what loading every shard and concatenating them needs: a 10,500-view
        640x360 set is 9 GB)."""
        if not paths:
            raise ValueError("no shards to load")
        shapes = [_npz_shapes(p) for p in paths]
        names = [f.name for f in dataclasses.fields(RenderedSet)]
        out: dict[str, np.ndarray] = {}
        for name in names:
            if name == "seg_labels" and any(name not in s for s in shapes):
                continue  # shards written before segmentation labels existed hold none
            try:
                (shape0, dtype) = shapes[0][name]
                rest = {(sh[1:], dt) for sh, dt in (s[name] for s in shapes)}
            except KeyError:
                raise ValueError(f"{paths[0]}: render shard lacks {name!r}") from None
            if len(rest) != 1:
                raise ValueError(f"render shards disagree on {name!r}: {sorted(map(str, rest))}")
            n = sum(s[name][0][0] for s in shapes)
            out[name] = np.empty((n, *shape0[1:]), dtype)
        starts = dict.fromkeys(out, 0)
        view_offset = 0
        for path in paths:
            with np.load(path) as z:
                n_views = 0
                for name in out:
                    a = z[name]
                    if name == "crop_view":
                        a = a + view_offset
                    if name == "det_images":
                        n_views = len(a)
                    out[name][starts[name]:starts[name] + len(a)] = a
                    starts[name] += len(a)
                    del a
            view_offset += n_views
        out.setdefault("seg_labels", np.zeros((len(out["det_images"]), 0, 0), np.uint8))
        return RenderedSet(**out)

    @staticmethod
    def load(path: Path) -> RenderedSet:
        with np.load(path) as z:
            arrays = {f.name: z[f.name] for f in dataclasses.fields(RenderedSet)
                      if f.name in z.files}
        # shards written before segmentation labels existed hold none
        arrays.setdefault("seg_labels", np.zeros((len(arrays["det_images"]), 0, 0), np.uint8))
        return RenderedSet(**arrays)


class ViewSource(Protocol):
    """Where labelled views come from. Sent to the render processes, so it must pickle.

    ``robot_model``: the :class:`core.site.RobotModel` whose keypoints are labelled;
    ``renderer(spec, geometry)``: a function index → sample (``image_rgb`` (H, W, 3) uint8,
    ``mode``, ``robots`` (none, e.g. the robot's own head camera, or ``robots[0]`` with
    ``bbox_xyxy`` (box edges or None), ``keypoints_px``, ``visible``, ``in_image``), ``class_id``
    for segmentation sets), the same sample for the same (spec, index);
    ``augment(image, rng)``: photometric augmentation of a clean image; ``identity()``: what
    the render cache is of (robot, scenario), as a JSON-able dict."""

    robot_model: Any

    def renderer(self, spec: SetSpec, geometry: Geometry) -> Callable[[int], Any]: ...

    def augment(self, image_rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray: ...

    def identity(self) -> dict[str, Any]: ...


#: modes whose renders are clean (no image-space augmentation yet)
#: views augmented like the site's (the renders without randomization, a lab's real frames)
CLEAN_MODES = ("site", "robot", "real")


def view_records(sample: Any, geometry: Geometry, rng: np.random.Generator,
                 augment: Callable[[np.ndarray, np.random.Generator], np.ndarray] | None = None,
                 num_keypoints: int = 0) -> RenderedSet:
    """One rendered sample → its rows; ``augment`` (if given) is applied to un-augmented
    (site and robot-head) views. A sample without robots (the robot's own head camera) gives a
    view without a box (NaN: a negative for the detector) and no keypoint crops of
    ``num_keypoints`` keypoints (the robot model's count, so sets concatenate)."""
    g = geometry
    image = sample.image_rgb
    if augment is not None and sample.mode in CLEAN_MODES:
        image = augment(image, rng)
    h, w = image.shape[:2]
    det = resize_for_detector(image, g.det_w, g.det_h)
    robot = sample.robots[0] if sample.robots else None
    box = (np.full(4, np.nan) if robot is None or robot.bbox_xyxy is None
           else np.asarray(robot.bbox_xyxy, np.float64))
    crops, kps, scales = [], [], []
    big_enough = (robot is not None and robot.bbox_xyxy is not None
                  and (box[2] - box[0]) * (box[3] - box[1]) >= 64)
    if big_enough and g.crops_per_robot > 0:
        n = g.crops_per_robot if g.crop_jitter else 1
        for _ in range(n):
            jitter: dict[str, Any] = {}
            if g.crop_jitter:
                jitter = {"shift": tuple(rng.uniform(-0.08, 0.08, 2)),
                          "zoom": float(rng.uniform(0.85, 1.3))}
            tf = crop_transform(box, g.crop_w, g.crop_h, **jitter)
            crops.append(extract_crop(image, tf, g.crop_w, g.crop_h))
            kps.append(tf.to_crop(robot.keypoints_px))  # type: ignore[union-attr]
            scales.append(tf.scale)
    k = num_keypoints if robot is None else len(robot.visible)
    in_image = np.zeros(k, bool) if robot is None else np.asarray(robot.in_image, bool)
    visible = np.zeros(k, bool) if robot is None else np.asarray(robot.visible, bool)
    m = len(crops)
    seg = (downscale_labels(sample.class_id, g.seg_w, g.seg_h)[None] if g.seg_w > 0
           else np.zeros((1, 0, 0), np.uint8))
    return RenderedSet(
        det_images=det[None],
        boxes=box[None],
        frame_size=np.array([[w, h]], np.int32),
        crops=np.asarray(crops, np.uint8).reshape(m, g.crop_h, g.crop_w, 3),
        crop_kp=np.asarray(kps, np.float32).reshape(m, k, 2),
        crop_in_image=np.repeat(in_image[None], m, 0),
        crop_visible=np.repeat(visible[None], m, 0),
        crop_scale=np.asarray(scales, np.float32),
        crop_view=np.zeros(m, np.int64),
        seg_labels=seg,
    )


@dataclasses.dataclass(frozen=True)
class RealData:
    """What a set of a lab's labelled frames was (for the model card): the dataset file, its
    content hash, frames used, per camera, where the labels came from, frames left out."""

    path: str
    sha256: str
    frames: int
    cameras: dict[str, int]
    label_sources: dict[str, int]
    left_out: dict[str, int]


def real_set(dataset_path: Path, geometry: Geometry, keypoint_names: Sequence[str],
             rng: np.random.Generator,
             augment: Callable[[np.ndarray, np.random.Generator], np.ndarray] | None = None,
             image_root: Path | None = None) -> tuple[RenderedSet, RealData]:
    """A lab's labelled frames (a COCO keypoints file, :mod:`core.coco`) as training rows, the
    same pre-processing as the renders (:func:`view_records`, ``augment`` as for the clean
    rendered views). Its category must name the robot model's keypoints in the model's order
    (``smartedge dataset import`` makes it so); a frame with several robots or an unreadable
    image is left out (counted, logged with its name)."""
    import collections
    import hashlib

    import cv2

    from core.coco import labelled_frames, read_dataset

    dataset = read_dataset(dataset_path)
    root = image_root or Path(dataset_path).parent
    names = tuple(keypoint_names)
    cats = [c for c in dataset.categories if c.keypoints == names]
    if len(cats) != 1:
        raise UsageError(f"{dataset_path}: no category with the robot model's keypoints "
                         f"{list(names)} in that order (categories: "
                         f"{[(c.name, list(c.keypoints)) for c in dataset.categories]}); "
                         f"smartedge dataset import matches a file to the model")

    def read_rgb(path: Path) -> np.ndarray | None:
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    frames, skipped = labelled_frames(dataset, cats[0], root, read_rgb)
    left_out = {why: len(names_) for why, names_ in skipped.items() if names_}
    for why, names_ in skipped.items():
        for name in names_:
            log.warning("%s: %s left out (%s)", dataset_path, name, why)
    if not frames:
        raise UsageError(f"{dataset_path}: no frame could be used ({left_out})")
    parts = [view_records(f, geometry, rng, augment, num_keypoints=len(names)) for f in frames]
    cameras = collections.Counter(f.image.camera_id or "?" for f in frames)
    sources = collections.Counter(f.annotation.label_source for f in frames
                                  if f.annotation is not None)
    digest = hashlib.sha256(Path(dataset_path).read_bytes()).hexdigest()
    info = RealData(str(dataset_path), digest, len(parts), dict(cameras), dict(sources),
                    left_out)
    return RenderedSet.concatenate(parts), info


_WORKER: dict[str, Any] = {}


def _worker_init(views: ViewSource) -> None:
    _WORKER.update(views=views, renderers={})


def _render_shard(spec: SetSpec, start: int, stop: int, geometry: Geometry,
                  augment_clean: bool) -> RenderedSet:
    views: ViewSource = _WORKER["views"]
    renderers = _WORKER["renderers"]
    if spec.name not in renderers:
        renderers[spec.name] = views.renderer(spec, geometry)
    render = renderers[spec.name]
    parts = []
    for i in range(start, stop):
        rng = np.random.default_rng(np.random.SeedSequence([spec.seed, i, 4242]))
        parts.append(view_records(render(i), geometry, rng,
                                  views.augment if augment_clean else None,
                                  num_keypoints=views.robot_model.num_keypoints))
    return RenderedSet.concatenate(parts)


def render_set(views: ViewSource, specs: Sequence[SetSpec], geometry: Geometry,
               cache_dir: Path, *, workers: int = 2, augment_clean: bool = True,
               progress: Callable[[str], None] | None = None) -> RenderedSet:
    """Render (or reuse from ``cache_dir``) every view of ``specs``; returns them concatenated.

    Shard files are named by set, range and geometry, so a cache folder can hold several sets
    and an interrupted render resumes. ``workers`` processes render in parallel, each with its
    own GL context."""
    say = progress or (lambda line: log.info("%s", line))
    cache_dir.mkdir(parents=True, exist_ok=True)
    _check_manifest(cache_dir, views.identity())
    tag = (f"d{geometry.det_w}x{geometry.det_h}-c{geometry.crop_w}x{geometry.crop_h}"
           f"-n{geometry.crops_per_robot}{'j' if geometry.crop_jitter else 'e'}"
           f"-f{geometry.frame_w}x{geometry.frame_h}{'-a' if augment_clean else ''}"
           # only segmentation sets carry labels: earlier shard names stay valid
           + (f"-s{geometry.seg_w}x{geometry.seg_h}" if geometry.seg_w > 0 else ""))
    jobs: list[tuple[SetSpec, int, int, Path]] = []
    for spec in specs:
        for start in range(0, spec.count, SHARD):
            stop = min(spec.count, start + SHARD)
            jobs.append((spec, start, stop, cache_dir / f"{spec.name}-{start}-{stop}-{tag}.npz"))
    todo = [j for j in jobs if not j[3].exists()]
    total = sum(j[2] - j[1] for j in todo)
    if todo:
        say(f"rendering {total} views ({len(jobs) - len(todo)} of {len(jobs)} shards cached) "
            f"with {workers} worker(s)")
        t0 = time.perf_counter()
        done = 0

        def finished(part: RenderedSet, path: Path) -> None:
            nonlocal done
            part.save(path)
            done += len(part.det_images)
            rate = done / max(time.perf_counter() - t0, 1e-9)
            say(f"  rendered {done}/{total} views ({rate:.1f} views/s)")

        if workers <= 1:  # in this process (tests, debugging)
            _worker_init(views)
            for spec, a, b, path in todo:
                finished(_render_shard(spec, a, b, geometry, augment_clean), path)
            return RenderedSet.load_many([j[3] for j in jobs])
        ctx = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(
                max(1, workers), mp_context=ctx, initializer=_worker_init,
                initargs=(views,)) as pool:
            futures = {pool.submit(_render_shard, spec, a, b, geometry, augment_clean): path
                       for spec, a, b, path in todo}
            for fut in concurrent.futures.as_completed(futures):
                finished(fut.result(), futures[fut])
    return RenderedSet.load_many([j[3] for j in jobs])


def _npz_shapes(path: Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shape and dtype of every array of an ``.npz`` file, read from the headers only."""
    shapes: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            for member in zf.namelist():
                with zf.open(member) as f:
                    version = np.lib.format.read_magic(f)
                    read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                            else np.lib.format.read_array_header_2_0)
                    shape, _fortran, dtype = read(f)
                shapes[member.removesuffix(".npy")] = (tuple(shape), np.dtype(dtype))
    except (OSError, zipfile.BadZipFile, ValueError) as exc:
        raise ValueError(f"{path}: not a readable render shard ({exc})") from None
    return shapes


def _check_manifest(cache_dir: Path, identity: dict[str, Any]) -> None:
    """A cache folder holds renders of one robot in one scenario: ``cache.json`` records which
    (the view source's identity), and a run for another robot is refused instead of training on
    the wrong renders."""
    import json

    doc = json.loads(json.dumps(identity))  # as it reads back
    path = cache_dir / "cache.json"
    if path.exists():
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            old = None
        if old != doc:
            raise UsageError(f"{path}: this render cache is of another robot or scenario "
                             f"({old}); use another --out or delete {cache_dir}")
        return
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
