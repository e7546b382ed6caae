"""The paper's pose-accuracy experiments (Sec. IV-B) on the simulated lab.

For each trajectory, direction and iteration (paper: 3 x 2 x 3 = 18 runs) the simulation streams
detections and odometry in arrival order through the backend's own pieces: the frame-set
synchronizer, the pose solver with and without the single-camera heuristic, the multi-frame
averager and (when available) the pose-graph fusion. At every waypoint, once the robot has been
static for ``dwell_s``, one sample per pose source is taken:

- Robot: the robot's internal localization (no corrections are fed back, as in the paper);
- Cameras (raw): the first frame-set's estimate without the single-camera heuristic;
- Cameras (1 frame): the same frame-set with the heuristic (prior = internal localization);
- Cameras (5 frames): the average of the first ``frames`` frame-sets (with the heuristic);
- Fused: the pose graph's smoothed pose at that stamp (after the run).

Table I groups the errors by the number of cameras that see the waypoint; Table II is the RMS
translation error over whole trajectories (Robot, Fused). The ground truth is the simulation's
true pose, in the same world frame, so no alignment is needed; ``align=True`` applies the
paper's per-run Procrustes (SE(2)) alignment anyway.

Fusion is pluggable: ``PaperConfig.fusion_factory`` builds a :class:`FusionBackend` per run
(``robot_id`` → object with ``add_odometry``, ``add_camera_estimate``, ``pose_at``). The default
uses :class:`backend_service.fusion.PoseGraphFusion` when it can be imported; otherwise the
Fused row says "fusion not available".
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
from typing import Protocol

import numpy as np

from backend_service.frame_set import FrameSet, PlanarPose
from backend_service.metrics import (
    MeanStd,
    align_planar,
    group_by_camera_count,
    heading_errors,
    rms,
    translation_errors,
    travelled_distance,
)
from protocol.messages import Odometry, PoseEstimate, RobotDetections
from simulation.detections import DetectionSimulator
from simulation.runner import SimulationRun, run_seed
from simulation.scenario import PAPER_SCENARIO, Scenario, load_scenario
from simulation.world import World

log = logging.getLogger(__name__)

SOURCES = ("robot", "raw", "one_frame", "five_frames", "fused")
ROW_NAMES = {
    "robot": "Robot",
    "raw": "Cameras (raw)",
    "one_frame": "Cameras (1 frame)",
    "five_frames": "Cameras (5 frames)",
    "fused": "Fused",
}
CAMERA_GROUPS = (1, 2, 4)
FUSION_UNAVAILABLE = "fusion not available"


class FusionBackend(Protocol):
    """What the experiment needs from a fusion: feed odometry and camera estimates in arrival
    order, then query smoothed poses. ``pose_at`` returns (3,) (x, y, theta), a
    :class:`protocol.PoseEstimate`, or ``None`` where it has no pose."""

    def add_odometry(self, msg: Odometry) -> object: ...

    def add_camera_estimate(self, est: PoseEstimate) -> object: ...

    def pose_at(self, stamp_ns: int) -> object: ...


FusionFactory = Callable[[str], FusionBackend]


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


def run_once(scenario: Scenario, trajectory: str, reverse: bool, iteration: int,
             config: PaperConfig, fusion_factory: FusionFactory | None,
             world: World | None = None,
             detector: DetectionSimulator | None = None) -> RunResult:
    """Simulate one run and take the per-stop samples (see the module docstring)."""
    from backend_service.estimate import SolverConfig, estimate_pose
    from backend_service.multi_frame import MultiFrameAverager
    from backend_service.sync import FrameSetSynchronizer

    wall0 = time.perf_counter()
    site = scenario.site
    robot_id = scenario.robot_id
    sim = SimulationRun(scenario, trajectory, reverse,
                        seed=run_seed(scenario, trajectory, reverse, iteration, config.seed),
                        world=world, detector=detector)
    name = f"{trajectory}{'r' if reverse else ''}_{iteration + 1}"
    sync = FrameSetSynchronizer(site, robot_id)
    fusion = fusion_factory(robot_id) if fusion_factory is not None else None
    raw_cfg = SolverConfig(use_single_camera_heuristic=False)
    one_cfg = SolverConfig(use_single_camera_heuristic=True)
    start_ns = scenario.start_stamp_ns
    per_stop: dict[int, dict[str, object]] = {}
    counters = {"frame_sets": 0, "solved": 0, "failed": 0}
    samples: dict[int, StopSample] = {}

    def localization_at(stamp_ns: int) -> np.ndarray:
        stamps = sim.log.stamps_ns
        i = max(bisect.bisect_right(stamps, stamp_ns) - 1, 0)
        return sim.log.localization[i]

    def handle(fs: FrameSet) -> None:
        counters["frame_sets"] += 1
        t_s = (fs.stamp_ns - start_ns) * 1e-9
        stop = sim.plan.stop_at(t_s)
        if stop is None or t_s < stop.t0_s + config.dwell_s:
            return
        state = per_stop.setdefault(stop.index, {"n": 0, "avg": MultiFrameAverager(
            config.frames), "done": False})
        if state["done"] or not fs.observations:
            return
        loc = localization_at(fs.stamp_ns)
        prior = PlanarPose(float(loc[0]), float(loc[1]), float(loc[2]))
        sample = samples.get(stop.index)
        if sample is None:
            sample = StopSample(
                run=name, trajectory=trajectory, waypoint=stop.waypoint,
                num_cameras=len(sim.stop_cameras[stop.index]), stamp_ns=fs.stamp_ns,
                ground_truth=np.asarray(sim.ground_truth_at(fs.stamp_ns)[0]),
                estimates={"robot": loc.copy()},
            )
            samples[stop.index] = sample
        one = estimate_pose(fs, site, prior, one_cfg)
        counters["solved" if one.ok else "failed"] += 1
        if one.ok and "one_frame" not in sample.estimates:
            raw = estimate_pose(fs, site, prior, raw_cfg)
            sample.estimates["raw"] = _to_pose(raw.pose) if raw.ok else None
            sample.estimates["one_frame"] = _to_pose(one.pose)
        averaged = state["avg"].add(one)  # type: ignore[union-attr]
        state["n"] = int(state["n"]) + 1  # type: ignore[call-overload]
        if averaged is not None and averaged.ok:
            sample.estimates["five_frames"] = _to_pose(averaged.pose)
            state["done"] = True
            if fusion is not None and averaged.estimate is not None:
                fusion.add_camera_estimate(averaged.estimate)
        elif int(state["n"]) >= 4 * config.frames:  # type: ignore[call-overload]
            state["done"] = True  # too few consistent frames at this stop

    for tm in sim.messages():
        msg = tm.message
        if isinstance(msg, Odometry):
            if fusion is not None:
                fusion.add_odometry(msg)
        elif isinstance(msg, RobotDetections):
            for fs in sync.push(msg, tm.arrival_ns):
                handle(fs)
    for fs in sync.flush():
        handle(fs)

    stamps, gt, loc = sim.log.arrays()
    fused = np.full_like(gt, np.nan)
    if fusion is not None:
        step = max(1, config.fused_trajectory_step)
        for i in range(0, len(stamps), step):
            p = _to_pose(fusion.pose_at(int(stamps[i])))
            if p is not None:
                fused[i] = p
        for s in samples.values():
            s.estimates["fused"] = _to_pose(fusion.pose_at(int(s.stamp_ns)))
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
    world = World(sc)
    detector = DetectionSimulator(sc, world)
    plan = [(n, rev, it) for n in names for rev in (False, True)
            for it in range(config.runs_per_direction)]
    say(f"paper experiment: {len(plan)} runs on {sc.name} "
        f"({'with' if fusion_available else 'without'} fusion)")
    results: list[RunResult] = []
    for k, (n, rev, it) in enumerate(plan, start=1):
        res = run_once(sc, n, rev, it, config, factory, world, detector)
        results.append(res)
        say(f"[{k}/{len(plan)}] {res.name}: {res.simulated_s:.0f} s simulated in "
            f"{res.wall_s:.1f} s ({res.simulated_s / max(res.wall_s, 1e-9):.0f}x), "
            f"{len(res.samples)} stops, {res.counters['frame_sets']} frame-sets")
    t1_md, t1 = table1(results, fusion_available, config.align)
    t2_md, t2 = table2(results, fusion_available, config.align)
    files = [out / "table1.md", out / "table2.md", out / "results.json", out / "samples.csv",
             out / "fig6_map.png"]
    files[0].write_text(t1_md, encoding="utf-8")
    files[1].write_text(t2_md, encoding="utf-8")
    files[2].write_text(json.dumps({
        "scenario": sc.name, "runs": len(results), "seed": config.seed, "align": config.align,
        "fusion_available": fusion_available, "table1": t1, "table2": t2,
        "simulated_s": sum(r.simulated_s for r in results),
    }, indent=2, default=float), encoding="utf-8")
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
    wall = time.perf_counter() - wall0
    sim_total = sum(r.simulated_s for r in results)
    say(f"done: {sim_total:.0f} s simulated in {wall:.1f} s; wrote {out}")
    return PaperReport(results, t1_md, t2_md, t1, t2, fusion_available, files, wall)
