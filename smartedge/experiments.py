"""The paper's pose-accuracy experiments (Sec. IV-B) on the simulated lab.

For each trajectory, direction and iteration (paper: 3 x 2 x 3 = 18 runs) the simulation's
messages (detections, odometry, the robot's own localization) go in arrival order through the
backend's one pipeline (:class:`backend_service.pipeline.BackendPipeline`, the object the
backend service runs), set up for the paper's protocol (:func:`paper_pipeline_config`: prior =
the robot's localization, camera estimates fused as the averages taken while static). At every
waypoint, once the robot has been static for ``dwell_s``, one sample per pose source is taken:

- Robot: the robot's internal localization (no corrections are fed back, as in the paper);
- Cameras (raw): the first solved frame-set, solved again from the same prior without any
  single-camera treatment (the ablation);
- Cameras (paper heuristic): the same, with the paper's bearing-only heuristic;
- Cameras (1 frame): the pipeline's estimate of that frame-set (single camera: the MAP
  combination with the localization and its covariance);
- Cameras (5 frames): the pipeline's first average of ``frames`` estimates while static;
- Fused: the pipeline's pose graph, smoothed, at that stamp (after the run).

Table I groups the errors by the number of cameras that see the waypoint; Table II is the RMS
translation error over whole trajectories (Robot, Fused). The ground truth is the simulation's
true pose, in the same world frame, so no alignment is needed; ``align=True`` applies the
paper's per-run Procrustes (SE(2)) alignment anyway.

Fusion is pluggable: ``PaperConfig.fusion_factory`` builds the pose graph of each run's
pipeline (``robot_id`` → an object like :class:`backend_service.fusion.PoseGraphFusion`); the
default is GTSAM's when it imports, otherwise the Fused row says "fusion not available".
"""

from __future__ import annotations

import bisect
import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from backend_service.estimate import estimate_pose
from backend_service.frame_set import FrameSet, PlanarPose
from backend_service.pipeline import (
    BackendPipeline,
    FusionFactory,
    PipelineConfig,
    PipelineOutput,
)
from protocol.messages import Odometry, PoseEstimate
from protocol.site import Site
from simulation.detections import DetectionSimulator
from simulation.runner import SimulationRun, run_seed
from simulation.scenario import PAPER_SCENARIO, Scenario, load_scenario
from simulation.world import World
from smartedge.evaluation.metrics import (
    MeanStd,
    align_planar,
    group_by_camera_count,
    heading_errors,
    rms,
    translation_errors,
    travelled_distance,
)

log = logging.getLogger(__name__)

SOURCES = ("robot", "raw", "paper", "one_frame", "five_frames", "fused")
ROW_NAMES = {
    "robot": "Robot",
    "raw": "Cameras (raw)",
    "paper": "Cameras (paper heuristic)",
    "one_frame": "Cameras (1 frame)",
    "five_frames": "Cameras (5 frames)",
    "fused": "Fused",
}
CAMERA_GROUPS = (1, 2, 4)
DETECTION_MODES = ("noise", "cnn")
#: default camera rate of the CNN mode: rendering and inferring every frame of 4 cameras at
#: 15 Hz on 2 CPU cores takes about 3 times longer; 5 Hz still gives the 5-frame average in 1 s
CNN_RATE_HZ = 5.0
FUSION_UNAVAILABLE = "fusion not available"
#: the robot bridge publishes the robot's own localization at this rate (robot_bridge.service)
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
    """Settings of the experiment; defaults follow the paper."""

    runs_per_direction: int = 3
    seed: int = 0
    trajectories: tuple[str, ...] | None = None
    scenario_path: str | None = None
    stop_s: float | None = None
    dwell_s: float = 1.0
    frames: int = 5
    align: bool = False
    use_fusion: bool = True
    fusion_factory: FusionFactory | None = None
    fused_trajectory_step: int = 4
    #: which experiments run_paper runs: 1 (Table I/II), 2 (feedback, Fig. 7), 3 (Table III),
    #: 4 (semantic mapping: coverage, labels, consistency; Sec. IV-C)
    experiments: tuple[int, ...] = (1, 2, 3, 4)
    long_route: str = "traj3x3"
    feedback_seeds: int = 1
    robustness_route: str = "robustness_route"
    robustness_runs: int | None = None
    #: experiment 4: the robot's exploration route and its head camera's cloud rate
    mapping_route: str = "robustness_route"
    mapping_cloud_rate_hz: float = 1.0
    #: where detections come from: "noise" (the scenario's detector error model) or "cnn"
    #: (rendered images through the edge's ONNX models: :mod:`smartedge.rendered_detections`)
    detections: str = "noise"
    #: camera frame rate instead of the scenario's (None: the scenario's; see CNN_RATE_HZ)
    camera_rate_hz: float | None = None
    #: CNN mode: a folder with other detector + keypoint models (default: the site's/shipped)
    model_dir: str | None = None
    #: CNN mode: onnxruntime threads
    threads: int = 2
    #: CNN mode: per-frame sensor noise of the rendered images (digital numbers, 0-255)
    sensor_noise_dn: float | None = None
    #: experiment 1: draw the cameras' calibration error with each of these seeds and pool the
    #: runs (None: the scenario's one draw). A covariance with a calibration term is consistent
    #: in expectation over calibration errors; one draw can be lucky or not.
    calibration_seeds: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if self.detections not in DETECTION_MODES:
            raise ValueError(f"detections {self.detections!r}: expected one of "
                             f"{DETECTION_MODES}")
        if self.camera_rate_hz is not None and not self.camera_rate_hz > 0:
            raise ValueError(f"camera_rate_hz must be > 0, got {self.camera_rate_hz}")

    def effective_camera_rate(self, scenario: Scenario) -> float:
        """The camera rate the runs use: ``camera_rate_hz``, else :data:`CNN_RATE_HZ` in CNN
        mode, else the scenario's."""
        if self.camera_rate_hz is not None:
            return float(self.camera_rate_hz)
        if self.detections == "cnn":
            return min(CNN_RATE_HZ, scenario.cameras.rate_hz)
        return float(scenario.cameras.rate_hz)


@dataclasses.dataclass
class StopSample:
    """One waypoint visit of one run: true pose and each source's estimate ((3,) or None)."""

    run: str
    trajectory: str
    waypoint: str
    num_cameras: int
    stamp_ns: int
    ground_truth: np.ndarray
    estimates: dict[str, np.ndarray | None]
    #: (3, 3) reported covariance per source (for NEES), where the source reports one
    covariances: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class RunResult:
    """One run: the samples at its stops and its full trajectories (for Table II and plots).

    ``stamps_ns`` (N,), ``ground_truth`` / ``robot`` / ``fused`` (N, 3); ``fused`` has NaN rows
    where the fusion had no pose (or everywhere without fusion).
    """

    name: str
    trajectory: str
    reverse: bool
    iteration: int
    samples: list[StopSample]
    stamps_ns: np.ndarray
    ground_truth: np.ndarray
    robot: np.ndarray
    fused: np.ndarray
    simulated_s: float
    wall_s: float
    counters: dict[str, int]


def _to_pose(value: object) -> np.ndarray | None:
    if value is None:
        return None
    if isinstance(value, PoseEstimate):
        return np.array([value.x, value.y, value.theta])
    if isinstance(value, PlanarPose):
        return value.as_array()
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    return arr[:3] if arr.size >= 3 and np.all(np.isfinite(arr[:3])) else None


def _keep_covariance(sample: StopSample, source: str, est: object) -> None:
    cov = getattr(est, "covariance", None)
    if cov is not None:
        arr = np.asarray(cov, dtype=np.float64)
        if arr.shape == (3, 3) and np.all(np.isfinite(arr)):
            sample.covariances[source] = arr


def nees_table(results: Sequence[RunResult]) -> tuple[str, dict[str, dict[str, float]]]:
    """Mean normalized estimation error squared (3 DoF: consistent = 3) of each camera source
    per number of cameras: e^T C^-1 e with e = estimate - truth (heading wrapped) and C the
    covariance the source reported."""
    numbers: dict[str, dict[str, float]] = {}
    for source in ("raw", "paper", "one_frame", "five_frames", "fused"):
        per: dict[str, list[float]] = {}
        for res in results:
            for smp in res.samples:
                est, cov = smp.estimates.get(source), smp.covariances.get(source)
                if est is None or cov is None:
                    continue
                e = np.asarray(est, np.float64) - smp.ground_truth
                e[2] = math.remainder(float(e[2]), 2 * math.pi)
                try:
                    value = float(e @ np.linalg.solve(cov, e))
                except np.linalg.LinAlgError:
                    continue
                for key in (str(smp.num_cameras), "all"):
                    per.setdefault(key, []).append(value)
        numbers[source] = {k: float(np.mean(v)) for k, v in per.items()}
        numbers[source].update({f"n_{k}": float(len(v)) for k, v in per.items()})
    groups = [str(c) for c in CAMERA_GROUPS] + ["all"]
    lines = ["**NEES**: mean normalized estimation error squared of the reported covariances "
             "(3 degrees of freedom: 3 is consistent, larger is overconfident).", "",
             "| Pose Estimation | " + " | ".join(
                 f"{g} camera{'s' if g != '1' else ''}" if g != "all" else "all"
                 for g in groups) + " |",
             "|---|" + "---|" * len(groups)]
    for source, row in numbers.items():
        cells = [f"{row[g]:.1f}" if g in row else "n/a" for g in groups]
        lines.append(f"| {ROW_NAMES[source]} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n", numbers


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


def run_once(scenario: Scenario, trajectory: str, reverse: bool, iteration: int,
             config: PaperConfig, fusion_factory: FusionFactory | None,
             world: World | None = None,
             detector: DetectionSimulator | None = None) -> RunResult:
    """Simulate one run and take the per-stop samples (see the module docstring).

    The simulated messages go in arrival order through :class:`BackendPipeline` (the backend
    service's own object) exactly as the service receives them. The raw row is an ablation on
    the pipeline's own record: the stop's first frame-set, from the prior the pipeline used,
    solved with the single-camera heuristic off."""
    wall0 = time.perf_counter()
    site = scenario.site
    sim = SimulationRun(scenario, trajectory, reverse,
                        seed=run_seed(scenario, trajectory, reverse, iteration, config.seed),
                        world=world, detector=detector)
    name = f"{trajectory}{'r' if reverse else ''}_{iteration + 1}"
    pipeline = BackendPipeline(site, paper_pipeline_config(site, frames=config.frames,
                                                           scenario=scenario,
                                                           detections=config.detections),
                               fusion_factory=fusion_factory,
                               with_fusion=fusion_factory is not None)
    ablations = {name: dataclasses.replace(pipeline.config.solver, single_camera=mode)
                 for name, mode in (("raw", "plain"), ("paper", "paper"))}
    start_ns = scenario.start_stamp_ns
    counters = {"frame_sets": 0, "solved": 0, "failed": 0}
    samples: dict[int, StopSample] = {}

    def localization_at(stamp_ns: int) -> np.ndarray:
        stamps = sim.log.stamps_ns
        i = max(bisect.bisect_right(stamps, stamp_ns) - 1, 0)
        return sim.log.localization[i]

    def sample_for(fs: FrameSet) -> StopSample | None:
        """The sample of the stop ``fs`` falls in, once the robot stood there ``dwell_s``."""
        t_s = (fs.stamp_ns - start_ns) * 1e-9
        stop = sim.plan.stop_at(t_s)
        if stop is None or t_s < stop.t0_s + config.dwell_s or not fs.observations:
            return None
        sample = samples.get(stop.index)
        if sample is None:
            sample = StopSample(
                run=name, trajectory=trajectory, waypoint=stop.waypoint,
                num_cameras=len(sim.stop_cameras[stop.index]), stamp_ns=fs.stamp_ns,
                ground_truth=np.asarray(sim.ground_truth_at(fs.stamp_ns)[0]),
                estimates={"robot": localization_at(fs.stamp_ns).copy()},
            )
            samples[stop.index] = sample
        return sample

    def take(out: PipelineOutput) -> None:
        for rec in out.solves:
            counters["frame_sets"] += 1
            counters["solved" if rec.result.ok else "failed"] += 1
            sample = sample_for(rec.frame_set)
            if sample is None or not rec.result.ok:
                continue
            if "one_frame" not in sample.estimates:
                sample.estimates["one_frame"] = _to_pose(rec.result.pose)
                _keep_covariance(sample, "one_frame", rec.result.estimate)
                # the ablations: the same frame-set from the same prior, other treatments
                for name, solver in ablations.items():
                    res = estimate_pose(rec.frame_set, site, rec.prior, solver,
                                        rec.prior_covariance)
                    sample.estimates[name] = _to_pose(res.pose) if res.ok else None
                    _keep_covariance(sample, name, res.estimate)
            if rec.averaged is not None and "five_frames" not in sample.estimates:
                sample.estimates["five_frames"] = _to_pose(rec.averaged)
                _keep_covariance(sample, "five_frames", rec.averaged)

    for tm in sim.messages(localization_rate_hz=LOCALIZATION_RATE_HZ):
        take(pipeline.step(tm.message, tm.arrival_ns))
    take(pipeline.flush())

    fusion = pipeline.tracks[scenario.robot_id].fusion
    stamps, gt, loc = sim.log.arrays()
    fused = np.full_like(gt, np.nan)
    if fusion is not None:
        step = max(1, config.fused_trajectory_step)
        for i in range(0, len(stamps), step):
            p = _to_pose(fusion.pose_at(int(stamps[i])))
            if p is not None:
                fused[i] = p
        for s in samples.values():
            at = fusion.pose_at(int(s.stamp_ns))
            s.estimates["fused"] = _to_pose(at)
            _keep_covariance(s, "fused", at)
    ordered = [samples[k] for k in sorted(samples)]
    return RunResult(
        name=name, trajectory=trajectory, reverse=reverse, iteration=iteration,
        samples=ordered, stamps_ns=stamps, ground_truth=gt, robot=loc, fused=fused,
        simulated_s=sim.duration_s, wall_s=time.perf_counter() - wall0, counters=counters,
    )


# --------------------------------------------------------------------------------------------
# tables
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SourceErrors:
    """Per-sample errors of one source: translation (m), heading (rad), camera counts."""

    translation_m: np.ndarray
    heading_rad: np.ndarray
    num_cameras: np.ndarray


def source_errors(results: Sequence[RunResult], source: str, align: bool = False,
                  ) -> SourceErrors:
    """Errors of ``source`` at all stops of all runs (samples without an estimate skipped)."""
    t_err: list[np.ndarray] = []
    h_err: list[np.ndarray] = []
    counts: list[np.ndarray] = []
    for res in results:
        rows = [(s.ground_truth, s.estimates.get(source), s.num_cameras) for s in res.samples]
        rows = [r for r in rows if r[1] is not None]
        if not rows:
            continue
        gt = np.array([r[0] for r in rows])
        est = np.array([r[1] for r in rows])
        if align and len(rows) >= 2:
            est, _ = align_planar(est, gt)
        t_err.append(translation_errors(gt[:, :2], est[:, :2]))
        h_err.append(heading_errors(gt[:, 2], est[:, 2]))
        counts.append(np.array([r[2] for r in rows]))
    if not t_err:
        return SourceErrors(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    return SourceErrors(np.concatenate(t_err), np.concatenate(h_err), np.concatenate(counts))


def _cell(ms: MeanStd, scale: float, digits: int) -> str:
    if ms.count == 0 or not math.isfinite(ms.mean):
        return "n/a"
    return f"{ms.mean * scale:.{digits}f} ± {ms.std * scale:.{digits}f}"


def table1(results: Sequence[RunResult], fusion_available: bool, align: bool = False,
           ) -> tuple[str, dict[str, dict[str, dict[str, float]]]]:
    """Table I as Markdown, and its numbers ({source: {group: {t_mean_cm, ...}}})."""
    header = ("| Pose Estimation | 1 Camera (cm) | 1 Camera (°) | 2 Cameras (cm) | 2 Cameras (°) "
              "| 4 Cameras (cm) | 4 Cameras (°) | **Average** (cm) | **Average** (°) |")
    lines = [header, "|---|" + "---|" * 8]
    numbers: dict[str, dict[str, dict[str, float]]] = {}
    for src in SOURCES:
        if src == "fused" and not fusion_available:
            lines.append(f"| {ROW_NAMES[src]} | " + " | ".join([FUSION_UNAVAILABLE] * 8) + " |")
            continue
        err = source_errors(results, src, align)
        gt_ = group_by_camera_count(err.translation_m, err.num_cameras, CAMERA_GROUPS)
        gh = group_by_camera_count(err.heading_rad, err.num_cameras, CAMERA_GROUPS)
        cells = []
        numbers[src] = {}
        for g in (*CAMERA_GROUPS, "average"):
            cells += [_cell(gt_[g], 100.0, 2), _cell(gh[g], 180.0 / math.pi, 2)]
            numbers[src][str(g)] = {
                "t_mean_cm": gt_[g].mean * 100, "t_std_cm": gt_[g].std * 100,
                "r_mean_deg": math.degrees(gh[g].mean), "r_std_deg": math.degrees(gh[g].std),
                "count": gt_[g].count,
            }
        lines.append(f"| {ROW_NAMES[src]} | " + " | ".join(cells) + " |")
    title = ("**Table I**: translation and orientation error (mean ± std) at waypoints, by "
             "number of cameras seeing the robot and pose estimation source"
             + (" (per-run SE(2) alignment)" if align else "") + ".\n\n")
    return title + "\n".join(lines) + "\n", numbers


def _trajectory_errors(res: RunResult, source: str, align: bool) -> np.ndarray:
    est = res.robot if source == "robot" else res.fused
    ok = np.all(np.isfinite(est), axis=1)
    if not np.any(ok):
        return np.zeros(0)
    gt, e = res.ground_truth[ok], est[ok]
    if align and len(e) >= 2:
        e, _ = align_planar(e, gt)
    return translation_errors(gt[:, :2], e[:, :2])


def table2(results: Sequence[RunResult], fusion_available: bool, align: bool = False,
           ) -> tuple[str, dict[str, dict[str, float]]]:
    """Table II (RMS translation error per trajectory, cm) as Markdown, and its numbers."""
    names = sorted({r.trajectory for r in results})
    lines = ["| Pose Estimation | " + " | ".join(names) + " | **Avg.** |",
             "|---|" + "---|" * (len(names) + 1)]
    numbers: dict[str, dict[str, float]] = {}
    for src in ("robot", "fused"):
        if src == "fused" and not fusion_available:
            lines.append(f"| {ROW_NAMES[src]} | "
                         + " | ".join([FUSION_UNAVAILABLE] * (len(names) + 1)) + " |")
            continue
        per = {}
        for n in names:
            errs = [_trajectory_errors(r, src, align) for r in results if r.trajectory == n]
            per[n] = rms(np.concatenate(errs)) * 100 if errs else math.nan
        avg = float(np.nanmean(list(per.values()))) if per else math.nan
        numbers[src] = {**per, "average": avg}
        lines.append(f"| {ROW_NAMES[src]} | " + " | ".join(f"{per[n]:.2f}" for n in names)
                     + f" | {avg:.2f} |")
    title = "**Table II**: root mean square translation error in cm.\n\n"
    return title + "\n".join(lines) + "\n", numbers


# --------------------------------------------------------------------------------------------
# plots (Fig. 6)
# --------------------------------------------------------------------------------------------

_GROUP_COLOURS = {1: "tab:red", 2: "tab:orange", 3: "tab:olive", 4: "tab:green"}


def plot_map(scenario: Scenario, detector: DetectionSimulator, path: Path) -> None:
    """Room, obstacles, cameras with their field of view, waypoints coloured by camera count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from simulation.world import box_corners_xy

    fig, ax = plt.subplots(figsize=(8, 5.2))
    lo, hi = scenario.room_min_xy_m, scenario.room_max_xy_m
    ax.add_patch(plt.Rectangle(lo, *(hi - lo), fill=False, lw=2, color="k"))
    for b in scenario.obstacles:
        ax.add_patch(plt.Polygon(box_corners_xy(b), color="0.75"))
    for cam_id, cam in scenario.site.cameras.items():
        pos = cam.position_world
        fwd = cam.optical_axis_world[:2]
        yaw = math.atan2(fwd[1], fwd[0])
        half = math.atan2(cam.width / 2, cam.K[0, 0])
        for a in (yaw - half, yaw + half):
            ax.plot([pos[0], pos[0] + 3 * math.cos(a)], [pos[1], pos[1] + 3 * math.sin(a)],
                    color="tab:blue", lw=0.8, alpha=0.6)
        ax.plot(pos[0], pos[1], marker="^", color="tab:blue", ms=10)
        ax.annotate(cam_id, pos[:2], textcoords="offset points", xytext=(5, 5), fontsize=8)
    for wp in scenario.waypoints.values():
        n = len(detector.cameras_seeing(np.array([wp.x, wp.y, wp.theta])))
        ax.plot(wp.x, wp.y, "o", color=_GROUP_COLOURS.get(n, "0.3"), ms=11)
        ax.annotate(wp.name, (wp.x, wp.y), textcoords="offset points", xytext=(7, -12),
                    fontsize=9)
    for n, c in _GROUP_COLOURS.items():
        if n != 3:
            ax.plot([], [], "o", color=c, label=f"{n} camera{'s' if n > 1 else ''}")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{scenario.name}: cameras and waypoints")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_runs(results: Sequence[RunResult], scenario: Scenario, out_dir: Path) -> list[Path]:
    """For the first run of each trajectory: paths (GT, Robot, Fused) and translation error
    over the travelled distance."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    firsts: dict[str, RunResult] = {}
    for r in results:
        firsts.setdefault(r.trajectory, r)
    if not firsts:
        return []
    n = len(firsts)
    fig_t, axes_t = plt.subplots(1, n, figsize=(5 * n, 4), squeeze=False)
    fig_e, axes_e = plt.subplots(1, n, figsize=(5 * n, 3), squeeze=False)
    for k, (_name, r) in enumerate(sorted(firsts.items())):
        ax = axes_t[0, k]
        ax.plot(r.ground_truth[:, 0], r.ground_truth[:, 1], "k-", lw=1.5, label="ground truth")
        ax.plot(r.robot[:, 0], r.robot[:, 1], "-", color="tab:red", lw=1, label="robot")
        ok = np.all(np.isfinite(r.fused), axis=1)
        if np.any(ok):
            ax.plot(r.fused[ok, 0], r.fused[ok, 1], "-", color="tab:green", lw=1, label="fused")
        for s in r.samples:
            ax.plot(s.ground_truth[0], s.ground_truth[1], "o",
                    color=_GROUP_COLOURS.get(s.num_cameras, "0.3"), ms=6)
            ax.annotate(s.waypoint, s.ground_truth[:2], fontsize=7, textcoords="offset points",
                        xytext=(4, 4))
        ax.set_aspect("equal")
        ax.set_title(r.name)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend(fontsize=7)
        ax2 = axes_e[0, k]
        dist = travelled_distance(r.ground_truth[:, :2])
        ax2.plot(dist, translation_errors(r.ground_truth[:, :2], r.robot[:, :2]) * 100,
                 color="tab:red", label="robot")
        if np.any(ok):
            ax2.plot(dist[ok], translation_errors(r.ground_truth[ok, :2], r.fused[ok, :2]) * 100,
                     color="tab:green", label="fused")
        cams = [(s, s.estimates.get("five_frames")) for s in r.samples]
        for s, est in cams:
            if est is None:
                continue
            i = int(np.clip(np.searchsorted(r.stamps_ns, s.stamp_ns), 0, len(dist) - 1))
            ax2.plot(dist[i], np.hypot(*(est[:2] - s.ground_truth[:2])) * 100, "s",
                     color=_GROUP_COLOURS.get(s.num_cameras, "0.3"), ms=5)
        ax2.set_xlabel("travelled distance [m]")
        ax2.set_ylabel("translation error [cm]")
        ax2.set_title(r.name)
        ax2.legend(fontsize=7)
    paths = [out_dir / "fig6_trajectories.png", out_dir / "fig6_error_over_distance.png"]
    for fig, p in zip((fig_t, fig_e), paths, strict=False):
        fig.tight_layout()
        fig.savefig(p, dpi=120)
        plt.close(fig)
    return paths


# --------------------------------------------------------------------------------------------
# the whole experiment
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass
class PaperReport:
    """What :func:`run_paper` produced."""

    results: list[RunResult]
    table1_markdown: str
    table2_markdown: str
    table1: dict[str, dict[str, dict[str, float]]]
    table2: dict[str, dict[str, float]]
    fusion_available: bool
    files: list[Path]
    wall_s: float
    feedback_runs: list[FeedbackRun] = dataclasses.field(default_factory=list)
    robustness_runs: list[FeedbackRun] = dataclasses.field(default_factory=list)
    feedback_markdown: str = ""
    robustness_markdown: str = ""
    nees_markdown: str = ""
    mapping_markdown: str = ""


def run_paper(config: PaperConfig, out_dir: str | Path,
              progress: Callable[[str], None] | None = None,
              scenario: Scenario | None = None) -> PaperReport:
    """Run the experiment, write ``table1.md``, ``table2.md``, ``results.json``,
    ``samples.csv`` and the PNG plots into ``out_dir``; returns the report."""
    wall0 = time.perf_counter()
    say = progress or (lambda line: log.info("%s", line))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sc = scenario or load_scenario(config.scenario_path or PAPER_SCENARIO)
    if config.stop_s is not None:
        sc = sc.with_overrides(motion=dataclasses.replace(sc.motion, stop_s=config.stop_s))
    names = config.trajectories or tuple(sc.trajectories)
    for n in names:
        if n not in sc.trajectories:
            raise ValueError(
                f"unknown trajectory {n!r}; the scenario has {sorted(sc.trajectories)}")
    factory = config.fusion_factory
    if factory is None and config.use_fusion:
        factory = default_fusion_factory()
    fusion_available = factory is not None
    rate = config.effective_camera_rate(sc)
    if rate != sc.cameras.rate_hz:
        sc = sc.with_overrides(cameras=dataclasses.replace(sc.cameras, rate_hz=rate))
    world = World(sc)
    detector = make_detector(sc, world, config)
    say(f"detections: {describe_detections(config, detector)}, cameras at {rate:g} Hz")
    results: list[RunResult] = []
    t1_md = t2_md = nees_md = ""
    t1: dict[str, dict[str, dict[str, float]]] = {}
    t2: dict[str, dict[str, float]] = {}
    files: list[Path] = []
    if 1 in config.experiments:
        cal_seeds = config.calibration_seeds or (sc.seeds.calibration,)
        plan = [(cs, n, rev, it) for cs in cal_seeds for n in names for rev in (False, True)
                for it in range(config.runs_per_direction)]
        say(f"paper experiment 1: {len(plan)} runs on {sc.name} "
            f"({'with' if fusion_available else 'without'} fusion"
            + (f", calibration seeds {','.join(map(str, cal_seeds))}"
               if config.calibration_seeds else "") + ")")
        detectors = {sc.seeds.calibration: detector}
        for k, (cs, n, rev, it) in enumerate(plan, start=1):
            if cs not in detectors:
                sc_cal = sc.with_overrides(seeds=dataclasses.replace(sc.seeds, calibration=cs))
                detectors[cs] = make_detector(sc_cal, world, config)
            res = run_once(sc, n, rev, it, config, factory, world, detectors[cs])
            if config.calibration_seeds:
                res = _with_suffix(res, f"_cal{cs}")
            results.append(res)
            say(f"[{k}/{len(plan)}] {res.name}: {res.simulated_s:.0f} s simulated in "
                f"{res.wall_s:.1f} s ({res.simulated_s / max(res.wall_s, 1e-9):.0f}x), "
                f"{len(res.samples)} stops, {res.counters['frame_sets']} frame-sets")
            if hasattr(detector, "stats"):
                say(f"  images so far: {detector.stats.line()}")
        t1_md, t1 = table1(results, fusion_available, config.align)
        t2_md, t2 = table2(results, fusion_available, config.align)
        nees_md, nees = nees_table(results)
        files += _write_experiment1(out, sc, config, results, t1_md, t2_md, t1, t2,
                                    fusion_available, detector, nees_md, nees)
    fb_runs: list[FeedbackRun] = []
    fb_md = ""
    fb_numbers: dict[str, float] = {}
    if 2 in config.experiments:
        say(f"paper experiment 2: {config.long_route} without and with correction feedback, "
            f"{config.feedback_seeds} seed(s)")
        fb_runs = run_experiment2(sc, config, factory, world, detector, say)
        fb_md, fb_numbers = feedback_table(fb_runs)
        files.append(plot_feedback(fb_runs, out / "fig7_feedback_error_over_distance.png"))
        (out / "experiment2.md").write_text(fb_md, encoding="utf-8")
        files.append(out / "experiment2.md")
    rb_runs: list[FeedbackRun] = []
    rb_md = ""
    rb_numbers: dict[str, dict[str, float]] = {}
    if 3 in config.experiments:
        fm = failure_model(sc)
        say(f"paper experiment 3: {config.robustness_route}, "
            f"{config.robustness_runs or sc.robustness.runs} runs without and with feedback "
            f"(WP tolerance {fm.waypoint_tolerance_m} m, footprint {fm.footprint_m} m)")
        rb_runs = run_experiment3(sc, config, factory, world, detector, say)
        rb_md, rb_numbers = robustness_table(rb_runs)
        (out / "table3.md").write_text(rb_md, encoding="utf-8")
        files.append(out / "table3.md")
    map_md = ""
    if 4 in config.experiments:
        map_md, map_files = run_experiment4(sc, config, factory, world, detector, out, say)
        files += map_files
    if 2 in config.experiments or 3 in config.experiments:
        (out / "feedback_results.json").write_text(json.dumps({
            "scenario": sc.name, "seed": config.seed, "experiment2": fb_numbers,
            "experiment2_runs": [_run_summary(r) for r in fb_runs],
            "experiment3": rb_numbers,
            "experiment3_runs": [_run_summary(r) for r in rb_runs],
        }, indent=2, default=float), encoding="utf-8")
        files.append(out / "feedback_results.json")
    wall = time.perf_counter() - wall0
    sections = ["# Paper experiments on the simulated lab\n"]
    if 1 in config.experiments:
        sections += ["## Experiment 1: pose accuracy (Sec. IV-B, Table I/II, Fig. 6)\n", t1_md,
                     t2_md, nees_md]
    if 2 in config.experiments:
        sections += ["## Experiment 2: correction feedback (Sec. IV-B, Fig. 7)\n", fb_md,
                     "![Fig. 7](fig7_feedback_error_over_distance.png)\n"]
    if 3 in config.experiments:
        sections += ["## Experiment 3: robustness (Sec. IV-D, Table III)\n", rb_md]
    if 4 in config.experiments:
        sections += ["## Experiment 4: collaborative semantic mapping (Sec. IV-C, Fig. 7-8)\n",
                     map_md, "![Semantic map](semantic_map_topdown.png)\n"]
    sections.append(f"Wall time: {wall:.0f} s.\n")
    (out / "report.md").write_text("\n".join(sections), encoding="utf-8")
    files.append(out / "report.md")
    say(f"done in {wall:.1f} s; wrote {out}")
    return PaperReport(results, t1_md, t2_md, t1, t2, fusion_available, files, wall,
                       fb_runs, rb_runs, fb_md, rb_md, nees_md, map_md)


def _with_suffix(res: RunResult, suffix: str) -> RunResult:
    """``res`` renamed (runs of several calibration draws keep distinct names and files)."""
    name = res.name + suffix
    return dataclasses.replace(res, name=name, samples=[dataclasses.replace(s, run=name)
                                                        for s in res.samples])


def make_detector(sc: Scenario, world: World, config: PaperConfig) -> DetectionSimulator:
    """The runs' detection source: the noise model, or rendered images through the edge's
    ONNX models (CNN mode)."""
    if config.detections == "noise":
        return DetectionSimulator(sc, world)
    from simulation.site_cameras import SensorNoise
    from smartedge.rendered_detections import RenderedDetections

    noise = None if config.sensor_noise_dn is None else SensorNoise(config.sensor_noise_dn)
    return RenderedDetections(sc, world, model_dir=config.model_dir, threads=config.threads,
                              noise=noise)


def describe_detections(config: PaperConfig, detector: DetectionSimulator) -> str:
    if config.detections == "noise":
        return "the scenario's detector noise model"
    images = detector.images  # type: ignore[attr-defined]
    return (f"rendered images (sensor noise {images.noise.sigma_dn:g} DN) through the ONNX "
            f"models {detector.model_id}")  # type: ignore[attr-defined]


def _run_summary(r: FeedbackRun) -> dict[str, object]:
    return {"name": r.name, "feedback": r.feedback, "outcome": r.outcome,
            "failure_waypoint": r.failure_waypoint, "failure_distance_m": r.failure_distance_m,
            "travelled_m": r.travelled_m, "robot_rms_cm": r.robot_rms_m() * 100,
            "fused_rms_cm": r.fused_rms_m() * 100,
            "corrections_accepted": sum(c.accepted for c in r.corrections),
            "simulated_s": r.simulated_s, "wall_s": r.wall_s}


def _write_experiment1(out: Path, sc: Scenario, config: PaperConfig,
                       results: list[RunResult], t1_md: str, t2_md: str,
                       t1: dict[str, dict[str, dict[str, float]]],
                       t2: dict[str, dict[str, float]], fusion_available: bool,
                       detector: DetectionSimulator, nees_md: str,
                       nees: dict[str, dict[str, float]]) -> list[Path]:
    files = [out / "table1.md", out / "table2.md", out / "results.json", out / "samples.csv",
             out / "fig6_map.png", out / "nees.md"]
    files[0].write_text(t1_md, encoding="utf-8")
    files[1].write_text(t2_md, encoding="utf-8")
    files[2].write_text(json.dumps({
        "scenario": sc.name, "runs": len(results), "seed": config.seed, "align": config.align,
        "fusion_available": fusion_available, "table1": t1, "table2": t2, "nees": nees,
        "simulated_s": sum(r.simulated_s for r in results),
    }, indent=2, default=float), encoding="utf-8")
    files[5].write_text(nees_md, encoding="utf-8")
    with files[3].open("w", encoding="utf-8") as f:
        f.write("run,waypoint,num_cameras,stamp_ns,gt_x,gt_y,gt_theta,source,x,y,theta\n")
        for r in results:
            for s in r.samples:
                for src in SOURCES:
                    e = s.estimates.get(src)
                    if e is None:
                        continue
                    f.write(f"{r.name},{s.waypoint},{s.num_cameras},{s.stamp_ns},"
                            f"{s.ground_truth[0]:.5f},{s.ground_truth[1]:.5f},"
                            f"{s.ground_truth[2]:.5f},{src},{e[0]:.5f},{e[1]:.5f},{e[2]:.5f}\n")
    plot_map(sc, detector, files[4])
    files += plot_runs(results, sc, out)
    files += write_run_trajectories(results, out / "tum")
    return files


def write_run_trajectories(results: Sequence[RunResult], folder: Path) -> list[Path]:
    """TUM files per run (``<folder>/<run>/``): ``ground_truth``, ``robot`` (its own
    localization) and ``fused`` over the whole run, and the camera estimates at the stops
    (``cameras_1frame``, ``cameras_5frames``), for evo or ``smartedge evaluate ate``."""
    from smartedge.evaluation.trajectory_io import write_tum_planar

    written: list[Path] = []
    for r in results:
        run_dir = folder / r.name
        t_s = r.stamps_ns * 1e-9
        tracks = {"ground_truth": (t_s, r.ground_truth), "robot": (t_s, r.robot)}
        ok = np.all(np.isfinite(r.fused), axis=1)
        if ok.any():
            tracks["fused"] = (t_s[ok], r.fused[ok])
        for source, name in (("one_frame", "cameras_1frame"), ("five_frames", "cameras_5frames")):
            rows = [(s.stamp_ns, s.estimates[source]) for s in r.samples
                    if s.estimates.get(source) is not None]
            if rows:
                rows.sort(key=lambda row: row[0])
                tracks[name] = (np.array([row[0] for row in rows]) * 1e-9,
                                np.array([row[1] for row in rows]))
        for name, (stamps, poses) in tracks.items():
            path = run_dir / f"{name}.tum"
            write_tum_planar(path, np.asarray(stamps), np.asarray(poses))
            written.append(path)
    return written


# --------------------------------------------------------------------------------------------
# experiments 2 and 3: correction feedback through the robot bridge (Sec. IV-B end, IV-D)
# --------------------------------------------------------------------------------------------

SUCCESS = "success"
WP_NOT_REACHED = "wp_not_reached"
EMERGENCY_STOP = "emergency_stop"


@dataclasses.dataclass(frozen=True)
class FailureModel:
    """When a run of experiment 3 fails (docs/simulation.md, "Robustness"): the robot drives
    by its internal localization, so it truly stands at the plan shifted by the localization
    error. "WP not reached": on arrival at a waypoint that shift exceeds
    ``waypoint_tolerance_m``; "emergency stop": the true footprint (radius ``footprint_m``)
    touches an obstacle or a wall."""

    waypoint_tolerance_m: float
    footprint_m: float


@dataclasses.dataclass(frozen=True)
class AppliedCorrection:
    """A pose the bridge pushed to the robot: when (s since run start), whether the robot took
    it, whether the plan was static then and at the correction's stamp, and the offset (m)."""

    t_s: float
    accepted: bool
    static_now: bool
    static_at_stamp: bool
    offset_m: float


@dataclasses.dataclass
class FeedbackRun:
    """One run with or without correction feedback.

    ``stamps_ns`` (N,), ``ground_truth`` / ``robot`` / ``fused`` (N, 3) as in
    :class:`RunResult` (the run may end early on a failure). ``outcome``: ``success``,
    ``wp_not_reached`` or ``emergency_stop`` (always ``success`` without a failure model);
    ``failure_distance_m``: travelled distance at the failure.
    """

    name: str
    route: str
    feedback: bool
    stamps_ns: np.ndarray
    ground_truth: np.ndarray
    robot: np.ndarray
    fused: np.ndarray
    corrections: list[AppliedCorrection]
    outcome: str
    failure_waypoint: str | None
    failure_distance_m: float
    travelled_m: float
    simulated_s: float
    wall_s: float
    bridge_counters: dict[str, int]
    #: (K, 4) every fused pose the pipeline published: stamp_ns, x, y, theta (what the bridge
    #: and the mapper service receive)
    published_fused: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros((0, 4)))

    def robot_rms_m(self) -> float:
        """RMS translation error (m) of the robot's internal localization over the run."""
        return rms(translation_errors(self.ground_truth[:, :2], self.robot[:, :2]))

    def fused_rms_m(self) -> float:
        """RMS translation error (m) of the fused trajectory (NaN rows skipped)."""
        ok = np.all(np.isfinite(self.fused), axis=1)
        if not np.any(ok):
            return math.nan
        return rms(translation_errors(self.ground_truth[ok, :2], self.fused[ok, :2]))


def run_feedback(scenario: Scenario, route: str, feedback: bool,
                 seed: int | np.random.SeedSequence, *, name: str | None = None,
                 fusion_factory: FusionFactory | None = None,
                 pipeline_config: PipelineConfig | None = None,
                 failure: FailureModel | None = None, fused_trajectory_step: int = 4,
                 world: World | None = None,
                 detector: DetectionSimulator | None = None) -> FeedbackRun:
    """Simulate one run of ``route`` with (``feedback=True``) or without correction feedback.

    The simulated messages go in arrival order through the backend's :class:`BackendPipeline`
    (``pipeline_config``, default :func:`paper_pipeline_config`), as in :func:`run_once`. With
    feedback, the real :class:`robot_bridge.bridge.RobotBridge` (the site's thresholds) gets the
    robot's odometry and localization through a :class:`SimRobotAdapter` and the fused poses the
    pipeline publishes (camera-only estimates without fusion), as the bridge service does; the
    corrections it decides on are pushed to
    the simulated robot, which takes them only while static. ``failure``: end the run at the
    first failure (experiment 3).
    """
    from robot_bridge.adapters.sim import SimRobotAdapter
    from robot_bridge.bridge import BridgeConfig, Outbox, RobotBridge

    wall0 = time.perf_counter()
    site = scenario.site
    sim = SimulationRun(scenario, route, False, seed=seed, world=world, detector=detector)
    robot = sim.robot
    world_ = sim.world
    run_name = name or f"{route}_{'fb' if feedback else 'nofb'}"
    if pipeline_config is None:
        # the simulator's own error model unless a rendering detector stands in for it
        mode = "noise" if detector is None or type(detector) is DetectionSimulator else "cnn"
        pipeline_config = paper_pipeline_config(site, scenario=scenario, detections=mode)
    pipeline = BackendPipeline(site, pipeline_config,
                               fusion_factory=fusion_factory,
                               with_fusion=fusion_factory is not None)
    bridge = RobotBridge(BridgeConfig.from_site(site, scenario.robot_id)) if feedback else None
    adapter = SimRobotAdapter(robot) if feedback else None
    start_ns = scenario.start_stamp_ns
    corrections: list[AppliedCorrection] = []
    arrived: set[int] = set()
    state: dict[str, object] = {"outcome": SUCCESS, "wp": None, "dist": math.nan}
    published: list[tuple[float, float, float, float]] = []

    def push(box: Outbox) -> None:
        """Corrections decided on an estimate go to the robot the one way the bridge has."""
        assert bridge is not None and adapter is not None
        before, t_now = robot.corrections_applied, robot.t_s
        bridge.apply(adapter, box)
        for k, corr in enumerate(box.corrections):
            record(corr, k < robot.corrections_applied - before, t_now)

    def record(corr: object, accepted: bool, t_now: float) -> None:
        stamp = int(corr.stamp_ns)  # type: ignore[attr-defined]
        corrections.append(AppliedCorrection(
            t_s=t_now, accepted=accepted, static_now=sim.plan.is_static(t_now),
            static_at_stamp=sim.plan.is_static((stamp - start_ns) * 1e-9),
            offset_m=float(corr.offset_m)))  # type: ignore[attr-defined]

    def check_failure(t_s: float) -> None:
        if failure is None or state["outcome"] != SUCCESS:
            return
        gt = robot.ground_truth()
        err = robot.localization_pose()[:2] - gt[:2]
        # the navigation stack follows the plan in its believed frame: truly it is off by -err
        if world_.footprint_collides(gt[:2] - err, failure.footprint_m):
            state.update(outcome=EMERGENCY_STOP, dist=robot.travelled_m, wp=None)
            return
        stop = sim.plan.stop_at(t_s)
        if stop is not None and stop.index > 0 and stop.index not in arrived:
            arrived.add(stop.index)
            if float(np.hypot(*err)) > failure.waypoint_tolerance_m:
                state.update(outcome=WP_NOT_REACHED, dist=robot.travelled_m, wp=stop.waypoint)

    for tm in sim.messages(on_step=check_failure if failure is not None else None,
                           localization_rate_hz=LOCALIZATION_RATE_HZ):
        if state["outcome"] != SUCCESS:
            break
        msg = tm.message
        out = pipeline.step(msg, tm.arrival_ns)
        published.extend((float(f.stamp_ns), f.x, f.y, f.theta) for f in out.fused)
        if bridge is None or adapter is None:
            continue
        if isinstance(msg, Odometry):
            adapter.feed([msg])
            before = robot.corrections_applied
            t_now = robot.t_s
            box = bridge.pump(adapter, tm.arrival_ns)
            for k, corr in enumerate(box.corrections):
                record(corr, k < robot.corrections_applied - before, t_now)
        # what the bridge service subscribes to: the fused pose, or without a pose graph the
        # camera-only estimates (--correction-source cameras)
        for est in out.fused if fusion_factory is not None else out.camera:
            push(bridge.on_pose_estimate(est, tm.arrival_ns))

    fusion = pipeline.tracks[scenario.robot_id].fusion
    stamps, gt, loc = sim.log.arrays()
    fused = np.full_like(gt, np.nan)
    if fusion is not None:
        step = max(1, fused_trajectory_step)
        for i in range(0, len(stamps), step):
            p = _to_pose(fusion.pose_at(int(stamps[i])))
            if p is not None:
                fused[i] = p
    return FeedbackRun(
        name=run_name, route=route, feedback=feedback, stamps_ns=stamps, ground_truth=gt,
        robot=loc, fused=fused, corrections=corrections, outcome=str(state["outcome"]),
        failure_waypoint=state["wp"] if isinstance(state["wp"], str) else None,
        failure_distance_m=float(state["dist"]),  # type: ignore[arg-type]
        travelled_m=robot.travelled_m, simulated_s=robot.t_s,
        wall_s=time.perf_counter() - wall0,
        bridge_counters=dict(bridge.counters) if bridge is not None else {},
        published_fused=np.array(published, dtype=np.float64).reshape(-1, 4),
    )


def feedback_table(runs: Sequence[FeedbackRun]) -> tuple[str, dict[str, float]]:
    """Experiment 2 as Markdown: RMS translation error (cm) of the robot's localization
    without and with feedback and of the fused trajectory (mean over seeds), with the paper's
    numbers."""
    wo = [r.robot_rms_m() for r in runs if not r.feedback]
    w = [r.robot_rms_m() for r in runs if r.feedback]
    fu = [r.fused_rms_m() for r in runs if r.feedback]
    numbers = {
        "robot_without_feedback_cm": float(np.mean(wo)) * 100 if wo else math.nan,
        "robot_with_feedback_cm": float(np.mean(w)) * 100 if w else math.nan,
        "fused_cm": float(np.nanmean(fu)) * 100 if fu and np.any(np.isfinite(fu)) else math.nan,
        "seeds": len(w),
        "corrections_accepted": sum(c.accepted for r in runs for c in r.corrections),
        "corrections_while_moving": sum(c.accepted and not (c.static_now and c.static_at_stamp)
                                        for r in runs for c in r.corrections),
    }
    route = runs[0].route if runs else "?"
    length = float(np.mean([r.travelled_m for r in runs])) if runs else math.nan

    def cell(v: float) -> str:
        return "n/a" if not math.isfinite(v) else f"{v:.2f}"

    lines = [
        f"**Experiment 2** ({route}, {length:.0f} m, {numbers['seeds']} seed(s)): RMS "
        "translation error over the whole trajectory in cm.\n",
        "| Pose Estimation | measured | paper |",
        "|---|---|---|",
        f"| Robot w/o correction feedback | {cell(numbers['robot_without_feedback_cm'])} | 17.5 |",
        f"| Robot w/ correction feedback | {cell(numbers['robot_with_feedback_cm'])} | 5.51 |",
        f"| Fused (pose graph) | {cell(numbers['fused_cm'])} | 3.34 |",
        "",
        f"Corrections accepted by the robot: {numbers['corrections_accepted']}, while moving: "
        f"{numbers['corrections_while_moving']}.",
    ]
    return "\n".join(lines) + "\n", numbers


def robustness_table(runs: Sequence[FeedbackRun]) -> tuple[str, dict[str, dict[str, float]]]:
    """Table III (paper) as Markdown: per condition the runs that did not reach a waypoint,
    ended in an emergency stop, succeeded, and the mean travelled distance at failure."""
    lines = ["| | WP not reached | Emergency Stop | Success Rate | mean distance at failure (m) |",
             "|---|---|---|---|---|"]
    numbers: dict[str, dict[str, float]] = {}
    for fb, label in ((False, "w/o correction fb"), (True, "w/ correction fb")):
        rs = [r for r in runs if r.feedback == fb]
        n = len(rs)
        wp = sum(r.outcome == WP_NOT_REACHED for r in rs)
        es = sum(r.outcome == EMERGENCY_STOP for r in rs)
        ok = sum(r.outcome == SUCCESS for r in rs)
        dists = [r.failure_distance_m for r in rs if r.outcome != SUCCESS]
        mean_d = float(np.mean(dists)) if dists else math.nan
        numbers["with_feedback" if fb else "without_feedback"] = {
            "runs": n, "wp_not_reached": wp, "emergency_stop": es, "success": ok,
            "mean_failure_distance_m": mean_d,
            "mean_route_length_m": float(np.mean([r.travelled_m for r in rs if r.outcome ==
                                                  SUCCESS])) if ok else math.nan,
        }
        lines.append(f"| {label} | {wp} / {n} | {es} / {n} | {ok} / {n} | "
                     + ("–" if not dists else f"{mean_d:.1f}") + " |")
    title = ("**Table III**: robustness over repeated runs of the cluttered route "
             "(paper: w/o 3/5, 1/5, 1/5, failures after 38 m on average; w/ 0/5, 0/5, 5/5).\n\n")
    return title + "\n".join(lines) + "\n", numbers


def plot_feedback(runs: Sequence[FeedbackRun], path: Path) -> Path:
    """Fig. 7: translation error over travelled distance of the first seed's runs: robot
    without feedback, robot with feedback, fused (with-feedback run)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.5))
    wo = next((r for r in runs if not r.feedback), None)
    w = next((r for r in runs if r.feedback), None)
    for r, label, colour in ((wo, "robot w/o correction feedback", "tab:red"),
                             (w, "robot w/ correction feedback", "tab:blue")):
        if r is None:
            continue
        dist = travelled_distance(r.ground_truth[:, :2])
        ax.plot(dist, translation_errors(r.ground_truth[:, :2], r.robot[:, :2]) * 100,
                color=colour, lw=1, label=label)
    if w is not None:
        ok = np.all(np.isfinite(w.fused), axis=1)
        if np.any(ok):
            dist = travelled_distance(w.ground_truth[:, :2])
            ax.plot(dist[ok], translation_errors(w.ground_truth[ok, :2], w.fused[ok, :2]) * 100,
                    color="tab:green", lw=1, label="fused")
        for c in w.corrections:
            if c.accepted:
                i = int(np.clip(np.searchsorted(w.stamps_ns, w.stamps_ns[0] + c.t_s * 1e9), 0,
                                len(w.stamps_ns) - 1))
                ax.axvline(travelled_distance(w.ground_truth[:, :2])[i], color="0.8", lw=0.6,
                           zorder=0)
    ax.set_xlabel("travelled distance [m]")
    ax.set_ylabel("translation error [cm]")
    ax.set_title("Experiment 2: with and without pose correction feedback (grey: corrections)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def failure_model(scenario: Scenario) -> FailureModel:
    """The scenario's failure model (``robustness:``) with the robot model's footprint."""
    rc = scenario.robustness
    radius = scenario.site.robot_model(scenario.robot_id).footprint_radius_m
    return FailureModel(rc.waypoint_tolerance_m, radius + rc.collision_margin_m)


def run_experiment4(sc: Scenario, config: PaperConfig, factory: FusionFactory | None,
                    world: World, detector: DetectionSimulator, out: Path,
                    say: Callable[[str], None]) -> tuple[str, list[Path]]:
    """Experiment 4 (:mod:`smartedge.mapping_experiment`): the static cameras' clouds, then
    the robot's exploration route (``config.mapping_route``, the same seed without and with
    feedback) with its head camera's clouds, into the backend's semantic map."""
    from smartedge.mapping_experiment import (
        MappingExperimentConfig,
        mapping_markdown,
        run_mapping,
    )

    route = config.mapping_route
    seed = run_seed(sc, route, False, 0, config.seed)
    say(f"paper experiment 4: semantic mapping, the static cameras then {route} (without and "
        f"with feedback for the consistency comparison)")

    def run_route(feedback: bool) -> FeedbackRun:
        r = run_feedback(sc, route, feedback, seed,
                         name=f"{route}_map_{'fb' if feedback else 'nofb'}",
                         fusion_factory=factory, world=world, detector=detector,
                         pipeline_config=paper_pipeline_config(
                             sc.site, scenario=sc, detections=config.detections),
                         fused_trajectory_step=config.fused_trajectory_step)
        say(f"[exp4] {r.name}: robot RMS {r.robot_rms_m() * 100:.1f} cm, fused "
            f"{r.fused_rms_m() * 100:.1f} cm, {r.simulated_s:.0f} s simulated in "
            f"{r.wall_s:.1f} s")
        return r

    mcfg = MappingExperimentConfig(route=route, seed=config.seed, threads=config.threads,
                                   robot_cloud_rate_hz=config.mapping_cloud_rate_hz)
    report = run_mapping(sc, mcfg, out, run_route=run_route, say=say)
    return mapping_markdown(report), report.files


def run_experiment2(sc: Scenario, config: PaperConfig, factory: FusionFactory | None,
                    world: World, detector: DetectionSimulator,
                    say: Callable[[str], None]) -> list[FeedbackRun]:
    """Experiment 2: ``config.long_route`` without and with feedback, per seed (the same seed
    for both, so the two runs differ only by the feedback)."""
    runs: list[FeedbackRun] = []
    total = 2 * config.feedback_seeds
    for k in range(config.feedback_seeds):
        seed = run_seed(sc, config.long_route, False, k, config.seed)
        for fb in (False, True):
            r = run_feedback(sc, config.long_route, fb, seed,
                             name=f"{config.long_route}_{'fb' if fb else 'nofb'}_{k + 1}",
                             fusion_factory=factory, world=world, detector=detector,
                             pipeline_config=paper_pipeline_config(
                                 sc.site, scenario=sc, detections=config.detections),
                             fused_trajectory_step=config.fused_trajectory_step)
            runs.append(r)
            say(f"[exp2 {len(runs)}/{total}] {r.name}: robot RMS {r.robot_rms_m() * 100:.1f} cm"
                f", fused {r.fused_rms_m() * 100:.1f} cm, "
                f"{sum(c.accepted for c in r.corrections)} corrections, "
                f"{r.simulated_s:.0f} s simulated in {r.wall_s:.1f} s")
    return runs


def run_experiment3(sc: Scenario, config: PaperConfig, factory: FusionFactory | None,
                    world: World, detector: DetectionSimulator,
                    say: Callable[[str], None]) -> list[FeedbackRun]:
    """Experiment 3: ``robustness.runs`` runs without, then as many with feedback, each with
    its own seed (iterations 0..n-1 without, n..2n-1 with)."""
    n = config.robustness_runs or sc.robustness.runs
    model = failure_model(sc)
    runs: list[FeedbackRun] = []
    for k in range(2 * n):
        fb = k >= n
        r = run_feedback(sc, config.robustness_route, fb,
                         run_seed(sc, config.robustness_route, False, k, config.seed),
                         name=f"{config.robustness_route}_{'fb' if fb else 'nofb'}_{k % n + 1}",
                         fusion_factory=factory, failure=model, world=world,
                         detector=detector,
                         pipeline_config=paper_pipeline_config(
                             sc.site, scenario=sc, detections=config.detections),
                         fused_trajectory_step=config.fused_trajectory_step)
        runs.append(r)
        where = "" if r.outcome == SUCCESS else (
            f" after {r.failure_distance_m:.1f} m"
            + (f" at {r.failure_waypoint}" if r.failure_waypoint else ""))
        say(f"[exp3 {k + 1}/{2 * n}] {r.name}: {r.outcome}{where} "
            f"({r.travelled_m:.1f} m, {r.wall_s:.1f} s)")
    return runs


# --------------------------------------------------------------------------------------------
# side-by-side comparison of finished runs (smartedge evaluate compare)
# --------------------------------------------------------------------------------------------

#: the paper's figures (ICRA 2023, Table I average row / per camera count, Table II, exp. 2/3)
PAPER_FIGURES: dict[str, str] = {
    "Robot (avg)": "19.1 cm / 1.11°",
    "Cameras (raw), 1 cam": "13.8 cm / 3.39°",
    "Cameras (raw), 2 cams": "2.59 cm / 0.97°",
    "Cameras (raw), 4 cams": "2.88 cm / 1.02°",
    "Cameras (5 frames), 1 cam": "7.77 cm",
    "Cameras (5 frames), >= 2 cams": "2.58 cm / 0.86°",
    "Fused (avg)": "2.93 cm / 0.88°",
    "Table II Fused Avg.": "n/a",
    "Exp. 2 robot w/o / w/ feedback": "17.5 / 5.51 cm",
    "Exp. 2 fused": "3.34 cm",
    "Table III w/ feedback success": "5 / 5",
}


def _cell_cm_deg(group: dict[str, float] | None) -> str:
    if not group or not group.get("count"):
        return "n/a"
    return f"{group['t_mean_cm']:.2f} cm / {group['r_mean_deg']:.2f}°"


def _multi_camera(t1: dict[str, dict[str, dict[str, float]]], source: str) -> str:
    """Mean over the 2- and 4-camera groups, weighted by their counts."""
    groups = [t1.get(source, {}).get(k) for k in ("2", "4")]
    groups = [g for g in groups if g and g.get("count")]
    n = sum(g["count"] for g in groups)
    if not n:
        return "n/a"
    t = sum(g["t_mean_cm"] * g["count"] for g in groups) / n
    r = sum(g["r_mean_deg"] * g["count"] for g in groups) / n
    return f"{t:.2f} cm / {r:.2f}°"


def compare_rows(run_dir: str | Path) -> dict[str, str]:
    """The comparison rows of one finished ``evaluate paper`` output folder."""
    folder = Path(run_dir)
    rows: dict[str, str] = {}
    res_path = folder / "results.json"
    if res_path.exists():
        res = json.loads(res_path.read_text(encoding="utf-8"))
        t1, t2 = res.get("table1", {}), res.get("table2", {})
        rows["Robot (avg)"] = _cell_cm_deg(t1.get("robot", {}).get("average"))
        for n, label in (("1", "1 cam"), ("2", "2 cams"), ("4", "4 cams")):
            rows[f"Cameras (raw), {label}"] = _cell_cm_deg(t1.get("raw", {}).get(n))
        for src, name in (("one_frame", "Cameras (1 frame)"), ("five_frames",
                                                                "Cameras (5 frames)")):
            rows[f"{name}, 1 cam"] = _cell_cm_deg(t1.get(src, {}).get("1"))
            rows[f"{name}, >= 2 cams"] = _multi_camera(t1, src)
        rows["Fused, >= 2 cams"] = _multi_camera(t1, "fused")
        rows["Fused (avg)"] = _cell_cm_deg(t1.get("fused", {}).get("average"))
        avg = t2.get("fused", {}).get("average")
        rows["Table II Fused Avg."] = "n/a" if avg is None else f"{avg:.2f} cm"
    fb_path = folder / "feedback_results.json"
    if fb_path.exists():
        fb = json.loads(fb_path.read_text(encoding="utf-8"))
        e2 = fb.get("experiment2") or {}
        if e2:
            rows["Exp. 2 robot w/o / w/ feedback"] = (
                f"{e2['robot_without_feedback_cm']:.1f} / {e2['robot_with_feedback_cm']:.1f} cm")
            rows["Exp. 2 fused"] = f"{e2['fused_cm']:.2f} cm"
        e3 = (fb.get("experiment3") or {}).get("with_feedback")
        if e3:
            rows["Table III w/ feedback success"] = f"{e3['success']} / {e3['runs']}"
    return rows


def compare_markdown(runs: Sequence[tuple[str, str | Path]], with_paper: bool = True) -> str:
    """A Markdown table with one column per ``(name, folder)`` of finished runs (and the
    paper's figures), one row per headline figure."""
    columns = [(name, compare_rows(folder)) for name, folder in runs]
    order: list[str] = []
    for _, rows in columns:
        order += [k for k in rows if k not in order]
    head = ["figure", *(["paper"] if with_paper else []), *(name for name, _ in columns)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for key in order:
        cells = [key, *([PAPER_FIGURES.get(key, "")] if with_paper else []),
                 *(rows.get(key, "") for _, rows in columns)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
