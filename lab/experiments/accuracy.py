"""Experiment 1 of ``smartedge evaluate paper``: the accuracy of the pose estimates (Sec. IV-B,
Table I/II, Fig. 6) on the simulated lab.

For each trajectory, direction and iteration (paper: 3 x 2 x 3 = 18 runs) the simulation's
messages (detections, odometry, the robot's own localization) go in arrival order through the
backend's one pipeline (:class:`backend_service.pipeline.BackendPipeline`, the object the
backend service runs), set up for the paper's protocol
(:func:`~lab.experiments.config.paper_pipeline_config`: prior = the robot's localization,
camera estimates fused as the averages taken while static). At every waypoint, once the robot
has been static for ``dwell_s``, one sample per pose source is taken:

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

Outputs (:func:`write_experiment1`): ``table1.md``, ``table2.md``, ``nees.md``,
``results.json``, ``samples.csv``, the Fig. 6 plots and per-run TUM files.
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
from typing import TYPE_CHECKING

import numpy as np

from backend_service.estimate import estimate_pose
from backend_service.frame_set import FrameSet
from backend_service.pipeline import BackendPipeline, FusionFactory, PipelineOutput
from core.site import Site
from lab.evaluation.metrics import (
    MeanStd,
    align_planar,
    group_by_camera_count,
    heading_errors,
    rms,
    translation_errors,
    travelled_distance,
)
from lab.experiments.config import (
    LOCALIZATION_RATE_HZ,
    PaperConfig,
    make_detector,
    paper_pipeline_config,
    pose_array,
)
from lab.experiments.parallel import map_runs, resolve_jobs
from simulation.detections import DetectionSimulator
from simulation.runner import SimulationRun, run_seed
from simulation.scenario import Scenario
from simulation.world import World

if TYPE_CHECKING:  # the rendering detection source is imported only in CNN mode
    from lab.rendered_detections import RenderedStats

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
FUSION_UNAVAILABLE = "fusion not available"


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


def run_once(scenario: Scenario, trajectory: str, reverse: bool, iteration: int,
             config: PaperConfig, fusion_factory: FusionFactory | None,
             world: World | None = None,
             detector: DetectionSimulator | None = None,
             service_site: Site | None = None) -> RunResult:
    """Simulate one run and take the per-stop samples (see the module docstring).

    The simulated messages go in arrival order through :class:`BackendPipeline` (the backend
    service's own object) exactly as the service receives them. The raw row is an ablation on
    the pipeline's own record: the stop's first frame-set, from the prior the pipeline used,
    solved with the single-camera heuristic off. ``service_site``: the site file the backend
    is given (default: the scenario's); the simulated cameras stay the scenario's true ones
    (:func:`simulation.detections.true_cameras`), so another calibration of the same cameras
    can be compared (``smartedge evaluate calibration``)."""
    wall0 = time.perf_counter()
    site = scenario.site if service_site is None else service_site
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
                sample.estimates["one_frame"] = pose_array(rec.result.pose)
                _keep_covariance(sample, "one_frame", rec.result.estimate)
                # the ablations: the same frame-set from the same prior, other treatments
                for name, solver in ablations.items():
                    res = estimate_pose(rec.frame_set, site, rec.prior, solver,
                                        rec.prior_covariance)
                    sample.estimates[name] = pose_array(res.pose) if res.ok else None
                    _keep_covariance(sample, name, res.estimate)
            if rec.averaged is not None and "five_frames" not in sample.estimates:
                sample.estimates["five_frames"] = pose_array(rec.averaged)
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
            p = pose_array(fusion.pose_at(int(stamps[i])))
            if p is not None:
                fused[i] = p
        for s in samples.values():
            at = fusion.pose_at(int(s.stamp_ns))
            s.estimates["fused"] = pose_array(at)
            _keep_covariance(s, "fused", at)
    ordered = [samples[k] for k in sorted(samples)]
    return RunResult(
        name=name, trajectory=trajectory, reverse=reverse, iteration=iteration,
        samples=ordered, stamps_ns=stamps, ground_truth=gt, robot=loc, fused=fused,
        simulated_s=sim.duration_s, wall_s=time.perf_counter() - wall0, counters=counters,
    )


@dataclasses.dataclass(frozen=True)
class PlannedRun:
    """One run of experiment 1: the draw of the cameras' calibration error, the trajectory,
    its direction and the iteration (the run's seed follows from these and the base seed)."""

    calibration_seed: int
    trajectory: str
    reverse: bool
    iteration: int


class Experiment1Worker:
    """What a process needs for experiment 1's runs: the scenario, the settings and the pose
    graph factory; the world and a detection source per calibration draw are built on first
    use (``world`` and ``detector``, the scenario's own draw, may be handed in)."""

    def __init__(self, scenario: Scenario, config: PaperConfig,
                 fusion_factory: FusionFactory | None, world: World | None = None,
                 detector: DetectionSimulator | None = None,
                 service_site: Site | None = None) -> None:
        self.scenario = scenario
        self.service_site = service_site
        self.config = config
        self.fusion_factory = fusion_factory
        self.world = world or World(scenario)
        self.detectors: dict[int, DetectionSimulator] = (
            {} if detector is None else {scenario.seeds.calibration: detector})

    def detector(self, calibration_seed: int) -> DetectionSimulator:
        """The detection source of one draw of the cameras' calibration error."""
        det = self.detectors.get(calibration_seed)
        if det is None:
            sc = self.scenario
            if calibration_seed != sc.seeds.calibration:
                sc = sc.with_overrides(
                    seeds=dataclasses.replace(sc.seeds, calibration=calibration_seed))
            det = self.detectors[calibration_seed] = make_detector(sc, self.world, self.config)
        return det

    def run(self, planned: PlannedRun) -> tuple[RunResult, RenderedStats | None]:
        """One run (:func:`run_once`) and, for a rendering detection source, the work it did
        (its ``stats`` counters over this run, which add up with ``+``)."""
        det = self.detector(planned.calibration_seed)
        stats: RenderedStats | None = getattr(det, "stats", None)
        before = dataclasses.replace(stats) if stats is not None else None
        res = run_once(self.scenario, planned.trajectory, planned.reverse, planned.iteration,
                       self.config, self.fusion_factory, self.world, det, self.service_site)
        if self.config.calibration_seeds:
            res = _with_suffix(res, f"_cal{planned.calibration_seed}")
        return res, (None if stats is None or before is None else stats - before)


def run_pose_accuracy(scenario: Scenario, trajectories: Sequence[str], config: PaperConfig,
                    fusion_factory: FusionFactory | None, world: World,
                    detector: DetectionSimulator, say: Callable[[str], None],
                    service_site: Site | None = None) -> list[RunResult]:
    """Experiment 1: each of ``trajectories`` in both directions, ``config.runs_per_direction``
    times (:func:`run_once`), for each of ``config.calibration_seeds`` (a detector per draw of
    the cameras' calibration error; without them the scenario's one draw, ``detector``).

    The runs are independent: with ``config.jobs`` > 1 they go to that many worker processes
    (:mod:`lab.experiments.parallel`), each building its own world and detection source,
    and come back in the planned order; the results are those of the serial run.
    ``service_site``: the site file the backend is given instead of the scenario's
    (:func:`run_once`)."""
    cal_seeds = config.calibration_seeds or (scenario.seeds.calibration,)
    plan = [PlannedRun(cs, n, rev, it) for cs in cal_seeds for n in trajectories
            for rev in (False, True) for it in range(config.runs_per_direction)]
    jobs = resolve_jobs(config.jobs, len(plan), (scenario, config, fusion_factory,
                                                 service_site))
    say(f"paper experiment 1: {len(plan)} runs on {scenario.name} "
        f"({'with' if fusion_factory is not None else 'without'} fusion"
        + (f", calibration seeds {','.join(map(str, cal_seeds))}"
           if config.calibration_seeds else "")
        + (f", {jobs} processes" if jobs > 1 else "") + ")")
    # workers build their own world and detection source; in this process, the given ones
    state_args: tuple[object, ...] = (
        (scenario, config.per_process(jobs), fusion_factory, None, None, service_site)
        if jobs > 1 else (scenario, config, fusion_factory, world, detector, service_site))
    results: list[RunResult] = []
    images: RenderedStats | None = None
    runs = map_runs(Experiment1Worker.run, plan, jobs, Experiment1Worker, state_args)
    for k, (res, stats) in enumerate(runs, start=1):
        results.append(res)
        say(f"[{k}/{len(plan)}] {res.name}: {res.simulated_s:.0f} s simulated in "
            f"{res.wall_s:.1f} s ({res.simulated_s / max(res.wall_s, 1e-9):.0f}x), "
            f"{len(res.samples)} stops, {res.counters['frame_sets']} frame-sets")
        if stats is not None:
            images = stats if images is None else images + stats
            say(f"  images so far: {images.line()}")
    return results


def _with_suffix(res: RunResult, suffix: str) -> RunResult:
    """``res`` renamed (runs of several calibration draws keep distinct names and files)."""
    name = res.name + suffix
    return dataclasses.replace(res, name=name, samples=[dataclasses.replace(s, run=name)
                                                        for s in res.samples])


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


def accuracy_by_camera_count(results: Sequence[RunResult], fusion_available: bool,
                             align: bool = False,
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


def rms_by_trajectory(results: Sequence[RunResult], fusion_available: bool,
                      align: bool = False) -> tuple[str, dict[str, dict[str, float]]]:
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


@dataclasses.dataclass(frozen=True)
class AccuracyTables:
    """Experiment 1's tables as Markdown and the numbers behind them (``results.json``).

    ``table1``: {source: {camera count or ``"average"``: {``t_mean_cm``, ``t_std_cm``,
    ``r_mean_deg``, ``r_std_deg``, ``count``}}}; ``table2``: {source: {trajectory or
    ``"average"``: RMS translation error, cm}}; ``nees``: {source: {camera count or ``"all"``:
    mean NEES, ``n_<group>``: samples}}.
    """

    table1_markdown: str
    table1: dict[str, dict[str, dict[str, float]]]
    table2_markdown: str
    table2: dict[str, dict[str, float]]
    nees_markdown: str
    nees: dict[str, dict[str, float]]
    fusion_available: bool


def accuracy_tables(results: Sequence[RunResult], fusion_available: bool, align: bool = False,
                    ) -> AccuracyTables:
    """Table I, Table II and the NEES table of ``results``."""
    t1_md, t1 = accuracy_by_camera_count(results, fusion_available, align)
    t2_md, t2 = rms_by_trajectory(results, fusion_available, align)
    nees_md, nees = nees_table(results)
    return AccuracyTables(table1_markdown=t1_md, table1=t1, table2_markdown=t2_md, table2=t2,
                          nees_markdown=nees_md, nees=nees, fusion_available=fusion_available)


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


def write_experiment1(out: Path, scenario: Scenario, config: PaperConfig,
                      results: Sequence[RunResult], tables: AccuracyTables,
                      detector: DetectionSimulator) -> list[Path]:
    """Write experiment 1's tables, ``results.json``, ``samples.csv`` (every sample: world
    frame, metres and radians), the Fig. 6 plots and the runs' TUM files into ``out``."""
    files = [out / "table1.md", out / "table2.md", out / "results.json", out / "samples.csv",
             out / "fig6_map.png", out / "nees.md"]
    files[0].write_text(tables.table1_markdown, encoding="utf-8")
    files[1].write_text(tables.table2_markdown, encoding="utf-8")
    files[2].write_text(json.dumps({
        "scenario": scenario.name, "runs": len(results), "seed": config.seed,
        "align": config.align, "fusion_available": tables.fusion_available,
        "table1": tables.table1, "table2": tables.table2, "nees": tables.nees,
        "simulated_s": sum(r.simulated_s for r in results),
    }, indent=2, default=float), encoding="utf-8")
    files[5].write_text(tables.nees_markdown, encoding="utf-8")
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
    plot_map(scenario, detector, files[4])
    files += plot_runs(results, scenario, out)
    files += write_run_trajectories(results, out / "tum")
    return files


def write_run_trajectories(results: Sequence[RunResult], folder: Path) -> list[Path]:
    """TUM files per run (``<folder>/<run>/``): ``ground_truth``, ``robot`` (its own
    localization) and ``fused`` over the whole run, and the camera estimates at the stops
    (``cameras_1frame``, ``cameras_5frames``), for evo or ``smartedge evaluate ate``."""
    from core.trajectory import write_tum_planar

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
