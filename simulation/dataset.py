"""Rendered, exactly labelled samples: a deterministic generator and a dataset writer.

:class:`SampleGenerator` turns an index into a :class:`Sample` (image, depth, class and instance
images, per-robot labels). The same (seed, index) always gives the same sample, whichever
process renders it, so datasets are reproducible and several processes can share the work.

Modes:
- ``site``: a view of the simulated site from one of its own cameras (intrinsics, distortion,
  pose as the site file says), the robot at a random free pose in the room, sometimes people
  standing around;
- ``randomized``: :func:`simulation.scenes.randomized_view` (camera, lens, textures,
  clutter, occluders, lights and materials, the robot's colours) plus image-space effects: the
  robot's shadow and dirt (:func:`scene_effects`) and the camera's (:func:`camera_effects`:
  vignetting, defocus and motion blur, exposure, white balance, gamma, saturation, sensor
  noise, JPEG), all drawn from the generator's :class:`simulation.scenes.RandomizationConfig`
  (:data:`simulation.scenes.HELD_OUT_VARIATION`: the held-out renderer variations);
- ``robot``: what the robot's own head camera (the robot model's ``head_camera`` in the site
  file) sees from a random free pose in the room with a random heading: the site without the
  robot itself (as :meth:`simulation.site_cameras.SiteCameraRenderer.render_head` draws it),
  sometimes people standing around and sometimes another instance of the robot in front of it.
  ``robots`` is empty unless that other robot is there; these views exist for the semantic
  segmentation network, whose furniture looks different from a 1 m high camera than from the
  ceiling (for the detector they are views without a robot, or with the other one).

:func:`write_dataset` writes ``images/``, ``depth/`` (uint16 millimetres, 0 = nothing),
``class/`` (uint8 class ids, legend in ``dataset.json``), ``instance/`` (uint16),
``labels.jsonl`` (one JSON object per image) and ``dataset.json``.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import functools
import itertools
import json
import logging
import multiprocessing
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from core.camera import CameraModel
from protocol.errors import SmartedgeError
from simulation.image_effects import camera_effects, scene_effects
from simulation.mesh import CLASS_ID, CLASSES, Mesh, SceneObject
from simulation.render_stages import StageClock
from simulation.scenes import (
    FIRST_OTHER_INSTANCE,
    ROBOT_INSTANCE,
    RandomizationConfig,
    hsr_arm_poses,
    person_mesh,
    random_environments,
    randomized_view,
    robot_appearances,
    robot_keypoints_world,
    site_geometry,
    site_scene,
)
from simulation.world import World

log = logging.getLogger(__name__)

MODES: Final = ("site", "randomized", "robot")
#: chance that a robot-mode view has another instance of the robot in front of the camera
OTHER_ROBOT_CHANCE: Final = 0.25
#: chance that each person of a robot-mode view stands in front of the camera (else anywhere)
PERSON_IN_VIEW_CHANCE: Final = 0.6


class DatasetError(SmartedgeError):
    """A dataset cannot be generated or written (bad mode, size, output folder...)."""


@dataclasses.dataclass(frozen=True, eq=False)
class RobotLabel:
    """One robot in one image. ``bbox_xyxy`` (4,) of its visible pixels (``None``: not
    visible); ``keypoints_px`` (K, 2) raw distorted pixels (``cv2.projectPoints``);
    ``visible`` (K,) inside the image and not occluded; ``in_image`` (K,); ``depth_m`` (K,)
    camera z of each keypoint."""

    robot_id: str
    instance_id: int
    bbox_xyxy: np.ndarray | None
    keypoints_px: np.ndarray
    visible: np.ndarray
    in_image: np.ndarray
    depth_m: np.ndarray

    def to_json(self) -> dict[str, Any]:
        return {
            "robot_id": self.robot_id,
            "instance_id": self.instance_id,
            "bbox_xyxy": None if self.bbox_xyxy is None else [float(v) for v in self.bbox_xyxy],
            "keypoints_px": np.round(self.keypoints_px, 3).tolist(),
            "visible": [bool(v) for v in self.visible],
            "in_image": [bool(v) for v in self.in_image],
            "depth_m": np.round(self.depth_m, 4).tolist(),
        }


@dataclasses.dataclass(frozen=True, eq=False)
class Sample:
    """A rendered image and its labels. ``image_rgb`` (H, W, 3) uint8 (augmented in
    randomized mode), ``depth_m`` (H, W) float32 (inf: nothing), ``class_id`` / ``instance_id``
    (H, W) int32; ``robot_pose`` (3,) x, y, theta in the scene's world frame (robot mode: the
    pose of the robot whose head camera took the view, not drawn); ``robots``: the robots in the
    scene (robot mode: none, or the other instance in front of the camera)."""

    index: int
    seed: int
    mode: str
    camera: CameraModel
    image_rgb: np.ndarray
    depth_m: np.ndarray
    class_id: np.ndarray
    instance_id: np.ndarray
    robots: tuple[RobotLabel, ...]
    robot_pose: np.ndarray

    def labels_json(self) -> dict[str, Any]:
        cam = self.camera
        return {
            "index": self.index, "seed": self.seed, "mode": self.mode,
            "camera": {"camera_id": cam.camera_id, "width": cam.width, "height": cam.height,
                       "K": cam.K.tolist(), "dist": cam.dist.tolist(),
                       "T_cam_world": np.round(cam.T_cam_world, 9).tolist()},
            "robot_pose": [float(v) for v in self.robot_pose],
            "robots": [r.to_json() for r in self.robots],
        }


def scaled_camera(camera: CameraModel, width: int, height: int) -> CameraModel:
    """``camera`` at another resolution (intrinsics scaled; same lens and pose)."""
    if (width, height) == (camera.width, camera.height):
        return camera
    sx, sy = width / camera.width, height / camera.height
    K = camera.K.copy()
    K[0, 0] *= sx
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 1] *= sy
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return dataclasses.replace(camera, width=width, height=height, K=K)


@dataclasses.dataclass(frozen=True, eq=False)
class View:
    """A sample before rendering: its ``index``, the random generator ``rng`` after building
    the scene (the augmentation draws from it next), the ``scene``, the ``camera``,
    ``robot_pose`` (3,) as in :class:`Sample` and ``robot_pose_labelled`` (3,): the robot whose
    keypoints are labelled (``None``: none, robot mode without another robot)."""

    index: int
    rng: np.random.Generator
    scene: Any
    camera: CameraModel
    robot_pose: np.ndarray
    robot_pose_labelled: np.ndarray | None


class SampleGenerator:
    """Index → :class:`Sample`, deterministic per (``seed``, index).

    ``scenario``: a :class:`simulation.scenario.Scenario` (site, room, obstacles);
    ``mode``: ``site``, ``randomized`` or ``robot`` (see the module docstring); ``width``/
    ``height``: image size (default: each site camera's own in site mode, the head camera's in
    robot mode, 848x480 randomized); ``robot_mesh``: the robot's mesh
    (default: the built-in HSR-like mesh of the scenario's robot model); ``robot_model``: its
    keypoints (default: the site's model of the scenario's robot); ``randomization``: the
    ranges of randomized views; ``arm_poses``: ``robot_mesh`` is the built-in HSR-like mesh,
    whose arm randomized views may show in other poses (``randomization.robot_arm_poses``,
    :func:`simulation.scenes.hsr_arm_poses`; default: when ``robot_mesh`` is not given). The
    GL renderer is created on first use, in the process that renders.
    """

    def __init__(self, scenario: Any, mode: str = "site", *, seed: int = 0,
                 width: int | None = None, height: int | None = None,
                 robot_mesh: Mesh | None = None,
                 robot_model: Any = None,
                 randomization: RandomizationConfig | None = None,
                 arm_poses: bool | None = None) -> None:
        if mode not in MODES:
            raise DatasetError(f"mode {mode!r}: expected one of {MODES}")
        if (width is None) != (height is None) or (width is not None and min(width, height) < 8):  # type: ignore[operator]
            raise DatasetError(f"image size {width}x{height}: give both, at least 8 px")
        self.scenario = scenario
        self.mode = mode
        self.seed = int(seed)
        self.width, self.height = width, height
        self.robot_id = scenario.robot_id
        self.model = robot_model or scenario.site.robot_model(self.robot_id)
        builtin_hsr = False
        if robot_mesh is None:
            from simulation.robot_mesh import BUILTIN_MESHES, builtin_robot_mesh

            robot_mesh = builtin_robot_mesh(self.model)
            builtin_hsr = self.model.name not in BUILTIN_MESHES
        #: randomized views also move the arm of the built-in HSR-like mesh
        self.arm_poses = builtin_hsr if arm_poses is None else bool(arm_poses)
        self.robot_mesh = robot_mesh
        self.randomization = randomization or RandomizationConfig()
        self.camera_ids = tuple(sorted(scenario.site.cameras))
        if mode == "robot" and self.model.head_camera is None:
            raise DatasetError(f"robot model {self.model.name!r} has no head_camera in the site "
                               "file: robot-mode views need one")
        in_site = mode in ("site", "robot")
        self._geometry = site_geometry(scenario, seed=self.seed) if in_site else None
        self._world = World(scenario) if in_site else None
        self._renderers: dict[tuple[int, int], Any] = {}
        self._environments: tuple[Any, ...] | None = None
        self._appearances: tuple[Mesh, ...] | None = None
        self._times: Any = None
        self._preloaded: set[tuple[int, int]] = set()

    def _renderer(self, width: int, height: int) -> Any:
        key = (width, height)
        if key not in self._renderers:
            from simulation.render_gl import Renderer

            renderer = self._renderers[key] = Renderer(width, height)
            renderer.times = self._times
        return self._renderers[key]

    def rng(self, index: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([self.seed, int(index), 7919]))

    @property
    def times(self) -> Any:
        """A :class:`simulation.render_stages.StageTimes` that every sample adds its stages to
        (scene, lens map, upload, draw, read-back, remap, labels, augmentation), or ``None``
        (the default: no timing, no GL synchronization for it)."""
        return self._times

    @times.setter
    def times(self, value: Any) -> None:
        self._times = value
        for renderer in self._renderers.values():
            renderer.times = value

    def __call__(self, index: int) -> Sample:
        return self.samples([index])[0]

    def view(self, index: int) -> View:
        """The scene and camera of sample ``index``, built but not rendered (what
        :meth:`samples` draws; benchmarks replay them)."""
        rng = self.rng(index)
        labelled: np.ndarray | None
        if self.mode == "robot":
            scene, camera, pose, labelled = self._robot_view(rng)
        elif self.mode == "site":
            scene, camera, pose = self._site_view(rng)
            labelled = pose
        else:
            w, h = self.width or 848, self.height or 480
            scene, camera, pose = randomized_view(rng, self.robot_mesh, self.model, w, h,
                                                  self.randomization, self.environments(),
                                                  self.appearances())
            labelled = pose
        return View(index, rng, scene, camera, pose, labelled)

    def environments(self) -> tuple[Any, ...]:
        """The floor/wall looks of randomized views (built on first use)."""
        if self._environments is None:
            self._environments = random_environments(self.seed, self.randomization)
        return self._environments

    def appearances(self) -> tuple[Mesh, ...]:
        """The robot's colour (and, for the built-in HSR-like mesh, arm pose) variants of
        randomized views (built on first use)."""
        if self._appearances is None:
            cfg = self.randomization
            shapes = hsr_arm_poses(self.model, self.seed, max(0, cfg.robot_appearances - 1),
                                   cfg) if self.arm_poses and cfg.robot_arm_poses else ()
            self._appearances = robot_appearances(self.robot_mesh, self.seed, cfg, shapes)
        return self._appearances

    def renderer(self, width: int, height: int) -> Any:
        """The :class:`simulation.render_gl.Renderer` for ``width`` x ``height`` images (made on
        first use, in this process; a randomized generator uploads its floor and wall textures
        to it at once: uploaded in the middle of a frame, building a texture's mipmaps stalls
        llvmpipe's pipeline, ~5 ms each)."""
        renderer = self._renderer(width, height)
        if self.mode == "randomized" and (width, height) not in self._preloaded:
            renderer.upload([*(m for env in self.environments()
                               for m in (env.floor.mesh, env.walls.mesh)),
                             *self.appearances()])
            self._preloaded.add((width, height))
        return renderer

    def samples(self, indices: Sequence[int]) -> list[Sample]:
        """Samples ``indices`` in one batch: their scenes are built first, then drawn with one
        :meth:`simulation.render_gl.Renderer.render_many` per image size (shared context switch
        and mesh uploads), then labelled and augmented. Each sample is exactly ``self(index)``.
        """
        clock = StageClock(self._times)
        views = [self.view(index) for index in indices]
        clock.lap("scene")
        outs: dict[int, Any] = {}
        by_size: dict[tuple[int, int], list[int]] = {}
        for k, v in enumerate(views):
            by_size.setdefault((v.camera.width, v.camera.height), []).append(k)
        for (w, h), ks in by_size.items():
            rendered = self.renderer(w, h).render_many([(views[k].scene, views[k].camera)
                                                        for k in ks])
            outs.update(zip(ks, rendered, strict=True))
        clock.restart()
        result = []
        for k, v in enumerate(views):
            out = outs[k]
            # robot mode: the other robot instance, if there is one, is the labelled robot
            robots = () if v.robot_pose_labelled is None else (
                self._label(out, v.camera, v.robot_pose_labelled),)
            clock.lap("labels")
            image = out.color_rgb
            if self.mode == "randomized":
                bbox = robots[0].bbox_xyxy if robots else None
                image = scene_effects(image, out.class_id, out.instance_id, v.camera, v.scene,
                                      v.robot_pose, self.model, bbox, v.rng, self.randomization)
                image = camera_effects(image, v.rng, self.randomization)
                clock.lap("augment")
            result.append(Sample(v.index, self.seed, self.mode, v.camera, image, out.depth_m,
                                 out.class_id, out.instance_id, robots, v.robot_pose))
        return result

    def stream(self, start: int = 0) -> Iterator[Sample]:
        """Samples ``start``, ``start + 1``, ... (for a training loop)."""
        index = start
        while True:
            yield self(index)
            index += 1

    def _free_pose(self, rng: np.random.Generator) -> np.ndarray:
        """(3,) x, y, theta: a random robot pose whose footprint is clear of the obstacles and
        walls (after 100 tries, the last one drawn)."""
        sc = self.scenario
        world = self._world
        assert world is not None
        lo = np.asarray(sc.room_min_xy_m) + self.model.footprint_radius_m
        hi = np.asarray(sc.room_max_xy_m) - self.model.footprint_radius_m
        pose = np.zeros(3)
        for _ in range(100):
            pose = np.array([*rng.uniform(lo, hi), rng.uniform(-np.pi, np.pi)])
            if not world.footprint_collides(pose[:2], self.model.footprint_radius_m):
                break
        return pose

    def _robot_view(self, rng: np.random.Generator
                    ) -> tuple[Any, CameraModel, np.ndarray, np.ndarray | None]:
        """The head camera of the robot at a free pose: (scene without that robot, camera in
        the world frame, its pose (3,), the pose (3,) of another robot instance in the scene or
        ``None``)."""
        from core.geometry import se3_from_planar
        from simulation.mesh import Scene

        sc = self.scenario
        head = self.model.head_camera
        pose = self._free_pose(rng)
        cam = head.camera_model("head", se3_from_planar(*(float(v) for v in pose)))
        if self.width is not None:
            cam = scaled_camera(cam, self.width, self.height)  # type: ignore[arg-type]
        world = self._world
        assert world is not None and self._geometry is not None
        lo, hi = np.asarray(sc.room_min_xy_m), np.asarray(sc.room_max_xy_m)

        def in_front(rng: np.random.Generator) -> np.ndarray:
            # a point 0.8-4 m ahead, within about the camera's horizontal field of view
            a = pose[2] + rng.uniform(-0.5, 0.5)
            return pose[:2] + rng.uniform(0.8, 4.0) * np.array([np.cos(a), np.sin(a)])

        objects: list[SceneObject] = list(self._geometry.objects)
        other: np.ndarray | None = None
        r = self.model.footprint_radius_m
        if rng.uniform() < OTHER_ROBOT_CHANCE:
            for _ in range(20):
                xy = in_front(rng)
                if (not world.footprint_collides(xy, r)
                        and np.hypot(*(xy - pose[:2])) > 2 * r + 0.2):
                    other = np.array([*xy, rng.uniform(-np.pi, np.pi)])
                    break
            if other is not None:
                objects.append(SceneObject(self.robot_mesh, se3_from_planar(*other),
                                           ROBOT_INSTANCE, CLASS_ID["robot"]))
        for k in range(int(rng.integers(0, 3))):  # people standing around
            p = in_front(rng) if rng.uniform() < PERSON_IN_VIEW_CHANCE else rng.uniform(lo, hi)
            if (np.hypot(*(p - pose[:2])) < r + 0.35
                    or (other is not None and np.hypot(*(p - other[:2])) < r + 0.35)
                    or world.footprint_collides(p, 0.2)):
                continue
            mesh = person_mesh(float(rng.uniform(1.5, 1.9)), rng.uniform(0.1, 0.9, 3))
            T = np.eye(4)
            T[:2, 3] = p
            objects.append(SceneObject(mesh, T, FIRST_OTHER_INSTANCE + k, CLASS_ID["person"]))
        return Scene(tuple(objects)), cam, pose, other

    def _site_view(self, rng: np.random.Generator) -> tuple[Any, CameraModel, np.ndarray]:
        sc = self.scenario
        cam = sc.site.cameras[self.camera_ids[int(rng.integers(len(self.camera_ids)))]]
        if self.width is not None:
            cam = scaled_camera(cam, self.width, self.height)  # type: ignore[arg-type]
        lo = np.asarray(sc.room_min_xy_m) + self.model.footprint_radius_m
        hi = np.asarray(sc.room_max_xy_m) - self.model.footprint_radius_m
        pose = self._free_pose(rng)  # a free pose: not inside an obstacle
        occluders: list[SceneObject] = []
        for k in range(int(rng.integers(0, 3))):  # people standing around
            p = rng.uniform(lo, hi)
            if np.hypot(*(p - pose[:2])) < self.model.footprint_radius_m + 0.35:
                continue
            mesh = person_mesh(float(rng.uniform(1.5, 1.9)), rng.uniform(0.1, 0.9, 3))
            T = np.eye(4)
            T[:2, 3] = p
            occluders.append(SceneObject(mesh, T, FIRST_OTHER_INSTANCE + k, CLASS_ID["person"]))
        assert self._geometry is not None
        return site_scene(self._geometry, self.robot_mesh, pose, occluders), cam, pose

    def _label(self, out: Any, camera: CameraModel, pose: np.ndarray) -> RobotLabel:
        from simulation.labels import instance_bbox, keypoint_labels

        kp = keypoint_labels(out, camera, robot_keypoints_world(self.model, pose))
        return RobotLabel(self.robot_id, ROBOT_INSTANCE, instance_bbox(out, ROBOT_INSTANCE),
                          kp.pixels_px, _near_instance(out.instance_id, kp.pixels_px,
                                                       kp.visible, ROBOT_INSTANCE),
                          kp.in_image, kp.depth_m)


#: a visible keypoint has a pixel of its robot within this many pixels (Chebyshev)
KEYPOINT_INSTANCE_RADIUS_PX: Final = 2


def _near_instance(instance_id: np.ndarray, pixels_px: np.ndarray, visible: np.ndarray,
                   instance: int, radius_px: int = KEYPOINT_INSTANCE_RADIUS_PX) -> np.ndarray:
    """``visible`` with the keypoints that have no pixel of ``instance`` within ``radius_px``
    of their pixel cleared: the depth test of :func:`simulation.labels.keypoint_labels` keeps a
    keypoint on an occluder's silhouette visible when the floor behind it is farther, even with
    the robot wholly hidden behind the occluder."""
    out = np.asarray(visible, bool).copy()
    idx = np.flatnonzero(out)
    if not len(idx):
        return out
    h, w = instance_id.shape
    iu = np.rint(pixels_px[idx, 0]).astype(np.intp)
    iv = np.rint(pixels_px[idx, 1]).astype(np.intp)
    offsets = np.arange(-radius_px, radius_px + 1)
    rows = np.clip(iv[:, None, None] + offsets[None, :, None], 0, h - 1)
    cols = np.clip(iu[:, None, None] + offsets[None, None, :], 0, w - 1)
    out[idx] = (instance_id[rows, cols] == instance).reshape(len(idx), -1).any(axis=1)
    return out


# --------------------------------------------------------------------------------------------
# writing a dataset
# --------------------------------------------------------------------------------------------


def _write_sample_to(out: str, sample: Sample) -> dict[str, Any]:
    return _write_sample(sample, Path(out))


def _write_sample(sample: Sample, out: Path) -> dict[str, Any]:
    import cv2

    name = f"{sample.index:06d}.png"
    cv2.imwrite(str(out / "images" / name), sample.image_rgb[..., ::-1])
    depth = sample.depth_m
    mm = np.where(np.isfinite(depth), np.clip(depth * 1000.0, 0, 65535), 0).astype(np.uint16)
    cv2.imwrite(str(out / "depth" / name), mm)
    cv2.imwrite(str(out / "class" / name), sample.class_id.astype(np.uint8))
    cv2.imwrite(str(out / "instance" / name),
                np.clip(sample.instance_id, 0, 65535).astype(np.uint16))
    doc = sample.labels_json()
    doc["image"] = f"images/{name}"
    return doc


def sample_summary(sample: Sample) -> tuple[int, tuple[dict[str, Any], ...]]:
    """(index, robot labels as JSON): what a benchmark keeps of a sample (a few hundred
    bytes instead of megabytes of images through the pipe)."""
    return sample.index, tuple(r.to_json() for r in sample.robots)


def _identity(sample: Sample) -> Sample:
    return sample


#: environment variable that sets llvmpipe's rasterizer threads (read when a context is made)
GL_THREADS_ENV: Final = "LP_NUM_THREADS"

_WORKER: dict[str, Any] = {}


def _pool_init(kwargs: dict[str, Any], gl_threads: int | None, cv_threads: int | None) -> None:
    import os

    if gl_threads is not None:
        os.environ[GL_THREADS_ENV] = str(gl_threads)
    if cv_threads is not None:
        import cv2

        cv2.setNumThreads(cv_threads)
    from simulation.scenario import load_scenario

    kw = dict(kwargs)
    scenario = load_scenario(kw.pop("scenario_path"))
    _WORKER["gen"] = SampleGenerator(scenario, **kw)


def _pool_run(fn: Callable[[Sample], Any], indices: list[int]) -> tuple[float, list[Any]]:
    """(CPU seconds this worker spent, all its threads, on the chunk; ``fn`` of each sample)."""
    cpu0 = time.process_time()
    results = [fn(sample) for sample in _WORKER["gen"].samples(indices)]
    return time.process_time() - cpu0, results


class SamplePool:
    """Worker processes rendering samples of one :class:`SampleGenerator`, each with its own GL
    context: the way to keep every core busy (one renderer is one thread of Python plus
    llvmpipe's rasterizer threads, and much of a sample's time is single-threaded numpy and
    OpenCV work).

    ``workers`` processes (``spawn``ed: EGL contexts do not survive a fork) each rebuild the
    generator from its scenario file and render ``chunk`` consecutive indices per task with
    :meth:`SampleGenerator.samples`. ``gl_threads``: llvmpipe rasterizer threads per worker
    (``LP_NUM_THREADS``; default 1: with one worker per core, more threads only contend;
    ``None`` leaves the environment alone); ``cv_threads``: OpenCV threads per worker (default
    1, for the same reason). Results come back in index order and are the same as the serial
    generator's for the same seed, whatever ``workers``, ``chunk`` or thread counts are.
    Use as a context manager (or call :meth:`close`).
    """

    def __init__(self, generator: SampleGenerator, workers: int = 2, *, chunk: int = 4,
                 gl_threads: int | None = 1, cv_threads: int | None = 1) -> None:
        if workers < 1 or chunk < 1:
            raise DatasetError(f"sample pool: need workers >= 1 and chunk >= 1, got {workers}, "
                               f"{chunk}")
        source = getattr(generator.scenario, "source_path", None)
        if not source:
            raise DatasetError("sample pool: the generator's scenario has no source file to "
                               "rebuild it from in the workers")
        self.workers, self.chunk = int(workers), int(chunk)
        #: CPU seconds the workers spent on the chunks returned so far (all their threads)
        self.cpu_seconds = 0.0
        kwargs = {"scenario_path": source, "mode": generator.mode,
                  "seed": generator.seed, "width": generator.width, "height": generator.height,
                  "robot_mesh": generator.robot_mesh, "robot_model": generator.model,
                  "randomization": generator.randomization,
                  "arm_poses": generator.arm_poses}
        self._pool = concurrent.futures.ProcessPoolExecutor(
            self.workers, mp_context=multiprocessing.get_context("spawn"),
            initializer=_pool_init, initargs=(kwargs, gl_threads, cv_threads))

    def map(self, fn: Callable[[Sample], Any], indices: Sequence[int]) -> Iterator[Any]:
        """``fn(sample)`` for every index, run in the workers (``fn`` must pickle: a
        module-level function or a :func:`functools.partial` of one), yielded in index
        order. At most two chunks per worker are in flight, so a slow consumer holds back
        the workers instead of filling memory."""
        chunks = [list(indices[i:i + self.chunk]) for i in range(0, len(indices), self.chunk)]
        pending: collections.deque[concurrent.futures.Future[tuple[float, list[Any]]]] = (
            collections.deque())
        ahead = 2 * self.workers
        it = iter(chunks)
        for chunk in itertools.islice(it, ahead):
            pending.append(self._pool.submit(_pool_run, fn, chunk))
        while pending:
            cpu_s, results = pending.popleft().result()
            self.cpu_seconds += cpu_s
            nxt = next(it, None)
            if nxt is not None:
                pending.append(self._pool.submit(_pool_run, fn, nxt))
            yield from results

    def samples(self, indices: Sequence[int]) -> Iterator[Sample]:
        """The samples themselves (each several MB through a pipe at 848x480: prefer
        :meth:`map` with a function that reduces a sample in the worker)."""
        return self.map(_identity, indices)

    def warm_up(self) -> None:
        """Start every worker and its GL context (blocks until they are ready)."""
        list(self.map(sample_summary, list(range(self.workers * self.chunk))))

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> SamplePool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_dataset(generator: SampleGenerator, out_dir: str | Path, count: int, *,
                  workers: int = 1, progress: Callable[[str], None] | None = None) -> Path:
    """Render samples ``0 .. count-1`` of ``generator`` into ``out_dir`` (see the module
    docstring); ``workers`` processes share the work (a :class:`SamplePool`, each with its own
    GL context); the result does not depend on ``workers``. Returns the labels file."""
    if count < 1:
        raise DatasetError(f"count {count}: at least 1")
    out = Path(out_dir)
    try:
        for sub in ("images", "depth", "class", "instance"):
            (out / sub).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DatasetError(f"{out}: cannot create the output folder: {exc}") from None
    say = progress or (lambda line: log.info("%s", line))
    t0 = time.perf_counter()
    docs: list[dict[str, Any]] = [{}] * count
    step = max(1, count // 20)

    def report(done: int) -> None:
        if done % step == 0 or done == count:
            rate = done / max(time.perf_counter() - t0, 1e-9)
            say(f"  {done}/{count} images ({rate:.1f} images/s)")

    if workers <= 1:
        for i in range(count):
            docs[i] = _write_sample(generator(i), out)
            report(i + 1)
    else:
        with SamplePool(generator, workers) as pool:
            write = functools.partial(_write_sample_to, str(out))
            for done, doc in enumerate(pool.map(write, range(count)), start=1):
                docs[done - 1] = doc
                report(done)
    labels = out / "labels.jsonl"
    with labels.open("w", encoding="utf-8") as fh:
        for doc in docs:
            fh.write(json.dumps(doc) + "\n")
    meta = {
        "mode": generator.mode, "seed": generator.seed, "count": count,
        "robot_id": generator.robot_id, "keypoint_names": list(generator.model.keypoint_names),
        "classes": list(CLASSES), "scenario": generator.scenario.source_path,
        "depth_png": "uint16 millimetres, 0 = nothing rendered",
    }
    (out / "dataset.json").write_text(json.dumps(meta, indent=2), encoding="utf-8")
    return labels
