"""What every experiment of ``smartedge evaluate paper`` shares: its settings
(:class:`PaperConfig`), the deployed pipeline set up for the paper's protocol
(:func:`paper_pipeline_config`), the source of the detections (the scenario's noise model or
rendered images through the edge's ONNX models: :func:`make_detector`), and the pipeline's poses
read as ``(x, y, theta)`` arrays (:func:`pose_array`; world frame, metres and radians).

Fusion is pluggable: ``PaperConfig.fusion_factory`` builds the pose graph of each run's
pipeline (``robot_id`` → an object like :class:`backend_service.fusion.PoseGraphFusion`); the
default is GTSAM's when it imports (:func:`default_fusion_factory`), otherwise the Fused rows say
"fusion not available".
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from backend_service.pipeline import FusionFactory
from backend_service.pipeline_config import PipelineConfig
from core.pose import PlanarPose
from core.site import Site
from protocol.messages import PoseEstimate
from simulation.detections import DetectionSimulator
from simulation.scenario import Scenario
from simulation.world import World

log = logging.getLogger(__name__)

DETECTION_MODES = ("noise", "cnn")
#: default camera rate of the CNN mode: rendering and inferring every frame of 4 cameras at
#: 15 Hz on 2 CPU cores takes about 3 times longer; 5 Hz still gives the 5-frame average in 1 s
CNN_RATE_HZ = 5.0
#: the robot bridge publishes the robot's own localization at this rate
#: (``robot_bridge.service.LOCALIZATION_PERIOD_NS``)
LOCALIZATION_RATE_HZ = 10.0


def default_fusion_factory() -> FusionFactory | None:
    """GTSAM pose-graph fusion if importable, else ``None``."""
    try:
        from backend_service.fusion import PoseGraphFusion
    except ImportError as exc:  # fusion is optional for the experiment
        log.info("fusion not available: %s", exc)
        return None
    return PoseGraphFusion


@dataclasses.dataclass(frozen=True)
class PaperConfig:
    """Settings of the experiments of ``smartedge evaluate paper``; defaults follow the paper."""

    #: experiment 1: runs of each trajectory in each direction (paper: 3)
    runs_per_direction: int = 3
    #: base seed of every run (:func:`simulation.runner.run_seed`)
    seed: int = 0
    #: experiment 1: trajectory names (None: all of the scenario's)
    trajectories: tuple[str, ...] | None = None
    #: scenario file (None: the paper's lab)
    scenario_path: str | None = None
    #: dwell time at each waypoint, s, instead of the scenario's
    stop_s: float | None = None
    #: experiment 1: a stop is sampled once the robot has stood there this long, s
    dwell_s: float = 1.0
    #: camera estimates averaged while static (the "5 frames" row)
    frames: int = 5
    #: experiment 1: per-run SE(2) (Procrustes) alignment before the errors, as in the paper
    align: bool = False
    #: fuse camera estimates and odometry in a pose graph (the Fused rows)
    use_fusion: bool = True
    #: the pose graph of each run (None: :func:`default_fusion_factory`)
    fusion_factory: FusionFactory | None = None
    #: the fused trajectory is read at every n-th logged stamp (Table II, plots)
    fused_trajectory_step: int = 4
    #: which experiments run_paper runs: 1 (Table I/II), 2 (feedback, Fig. 7), 3 (Table III),
    #: 4 (semantic mapping: coverage, labels, consistency; Sec. IV-C)
    experiments: tuple[int, ...] = (1, 2, 3, 4)
    #: experiment 2: the long route driven without and with feedback, and its seeds
    long_route: str = "traj3x3"
    feedback_seeds: int = 1
    #: experiment 3: the cluttered route and its runs per condition (None: the scenario's)
    robustness_route: str = "robustness_route"
    robustness_runs: int | None = None
    #: experiment 4: the robot's exploration route and its head camera's cloud rate
    mapping_route: str = "robustness_route"
    mapping_cloud_rate_hz: float = 1.0
    #: where detections come from: "noise" (the scenario's detector error model) or "cnn"
    #: (rendered images through the edge's ONNX models: :mod:`lab.rendered_detections`)
    detections: str = "noise"
    #: camera frame rate instead of the scenario's (None: the scenario's; see CNN_RATE_HZ)
    camera_rate_hz: float | None = None
    #: CNN mode: a folder with other detector + keypoint models (default: the site's/shipped)
    model_dir: str | None = None
    #: CNN mode: onnxruntime threads
    threads: int = 2
    #: CNN mode: each camera's far band, as the edge agent's ``--far-band on`` (default off,
    #: as the edge on the CPU)
    far_band: bool = False
    #: CNN mode: per-frame sensor noise of the rendered images (digital numbers, 0-255)
    sensor_noise_dn: float | None = None
    #: experiment 1: draw the cameras' calibration error with each of these seeds and pool the
    #: runs (None: the scenario's one draw). A covariance with a calibration term is consistent
    #: in expectation over calibration errors; one draw can be lucky or not.
    calibration_seeds: tuple[int, ...] | None = None
    #: worker processes for the independent runs of experiments 1-3 (None: one per core; 1:
    #: all in this process); the results do not depend on it
    jobs: int | None = None

    def __post_init__(self) -> None:
        if self.detections not in DETECTION_MODES:
            raise ValueError(f"detections {self.detections!r}: expected one of "
                             f"{DETECTION_MODES}")
        if self.camera_rate_hz is not None and not self.camera_rate_hz > 0:
            raise ValueError(f"camera_rate_hz must be > 0, got {self.camera_rate_hz}")
        if self.jobs is not None and self.jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {self.jobs}")

    def per_process(self, jobs: int) -> PaperConfig:
        """The settings each of ``jobs`` worker processes runs with: the cores are shared, so
        each gets its share of onnxruntime threads (the networks' outputs do not depend on
        the thread count)."""
        if jobs <= 1:
            return self
        return dataclasses.replace(self, threads=max(1, self.threads // jobs))

    def effective_camera_rate(self, scenario: Scenario) -> float:
        """The camera rate the runs use: ``camera_rate_hz``, else :data:`CNN_RATE_HZ` in CNN
        mode, else the scenario's."""
        if self.camera_rate_hz is not None:
            return float(self.camera_rate_hz)
        if self.detections == "cnn":
            return min(CNN_RATE_HZ, scenario.cameras.rate_hz)
        return float(scenario.cameras.rate_hz)


def pose_array(value: object) -> np.ndarray | None:
    """A pose of the pipeline (:class:`PoseEstimate`, :class:`PlanarPose` or anything with at
    least 3 numbers) as a (3,) array ``(x, y, theta)``; ``None`` for ``None`` or a non-finite
    array."""
    if value is None:
        return None
    if isinstance(value, PoseEstimate):
        return np.array([value.x, value.y, value.theta])
    if isinstance(value, PlanarPose):
        return value.as_array()
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    return arr[:3] if arr.size >= 3 and np.all(np.isfinite(arr[:3])) else None


def paper_pipeline_config(site: Site, single_camera: str = "map", frames: int | None = None,
                          scenario: Scenario | None = None, detections: str = "cnn",
                          ) -> PipelineConfig:
    """The deployed pipeline set up for the paper's protocol: the prior is the robot's own
    localization, and camera estimates go into the pose graph only as the averages taken at
    static waypoints. ``single_camera``: the single-camera treatment (``SolverConfig``);
    ``frames``: estimates averaged while static (default: the site's). With ``detections``
    ``"noise"`` and the ``scenario``, the covariance's detector error model is the scenario's
    (its per-detection shift and scale, drawn independently every frame), as a detector card
    would state it; with ``"cnn"`` the defaults measured for the shipped CNN apply."""
    config = PipelineConfig.from_site(site, prior="localization", fuse_while_moving=False)
    solver = dataclasses.replace(config.solver, single_camera=single_camera)
    multi_frame = config.multi_frame
    if frames is not None:
        multi_frame = dataclasses.replace(multi_frame, count=int(frames))
    if detections == "noise" and scenario is not None:
        solver = dataclasses.replace(
            solver, detection_shift_sigma_px=scenario.noise.sigma_shift_px,
            detection_scale_sigma=scenario.noise.sigma_scale)
        multi_frame = dataclasses.replace(multi_frame, frame_correlation=0.0)
    return dataclasses.replace(config, solver=solver, multi_frame=multi_frame)


def make_detector(scenario: Scenario, world: World, config: PaperConfig) -> DetectionSimulator:
    """The runs' detection source: the noise model, or rendered images through the edge's
    ONNX models (CNN mode)."""
    if config.detections == "noise":
        return DetectionSimulator(scenario, world)
    from lab.rendered_detections import RenderedDetections
    from simulation.site_cameras import SensorNoise

    noise = None if config.sensor_noise_dn is None else SensorNoise(config.sensor_noise_dn)
    return RenderedDetections(scenario, world, model_dir=config.model_dir, threads=config.threads,
                              noise=noise, far_band=config.far_band)


def describe_detections(config: PaperConfig, detector: DetectionSimulator) -> str:
    """One line naming the detection source (for the progress lines)."""
    if config.detections == "noise":
        return "the scenario's detector noise model"
    images = detector.images  # type: ignore[attr-defined]
    return (f"rendered images (sensor noise {images.noise.sigma_dn:g} DN) through the ONNX "
            f"models {detector.model_id}")  # type: ignore[attr-defined]
