"""The closed loop in simulated time: camera images of the simulated site through the edge's
ONNX pipeline, as the detection source of :class:`simulation.runner.SimulationRun`.

``smartedge evaluate paper --detections cnn`` runs the paper's experiments with this in place of
the detection noise model: every camera frame is rendered from the camera's true pose with the
robot at its true pose (:class:`simulation.site_cameras.SiteCameraRenderer`, per-frame sensor
noise), and the deployed :class:`edge_agent.pipeline.EdgePipeline` (detector → crop → keypoint
network, onnxruntime) turns it into the :class:`protocol.messages.RobotDetections` the edge
agent would publish. Stamps, clock errors and arrival delays are the simulation's, as in the
noise model.

Three savings, none of which changes a message: a frame whose image cannot contain the robot
(its bounding cylinder projects outside the image) is not rendered and gives an empty
detection list; the clean render of a static robot is reused (the sensor noise still differs
per frame, and every frame still goes through the networks); and the frames the cameras
capture at about the same time go through the networks together (:meth:`RenderedDetections.
detect_many`, one batch per network: the shipped models take a batch dimension, and a batch
gives each image the numbers it gets alone, checked in ``tests/smartedge/
test_rendered_detections.py``).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edge_agent.frames import Frame
from edge_agent.models import RobotKeypointPipeline
from edge_agent.pipeline import EdgePipeline, camera_far_band, process_batch
from protocol.messages import RobotDetections
from simulation.detections import DetectionSimulator, FrameRequest
from simulation.scenario import Scenario
from simulation.site_cameras import SensorNoise, SiteCameraRenderer
from simulation.world import World

log = logging.getLogger(__name__)


@dataclasses.dataclass
class RenderedStats:
    """Work done so far: frames asked for, frames without the robot in the image (not rendered),
    renders, static-robot cache hits, and seconds spent rendering and in the networks."""

    frames: int = 0
    out_of_view: int = 0
    renders: int = 0
    cache_hits: int = 0
    render_s: float = 0.0
    networks_s: float = 0.0

    def __add__(self, other: RenderedStats) -> RenderedStats:
        """The work of both (e.g. runs done in different processes)."""
        return RenderedStats(*(getattr(self, f.name) + getattr(other, f.name)
                               for f in dataclasses.fields(self)))

    def __sub__(self, other: RenderedStats) -> RenderedStats:
        """The work done since ``other`` was copied from the same counters."""
        return RenderedStats(*(getattr(self, f.name) - getattr(other, f.name)
                               for f in dataclasses.fields(self)))

    def line(self) -> str:
        inferred = self.frames - self.out_of_view
        per = 1e3 / max(inferred, 1)
        return (f"{self.frames} frames ({self.out_of_view} without the robot in view), "
                f"{self.renders} renders + {self.cache_hits} static reuses, "
                f"{self.render_s * per:.1f} ms render + {self.networks_s * per:.1f} ms "
                f"networks per frame")


class RenderedDetections(DetectionSimulator):
    """A :class:`DetectionSimulator` whose :meth:`detect` renders the frame and runs the edge
    pipeline instead of perturbing the true keypoints.

    ``models``: the edge's networks (default: the site robot model's, else the shipped ones);
    ``model_dir``: a folder with other models instead; ``min_score``: as the edge agent's
    ``--min-score``; ``noise``: per-frame sensor noise; ``far_band``: each camera's far band
    (the edge agent's ``--far-band on``) or none (default, as the edge on the CPU)."""

    #: the runner hands over the cameras' frames of one capture together (one network batch)
    batches_frames = True

    def __init__(self, scenario: Scenario, world: World | None = None, *,
                 models: RobotKeypointPipeline | None = None, model_dir: str | Path | None = None,
                 threads: int = 2, min_score: float = 0.3, noise: SensorNoise | None = None,
                 texture_seed: int = 0, far_band: bool = False) -> None:
        super().__init__(scenario, world)
        self.images = SiteCameraRenderer(scenario, texture_seed=texture_seed, noise=noise)
        if models is None:
            models = RobotKeypointPipeline.for_robot(
                self.model, None if model_dir is None else str(model_dir), threads=threads)
        self.models = models
        self.pipelines = {
            c: EdgePipeline(c, models, min_score=min_score,
                            expected_size=(cam.width, cam.height),
                            far_band=camera_far_band(scenario.site, c, models) if far_band
                            else None)
            for c, cam in self.cameras.items()
        }
        self.stats = RenderedStats()
        log.info("rendered detections through %s (%s), sensor noise %.1f DN",
                 models.model_id, ", ".join(models.providers), self.images.noise.sigma_dn)

    @property
    def model_id(self) -> str:
        return self.models.model_id

    def prepare_frames(self, camera_id: str, poses: np.ndarray) -> None:
        """Nothing to prepare: these frames are rendered, not made from the noise model's
        geometry."""

    def detect(self, camera_id: str, true_capture_ns: int, pose: np.ndarray, seq: int,
               rng: np.random.Generator) -> RobotDetections:
        """The edge agent's message for the frame ``camera_id`` captures at
        ``true_capture_ns`` with the robot at true planar ``pose``."""
        return self.detect_many([FrameRequest(camera_id, true_capture_ns, pose, seq, rng)])[0]

    def detect_many(self, frames: Sequence[FrameRequest]) -> list[RobotDetections]:
        """The messages of several frames (e.g. the cameras' frames of one capture): each
        rendered as :meth:`detect` renders it (its sensor noise from its own ``rng``), the
        networks run once for all frames with the robot in view (a batch; each message is the
        one its frame gives alone)."""
        out: list[RobotDetections | None] = [None] * len(frames)
        todo: list[tuple[int, Frame]] = []
        t0 = time.perf_counter()
        for i, req in enumerate(frames):
            cam = self.cameras[req.camera_id]
            stamp = max(self.capture_stamp_ns(req.camera_id, req.true_capture_ns), 0)
            self.stats.frames += 1
            if not self.images.robot_in_image(req.camera_id, req.pose):
                self.stats.out_of_view += 1
                out[i] = RobotDetections(req.camera_id, stamp, req.seq, cam.width, cam.height,
                                         self.model_id, ())
                continue
            renders = self.images.renders
            image = self.images.render(req.camera_id, req.pose, req.rng)
            if self.images.renders > renders:
                self.stats.renders += 1
            else:
                self.stats.cache_hits += 1
            todo.append((i, Frame(image, stamp, req.seq)))
        t1 = time.perf_counter()
        results = process_batch([(self.pipelines[frames[i].camera_id], frame)
                                 for i, frame in todo])
        for (i, _), (msg, _latency) in zip(todo, results, strict=True):
            out[i] = msg
        self.stats.render_s += t1 - t0
        self.stats.networks_s += time.perf_counter() - t1
        return [msg for msg in out if msg is not None]
