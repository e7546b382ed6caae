"""Experiments 2 and 3 of ``smartedge evaluate paper``: correction feedback through the robot
bridge (Sec. IV-B end, Fig. 7) and robustness over repeated runs (Sec. IV-D, Table III).

A run (:func:`run_feedback`) drives a route through the backend's one pipeline, as experiment 1
does; with feedback, the real :class:`robot_bridge.bridge.RobotBridge` decides on corrections
from the published poses and pushes them to the simulated robot, which takes them only while
static. Experiment 2 (:func:`run_correction_feedback`) compares the robot's own localization
without and with feedback over ``PaperConfig.long_route``; experiment 3 (:func:`run_robustness`)
counts the runs of ``PaperConfig.robustness_route`` that fail (:class:`FailureModel`). Poses are
``(x, y, theta)`` in the world frame (metres, radians).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np

from backend_service.pipeline import BackendPipeline, FusionFactory
from backend_service.pipeline_config import PipelineConfig
from lab.evaluation.metrics import rms, translation_errors, travelled_distance
from lab.experiments.comparison import (
    PAPER_EXP2_FUSED_CM,
    PAPER_EXP2_ROBOT_WITH_FEEDBACK_CM,
    PAPER_EXP2_ROBOT_WITHOUT_FEEDBACK_CM,
    PAPER_TABLE3_FAILURE_DISTANCE_M,
    paper_table3_outcomes,
)
from lab.experiments.config import (
    LOCALIZATION_RATE_HZ,
    PaperConfig,
    make_detector,
    paper_pipeline_config,
    pose_array,
)
from lab.experiments.parallel import map_runs, resolve_jobs
from protocol.messages import Odometry
from simulation.detections import DetectionSimulator
from simulation.runner import SimulationRun, run_seed
from simulation.scenario import Scenario
from simulation.world import World

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
    :class:`~lab.experiments.accuracy.RunResult` (the run may end early on a failure).
    ``outcome``: ``success``, ``wp_not_reached`` or ``emergency_stop`` (always ``success``
    without a failure model); ``failure_distance_m``: travelled distance at the failure.
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
    (``pipeline_config``, default :func:`paper_pipeline_config`), as in
    :func:`~lab.experiments.accuracy.run_once`. With feedback, the real
    :class:`robot_bridge.bridge.RobotBridge` (the site's thresholds) gets the robot's odometry
    and localization through a :class:`SimRobotAdapter` and the fused poses the pipeline
    publishes (camera-only estimates without fusion), as the bridge service does; the
    corrections it decides on are pushed to the simulated robot, which takes them only while
    static. ``failure``: end the run at the first failure (experiment 3).
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
            p = pose_array(fusion.pose_at(int(stamps[i])))
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
        f"| Robot w/o correction feedback | {cell(numbers['robot_without_feedback_cm'])} | "
        f"{PAPER_EXP2_ROBOT_WITHOUT_FEEDBACK_CM:g} |",
        f"| Robot w/ correction feedback | {cell(numbers['robot_with_feedback_cm'])} | "
        f"{PAPER_EXP2_ROBOT_WITH_FEEDBACK_CM:g} |",
        f"| Fused (pose graph) | {cell(numbers['fused_cm'])} | {PAPER_EXP2_FUSED_CM:g} |",
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
             f"(paper: w/o {paper_table3_outcomes(False)}, failures after "
             f"{PAPER_TABLE3_FAILURE_DISTANCE_M} m on average; w/ "
             f"{paper_table3_outcomes(True)}).\n\n")
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



@dataclasses.dataclass(frozen=True)
class PlannedFeedbackRun:
    """One run of experiment 2 or 3: the route, with or without feedback, its seed and name,
    and whether it ends at the first failure (experiment 3)."""

    route: str
    feedback: bool
    seed: np.random.SeedSequence
    name: str
    stop_at_failure: bool = False


class FeedbackWorker:
    """What a process needs for the runs of experiments 2 and 3: the scenario, the settings
    and the pose graph factory; the world and the detection source are built on first use
    (or handed in)."""

    def __init__(self, scenario: Scenario, config: PaperConfig,
                 fusion_factory: FusionFactory | None, world: World | None = None,
                 detector: DetectionSimulator | None = None) -> None:
        self.scenario = scenario
        self.config = config
        self.fusion_factory = fusion_factory
        self.world = world or World(scenario)
        self._detector = detector

    @property
    def detector(self) -> DetectionSimulator:
        if self._detector is None:
            self._detector = make_detector(self.scenario, self.world, self.config)
        return self._detector

    def run(self, planned: PlannedFeedbackRun) -> FeedbackRun:
        """One run (:func:`run_feedback`) set up for the paper's protocol."""
        sc = self.scenario
        return run_feedback(
            sc, planned.route, planned.feedback, planned.seed, name=planned.name,
            fusion_factory=self.fusion_factory,
            failure=failure_model(sc) if planned.stop_at_failure else None,
            world=self.world, detector=self.detector,
            pipeline_config=paper_pipeline_config(sc.site, scenario=sc,
                                                  detections=self.config.detections),
            fused_trajectory_step=self.config.fused_trajectory_step)


def _feedback_runs(sc: Scenario, config: PaperConfig, factory: FusionFactory | None,
                   world: World, detector: DetectionSimulator,
                   plan: Sequence[PlannedFeedbackRun]) -> Iterator[FeedbackRun]:
    """The runs of ``plan`` in order, in ``config.jobs`` worker processes when more than one
    (:mod:`lab.experiments.parallel`; the results do not depend on it)."""
    jobs = resolve_jobs(config.jobs, len(plan), (sc, config, factory))
    state_args: tuple[object, ...] = (
        (sc, config.per_process(jobs), factory) if jobs > 1
        else (sc, config, factory, world, detector))
    return map_runs(FeedbackWorker.run, plan, jobs, FeedbackWorker, state_args)


def run_correction_feedback(sc: Scenario, config: PaperConfig, factory: FusionFactory | None,
                    world: World, detector: DetectionSimulator,
                    say: Callable[[str], None]) -> list[FeedbackRun]:
    """Experiment 2: ``config.long_route`` without and with feedback, per seed (the same seed
    for both, so the two runs differ only by the feedback)."""
    route = config.long_route
    plan = [PlannedFeedbackRun(route, fb, run_seed(sc, route, False, k, config.seed),
                               f"{route}_{'fb' if fb else 'nofb'}_{k + 1}")
            for k in range(config.feedback_seeds) for fb in (False, True)]
    runs: list[FeedbackRun] = []
    for r in _feedback_runs(sc, config, factory, world, detector, plan):
        runs.append(r)
        say(f"[exp2 {len(runs)}/{len(plan)}] {r.name}: robot RMS "
            f"{r.robot_rms_m() * 100:.1f} cm, fused {r.fused_rms_m() * 100:.1f} cm, "
            f"{sum(c.accepted for c in r.corrections)} corrections, "
            f"{r.simulated_s:.0f} s simulated in {r.wall_s:.1f} s")
    return runs


def run_robustness(sc: Scenario, config: PaperConfig, factory: FusionFactory | None,
                    world: World, detector: DetectionSimulator,
                    say: Callable[[str], None]) -> list[FeedbackRun]:
    """Experiment 3: ``robustness.runs`` runs without, then as many with feedback, each with
    its own seed (iterations 0..n-1 without, n..2n-1 with)."""
    n = config.robustness_runs or sc.robustness.runs
    route = config.robustness_route
    plan = [PlannedFeedbackRun(route, k >= n, run_seed(sc, route, False, k, config.seed),
                               f"{route}_{'fb' if k >= n else 'nofb'}_{k % n + 1}",
                               stop_at_failure=True)
            for k in range(2 * n)]
    runs: list[FeedbackRun] = []
    for k, r in enumerate(_feedback_runs(sc, config, factory, world, detector, plan)):
        runs.append(r)
        where = "" if r.outcome == SUCCESS else (
            f" after {r.failure_distance_m:.1f} m"
            + (f" at {r.failure_waypoint}" if r.failure_waypoint else ""))
        say(f"[exp3 {k + 1}/{2 * n}] {r.name}: {r.outcome}{where} "
            f"({r.travelled_m:.1f} m, {r.wall_s:.1f} s)")
    return runs


def run_summary(r: FeedbackRun) -> dict[str, object]:
    """One run's outcome and errors for ``feedback_results.json`` (RMS in cm)."""
    return {"name": r.name, "feedback": r.feedback, "outcome": r.outcome,
            "failure_waypoint": r.failure_waypoint, "failure_distance_m": r.failure_distance_m,
            "travelled_m": r.travelled_m, "robot_rms_cm": r.robot_rms_m() * 100,
            "fused_rms_cm": r.fused_rms_m() * 100,
            "corrections_accepted": sum(c.accepted for c in r.corrections),
            "simulated_s": r.simulated_s, "wall_s": r.wall_s}
