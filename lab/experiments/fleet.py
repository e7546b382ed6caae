"""``smartedge evaluate fleet``: identical robots crossing paths, through the real per-robot
pipeline, each scored against the same robot driving its route alone (issue #30 item 5).

With ``types`` (``--types``) the fleet has two robot types (:data:`simulation.fleet.MIXED_FLEET`:
two HSR-like robots passing each other and a box base crossing their lanes) and every
detection names its robot's type, as an edge running each type's detector reports it; the
same fleet is then driven again with the types stripped (an untyped edge) as the comparison.

A run drives the robots of :data:`simulation.fleet.CROSSING_ROUTES` (the first ``robots`` of
them) on the paper lab (:mod:`simulation.fleet`: one camera image of all robots, detections
merged and stripped of their robot id) through the backend's
:class:`~backend_service.pipeline.BackendPipeline` (the object ``smartedge backend`` runs: the
detections go to robots by :class:`~backend_service.detection_router.DetectionRouter`) with
correction feedback as experiment 2 of ``evaluate paper`` does it: one real
:class:`robot_bridge.bridge.RobotBridge` per robot decides corrections from that robot's fused
poses and pushes them to its simulated robot, which takes them only while static. Then each
robot drives alone: a site with only that robot, the same seed (same motion, drift and
detection noise), the same pipeline and bridge.

Scores (per run; :class:`FleetRunResult`):

* wrong-robot detections: detections the router gave to a robot they are not (the simulation
  knows the truth of every detection);
* wrong-robot corrections: corrections pushed to robot A decided on an estimate whose data
  holds a detection of another robot (A's first frame-set with one, and everything after it
  in A's pose graph, counts), or whose pose lies nearer another robot's true position than
  A's own;
* identity switches: per robot, how often the true robot nearest to its published estimates
  (camera and fused) changes (starting from the robot itself);
* wrong-type detections: wrong-robot detections given to a robot of another type;
* unassigned, ambiguous and no-prediction detections (the router's counters);
* per robot: RMS translation error (ATE) of the fused trajectory, of the camera estimates and
  of the robot's own localization, in the fleet and alone, and the ratio fleet / alone (the
  target: <= 1.10).

Poses are ``(x, y, theta)`` in the world frame (metres, radians).
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from backend_service.pipeline import BackendPipeline
from backend_service.pipeline_config import PipelineConfig
from lab.evaluation.metrics import rms, translation_errors
from lab.evaluation.scoring import wrong_robot_corrections
from lab.experiments.config import LOCALIZATION_RATE_HZ, paper_pipeline_config, pose_array
from protocol.messages import Odometry, PoseCorrection, RobotDetections
from simulation.fleet import (
    CROSSING_ROUTES,
    FleetRun,
    alone_run,
    fleet_routes,
    fleet_run,
    fleet_site,
    fleet_spec,
)
from simulation.scenario import Scenario, load_scenario

log = logging.getLogger(__name__)

#: the issue's target: per-robot ATE in the fleet within 10 % of the robot driving alone
ATE_RATIO_TARGET = 1.10
#: simulated seconds of ``--quick`` (the three robots' closest approaches are at 7-10 s)
QUICK_UNTIL_S = 12.0
#: frame-set stamps within this of a wrongly assigned detection's stamp hold it (ns)
_STAMP_MATCH_NS = 1_000_000


@dataclasses.dataclass(frozen=True)
class FleetConfig:
    """``robots``: how many of :data:`CROSSING_ROUTES` drive (2 or 3); ``runs``: seeds
    ``seed``, ``seed + 1``, ...; ``until_s``: simulated seconds (default: until the shortest
    route ends); ``feedback``: correction feedback through the robot bridges;
    ``min_sigma_xy_m``: a floor on every robot's predicted position uncertainty (default: the
    site's association settings; larger: vaguer predictions, more detections left ambiguous);
    ``types``: two robot types (the last robot a box base, :func:`simulation.fleet.fleet_spec`),
    typed detections, and the same fleet untyped as the comparison."""

    robots: int = 3
    runs: int = 1
    seed: int = 3
    until_s: float | None = None
    feedback: bool = True
    min_sigma_xy_m: float | None = None
    types: bool = False

    def __post_init__(self) -> None:
        if not 1 <= self.robots <= len(CROSSING_ROUTES):
            raise ValueError(f"fleet: robots must be 1..{len(CROSSING_ROUTES)} "
                             f"(the crossing routes), got {self.robots}")
        if self.runs < 1:
            raise ValueError(f"fleet: runs must be >= 1, got {self.runs}")
        if self.until_s is not None and not self.until_s > 0:
            raise ValueError(f"fleet: until_s must be > 0, got {self.until_s}")
        if self.min_sigma_xy_m is not None and not self.min_sigma_xy_m > 0:
            raise ValueError(f"fleet: min_sigma_xy_m must be > 0, got {self.min_sigma_xy_m}")
        if self.types and self.robots < 2:
            raise ValueError("fleet: --types needs 2 or 3 robots (an HSR and a box base)")

    def pipeline_config(self, fleet: FleetRun) -> PipelineConfig:
        """The paper's protocol with the noise model's error model (as ``evaluate paper``
        experiment 2), the association floor of ``min_sigma_xy_m`` when given."""
        scenario = next(iter(fleet.runs.values())).scenario
        config = paper_pipeline_config(fleet.site, scenario=scenario, detections="noise")
        if self.min_sigma_xy_m is None:
            return config
        return dataclasses.replace(config, association=dataclasses.replace(
            config.association, min_sigma_xy_m=self.min_sigma_xy_m))

    def models(self) -> dict[str, str]:
        """Robot id → robot model of the fleet."""
        return fleet_spec(self.robots, self.types)

    def routes(self) -> dict[str, tuple[tuple[float, float, float], ...]]:
        return {rid: tuple(pts) for rid, pts in fleet_routes(list(self.models())).items()}


@dataclasses.dataclass
class Drive:
    """What one drive (the fleet, or one robot alone) did, per robot: ``camera`` (K, 4) and
    ``fused`` (K, 4) published estimates (stamp_ns, x, y, theta); ``trajectory`` (N, 3) the
    pose graph at the odometry stamps ``stamps_ns`` (NaN before it had one); ``truth`` /
    ``localization`` (N, 3) at those stamps; ``corrections`` pushed to the robot with whether
    it took them."""

    stamps_ns: dict[str, np.ndarray]
    truth: dict[str, np.ndarray]
    localization: dict[str, np.ndarray]
    trajectory: dict[str, np.ndarray]
    camera: dict[str, np.ndarray]
    fused: dict[str, np.ndarray]
    corrections: dict[str, list[tuple[PoseCorrection, bool]]]
    wrong_detections: collections.Counter[str]
    contaminated_from_ns: dict[str, int]
    counters: dict[str, int]
    wall_s: float
    #: per robot: the wrong-robot detections it got from a robot of another model
    wrong_type: collections.Counter[str] = dataclasses.field(
        default_factory=collections.Counter)

    def fused_rms_m(self, rid: str) -> float:
        tr = self.trajectory[rid]
        ok = np.all(np.isfinite(tr), axis=1)
        if not np.any(ok):
            return math.nan
        return rms(translation_errors(self.truth[rid][ok, :2], tr[ok, :2]))

    def robot_rms_m(self, rid: str) -> float:
        return rms(translation_errors(self.truth[rid][:, :2], self.localization[rid][:, :2]))


def _estimates_rms_m(fleet: FleetRun, rid: str, est: np.ndarray) -> float:
    if len(est) == 0:
        return math.nan
    gt = fleet.runs[rid].ground_truth_at(est[:, 0].astype(np.int64))
    return rms(translation_errors(gt[:, :2], est[:, 1:3]))


def drive(fleet: FleetRun, feedback: bool, config: PipelineConfig | None = None,
          fused_step: int = 4) -> Drive:
    """``fleet``'s messages in arrival order through one :class:`BackendPipeline` (the site's
    robots; ``config`` default: the paper's protocol with the noise model's error model), with
    one :class:`RobotBridge` per robot deciding corrections when ``feedback``."""
    from robot_bridge.adapters.sim import SimRobotAdapter
    from robot_bridge.bridge import BridgeConfig, Outbox, RobotBridge

    wall0 = time.perf_counter()
    site = fleet.site
    scenario = next(iter(fleet.runs.values())).scenario
    pipeline = BackendPipeline(
        site, config or paper_pipeline_config(site, scenario=scenario, detections="noise"))
    ids = list(fleet.runs)
    bridges = {rid: RobotBridge(BridgeConfig.from_site(site, rid)) for rid in ids}
    adapters = {rid: SimRobotAdapter(fleet.runs[rid].robot) for rid in ids}
    camera: dict[str, list[tuple[float, ...]]] = {rid: [] for rid in ids}
    fused: dict[str, list[tuple[float, ...]]] = {rid: [] for rid in ids}
    corrections: dict[str, list[tuple[PoseCorrection, bool]]] = {rid: [] for rid in ids}
    wrong: collections.Counter[str] = collections.Counter()
    wrong_type: collections.Counter[str] = collections.Counter()
    #: per robot: corrected stamps of the images from which it got another robot's detection
    bad: dict[str, list[tuple[str, int]]] = collections.defaultdict(list)
    contaminated: dict[str, int] = {}

    def push(rid: str, box: Outbox) -> None:
        robot = fleet.runs[rid].robot
        before = robot.corrections_applied
        bridges[rid].apply(adapters[rid], box)
        record(rid, box, before)

    def record(rid: str, box: Outbox, before: int) -> None:
        took = fleet.runs[rid].robot.corrections_applied - before
        for k, corr in enumerate(box.corrections):
            corrections[rid].append((corr, k < took))

    for tm in fleet.messages(LOCALIZATION_RATE_HZ):
        msg = tm.message
        out = pipeline.step(msg, tm.arrival_ns)
        if (isinstance(msg, RobotDetections) and msg.detections
                and pipeline.router is not None and pipeline.router.last is not None):
            cam = site.cameras[msg.camera_id]
            stamp = int(msg.stamp_ns) + int(cam.clock_offset_ns)
            for outcome, true_id in zip(pipeline.router.last.outcomes, fleet.truth[id(msg)],
                                        strict=True):
                if outcome.used and outcome.robot_id != true_id:
                    wrong[outcome.robot_id] += 1
                    if site.robots[outcome.robot_id] != site.robots[true_id]:
                        wrong_type[outcome.robot_id] += 1
                    bad[outcome.robot_id].append((msg.camera_id, stamp))
        for solve in out.solves:
            rid = solve.robot_id
            if solve.result.ok and bad.get(rid) and any(
                    o.camera_id == c and abs(o.stamp_ns - s) <= _STAMP_MATCH_NS
                    for o in solve.frame_set.observations for c, s in bad[rid]):
                contaminated[rid] = min(contaminated.get(rid, solve.frame_set.stamp_ns),
                                        solve.frame_set.stamp_ns)
        for est in out.camera:
            camera[est.robot_id].append((est.stamp_ns, est.x, est.y, est.theta))
        for est in out.fused:
            fused[est.robot_id].append((est.stamp_ns, est.x, est.y, est.theta))
        if not feedback:
            continue
        if isinstance(msg, Odometry) and msg.robot_id in adapters:
            rid = msg.robot_id
            adapters[rid].feed([msg])
            before = fleet.runs[rid].robot.corrections_applied
            record(rid, bridges[rid].pump(adapters[rid], tm.arrival_ns), before)
        # what each robot's bridge subscribes to: its own robot's fused pose
        for est in out.fused:
            push(est.robot_id, bridges[est.robot_id].on_pose_estimate(est, tm.arrival_ns))

    stamps: dict[str, np.ndarray] = {}
    truth: dict[str, np.ndarray] = {}
    loc: dict[str, np.ndarray] = {}
    traj: dict[str, np.ndarray] = {}
    for rid in ids:
        s, gt, lo = fleet.runs[rid].log.arrays()
        stamps[rid], truth[rid], loc[rid] = s, gt, lo
        tr = np.full_like(gt, np.nan)
        fusion = pipeline.tracks[rid].fusion
        if fusion is not None:
            for i in range(0, len(s), max(1, fused_step)):
                p = pose_array(fusion.pose_at(int(s[i])))
                if p is not None:
                    tr[i] = p
        traj[rid] = tr
    return Drive(stamps, truth, loc, traj,
                 {r: np.array(v, dtype=np.float64).reshape(-1, 4) for r, v in camera.items()},
                 {r: np.array(v, dtype=np.float64).reshape(-1, 4) for r, v in fused.items()},
                 corrections, wrong, contaminated, dict(pipeline.counter_snapshot()),
                 time.perf_counter() - wall0, wrong_type)


@dataclasses.dataclass(frozen=True)
class RobotScore:
    """One robot of one run: ATEs (m) in the fleet and alone, identity and corrections."""

    robot_id: str
    fused_rms_m: float
    camera_rms_m: float
    robot_rms_m: float
    alone_fused_rms_m: float
    alone_camera_rms_m: float
    alone_robot_rms_m: float
    camera_estimates: int
    alone_camera_estimates: int
    identity_switches: int
    estimates_nearer_other: int
    wrong_detections: int
    corrections: int
    corrections_accepted: int
    wrong_corrections: int
    #: the robot's model, and the wrong-robot detections it got from another model's robot
    model: str = "hsr"
    wrong_type_detections: int = 0

    @property
    def fused_ratio(self) -> float:
        return _ratio(self.fused_rms_m, self.alone_fused_rms_m)

    @property
    def camera_ratio(self) -> float:
        return _ratio(self.camera_rms_m, self.alone_camera_rms_m)


def _ratio(a: float, b: float) -> float:
    return a / b if math.isfinite(a) and math.isfinite(b) and b > 0 else math.nan


@dataclasses.dataclass(frozen=True)
class FleetRunResult:
    """One seed: per-robot scores, the router's counters, the closest approach (distance m,
    time s, robots) of the true paths, the true trajectories (for the figure), wall time."""

    seed: int
    until_s: float
    robots: Mapping[str, RobotScore]
    assigned: int
    ambiguous: int
    unassigned: int
    no_prediction: int
    closest: tuple[float, float, str, str]
    truth_xy: Mapping[str, np.ndarray]
    wall_s: float
    #: the two closest robots' true positions then
    closest_xy: Mapping[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    #: detections that named their robot's model; typed detections of a model no robot has
    typed: bool = True
    unknown_model: int = 0
    #: a typed mixed fleet: the same seed driven with the types stripped (the comparison)
    untyped: FleetRunResult | None = None

    @property
    def wrong_type_detections(self) -> int:
        return sum(r.wrong_type_detections for r in self.robots.values())

    @property
    def identity_switches(self) -> int:
        return sum(r.identity_switches for r in self.robots.values())

    @property
    def wrong_detections(self) -> int:
        return sum(r.wrong_detections for r in self.robots.values())

    @property
    def wrong_corrections(self) -> int:
        return sum(r.wrong_corrections for r in self.robots.values())

    def summary(self) -> dict[str, object]:
        return {
            "seed": self.seed, "until_s": self.until_s, "wall_s": self.wall_s,
            "typed": self.typed,
            "identity_switches": self.identity_switches,
            "wrong_detections": self.wrong_detections,
            "wrong_type_detections": self.wrong_type_detections,
            "wrong_corrections": self.wrong_corrections,
            "assigned": self.assigned, "ambiguous": self.ambiguous,
            "unassigned": self.unassigned, "no_prediction": self.no_prediction,
            "unknown_model": self.unknown_model,
            "closest_m": self.closest[0], "closest_t_s": self.closest[1],
            "closest_robots": list(self.closest[2:]),
            "robots": {rid: {**dataclasses.asdict(r), "fused_ratio": r.fused_ratio,
                             "camera_ratio": r.camera_ratio}
                       for rid, r in self.robots.items()},
            **({"untyped": self.untyped.summary()} if self.untyped is not None else {}),
        }


def identity_score(fleet: FleetRun, rid: str, estimates: np.ndarray) -> tuple[int, int]:
    """(switches, estimates nearer another robot) of ``rid``'s estimates (K, 4) in stamp
    order: the true robot nearest each one, and how often that changes (from ``rid``)."""
    if len(estimates) == 0 or len(fleet.runs) == 1:
        return 0, 0
    est = estimates[np.argsort(estimates[:, 0], kind="stable")]
    stamps = est[:, 0].astype(np.int64)
    ids = list(fleet.runs)
    dist = np.stack([translation_errors(fleet.runs[r].ground_truth_at(stamps)[:, :2],
                                        est[:, 1:3]) for r in ids], axis=1)
    nearest = np.argmin(dist, axis=1)
    own = ids.index(rid)
    labels = np.concatenate([[own], nearest])
    return int(np.count_nonzero(np.diff(labels))), int(np.count_nonzero(nearest != own))


def count_wrong_corrections(fleet: FleetRun, rid: str, dr: Drive) -> int:
    """Corrections pushed to ``rid`` decided on data holding another robot's detection, or
    placing it nearer another robot than itself."""
    return wrong_robot_corrections(
        [corr for corr, _took in dr.corrections[rid]],
        lambda stamp_ns, robot: np.asarray(fleet.true_pose(robot, stamp_ns)), list(fleet.runs),
        tainted_from_ns=dr.contaminated_from_ns.get(rid))


def run_fleet_once(config: FleetConfig, seed: int, scenario: Scenario | None = None,
                   say: Callable[[str], None] = lambda s: None) -> FleetRunResult:
    """One seed: the fleet, then each robot alone (module docstring); with ``config.types``
    also the fleet untyped (:attr:`FleetRunResult.untyped`)."""
    wall0 = time.perf_counter()
    scenario = scenario or load_scenario()
    routes = config.routes()
    site = fleet_site(config.models())
    fleet = fleet_run(routes, until_s=config.until_s, seed=seed, site=site, scenario=scenario)
    closest = fleet.min_distance()
    kinds = ", ".join(f"{r} ({m})" for r, m in config.models().items())
    say(f"[seed {seed}] {len(routes)} robots {kinds}, {fleet.until_s:.0f} s simulated, closest "
        f"approach {closest[0]:.2f} m ({closest[2]}/{closest[3]} at {closest[1]:.1f} s)")
    dr = drive(fleet, config.feedback, config.pipeline_config(fleet))
    say(f"[seed {seed}] fleet driven in {dr.wall_s:.1f} s"
        + (" (typed detections)" if config.types else ""))
    alone: dict[str, tuple[FleetRun, Drive]] = {}
    for rid in routes:
        run = alone_run(fleet, rid, scenario)
        alone_fleet = FleetRun(run.scenario.site, {rid: run}, fleet.until_s, seed)
        alone[rid] = (alone_fleet,
                      drive(alone_fleet, config.feedback, config.pipeline_config(alone_fleet)))
    result = _score(fleet, dr, alone, closest, say, time.perf_counter() - wall0)
    if not config.types:
        return result
    t1 = time.perf_counter()
    bare = fleet_run(routes, until_s=config.until_s, seed=seed, site=site, scenario=scenario,
                     typed=False)
    du = drive(bare, config.feedback, config.pipeline_config(bare))
    say(f"[seed {seed}] the same fleet untyped (types stripped) driven in {du.wall_s:.1f} s")
    untyped = _score(bare, du, alone, closest, say, time.perf_counter() - t1)
    return dataclasses.replace(result, untyped=untyped,
                               wall_s=time.perf_counter() - wall0)


def _score(fleet: FleetRun, dr: Drive, alone: Mapping[str, tuple[FleetRun, Drive]],
           closest: tuple[float, float, str, str], say: Callable[[str], None], wall_s: float
           ) -> FleetRunResult:
    """A drive of ``fleet`` scored per robot against its drive alone."""
    seed = fleet.seed
    tag = "" if fleet.typed else " untyped"
    scores: dict[str, RobotScore] = {}
    for rid in fleet.runs:
        alone_fleet, da = alone[rid]
        sw_c, near_c = identity_score(fleet, rid, dr.camera[rid])
        sw_f, near_f = identity_score(fleet, rid, dr.fused[rid])
        corr = dr.corrections[rid]
        scores[rid] = RobotScore(
            robot_id=rid, fused_rms_m=dr.fused_rms_m(rid),
            camera_rms_m=_estimates_rms_m(fleet, rid, dr.camera[rid]),
            robot_rms_m=dr.robot_rms_m(rid),
            alone_fused_rms_m=da.fused_rms_m(rid),
            alone_camera_rms_m=_estimates_rms_m(alone_fleet, rid, da.camera[rid]),
            alone_robot_rms_m=da.robot_rms_m(rid),
            camera_estimates=len(dr.camera[rid]), alone_camera_estimates=len(da.camera[rid]),
            identity_switches=sw_c + sw_f, estimates_nearer_other=near_c + near_f,
            wrong_detections=int(dr.wrong_detections[rid]),
            corrections=len(corr), corrections_accepted=sum(t for _, t in corr),
            wrong_corrections=count_wrong_corrections(fleet, rid, dr),
            model=fleet.model_of(rid), wrong_type_detections=int(dr.wrong_type[rid]))
        s = scores[rid]
        say(f"[seed {seed}{tag}] {rid} ({s.model}): fused {s.fused_rms_m * 100:.2f} cm (alone "
            f"{s.alone_fused_rms_m * 100:.2f} cm, x{s.fused_ratio:.3f}), camera "
            f"{s.camera_rms_m * 100:.2f} cm (alone {s.alone_camera_rms_m * 100:.2f} cm), "
            f"{s.identity_switches} switches, {s.wrong_detections} wrong-robot detections "
            f"({s.wrong_type_detections} of another type), {s.wrong_corrections} wrong "
            f"corrections ({da.wall_s:.1f} s alone)")
    c = dr.counters
    return FleetRunResult(
        seed=seed, until_s=fleet.until_s, robots=scores,
        assigned=int(c.get("association.detections_assigned", 0)),
        ambiguous=int(c.get("association.detections_ambiguous", 0)),
        unassigned=int(c.get("association.detections_unassigned", 0)),
        no_prediction=int(c.get("association.detections_no_prediction", 0)),
        closest=closest,
        truth_xy={rid: dr.truth[rid][:, :2] for rid in fleet.runs},
        wall_s=wall_s,
        closest_xy={rid: (float(xy[0]), float(xy[1])) for rid in closest[2:] if rid
                    for xy in [fleet.runs[rid].plan.pose_at(np.array([closest[1]]))[0, :2]]},
        typed=fleet.typed,
        unknown_model=int(c.get("association.detections_unknown_model", 0)))


def run_fleet(config: FleetConfig, scenario: Scenario | None = None,
              say: Callable[[str], None] = lambda s: None) -> list[FleetRunResult]:
    """``config.runs`` seeds, one after the other."""
    scenario = scenario or load_scenario()
    return [run_fleet_once(config, config.seed + k, scenario, say) for k in range(config.runs)]


def _cm(v: float) -> str:
    return "n/a" if not math.isfinite(v) else f"{v * 100:.2f}"


def _x(v: float) -> str:
    return "n/a" if not math.isfinite(v) else f"{v:.3f}"


def fleet_table(results: Sequence[FleetRunResult]) -> tuple[str, dict[str, object]]:
    """The report's tables (Markdown) and the headline numbers: per robot (mean over seeds)
    ATE fleet / alone, worst ratio, and the identity figures summed over seeds; a typed mixed
    fleet: the same for its untyped comparison (``numbers["untyped"]``) and a table of both."""
    ids = list(results[0].robots)
    models = {rid: results[0].robots[rid].model for rid in ids}
    numbers = _identity_numbers(results)
    numbers["closest_m"] = min(r.closest[0] for r in results)
    mixed = len(set(models.values())) > 1
    who = (f"{len(ids)} robots of {len(set(models.values()))} types "
           f"({', '.join(f'{r}: {m}' for r, m in models.items())}), detections "
           f"{'typed' if results[0].typed else 'untyped'}"
           if mixed else f"{len(ids)} identical robots ({', '.join(ids)})")
    lines = [
        f"{who}, {len(results)} seed(s), {results[0].until_s:.0f} s simulated each; closest "
        f"approach {numbers['closest_m']:.2f} m.",
        "",
        "| | identity switches | wrong-robot detections | of another type | wrong-robot "
        "corrections | assigned | ambiguous | unassigned | no prediction |",
        "|---|---|---|---|---|---|---|---|---|",
        _identity_row("all seeds", numbers),
        "",
        "Per robot, mean over seeds: RMS translation error (cm) in the fleet and driving alone "
        f"(same seed), and the ratio (target <= {ATE_RATIO_TARGET:.2f}).",
        "",
        "| robot | model | fused fleet | fused alone | ratio | camera fleet | camera alone | "
        "ratio | own localization fleet | alone | corrections (taken) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    worst = 0.0
    per: dict[str, dict[str, float]] = {}
    for rid in ids:
        rs = [r.robots[rid] for r in results]

        def mean(attr: str, rs: list[RobotScore] = rs) -> float:
            v = [getattr(s, attr) for s in rs]
            v = [x for x in v if math.isfinite(x)]
            return float(np.mean(v)) if v else math.nan

        f, fa = mean("fused_rms_m"), mean("alone_fused_rms_m")
        c, ca = mean("camera_rms_m"), mean("alone_camera_rms_m")
        fr, cr = _ratio(f, fa), _ratio(c, ca)
        worst = max(worst, *(x for x in (fr, cr) if math.isfinite(x)), 0.0)
        per[rid] = {"fused_cm": f * 100, "alone_fused_cm": fa * 100, "fused_ratio": fr,
                    "camera_cm": c * 100, "alone_camera_cm": ca * 100, "camera_ratio": cr}
        lines.append(
            f"| {rid} | {models[rid]} | {_cm(f)} | {_cm(fa)} | {_x(fr)} | {_cm(c)} | {_cm(ca)} | "
            f"{_x(cr)} | "
            f"{_cm(mean('robot_rms_m'))} | {_cm(mean('alone_robot_rms_m'))} | "
            f"{sum(s.corrections for s in rs)} ({sum(s.corrections_accepted for s in rs)}) |")
    numbers["per_robot"] = per
    numbers["worst_ratio"] = worst
    numbers["target_met"] = bool(
        numbers["identity_switches"] == 0 and numbers["wrong_corrections"] == 0
        and worst <= ATE_RATIO_TARGET)
    lines += ["", f"Worst ratio {worst:.3f} (target <= {ATE_RATIO_TARGET:.2f}): target "
              f"{'met' if numbers['target_met'] else 'NOT met'}."]
    bare = [r.untyped for r in results if r.untyped is not None]
    if bare:
        un = _identity_numbers(bare)
        worst_untyped = _worst_ratio(bare)
        un["worst_ratio"] = worst_untyped
        un["per_robot"] = {rid: {
            "fused_ratio": _ratio(*_means(bare, rid, "fused_rms_m", "alone_fused_rms_m")),
            "camera_ratio": _ratio(*_means(bare, rid, "camera_rms_m", "alone_camera_rms_m")),
            "camera_cm": _means(bare, rid, "camera_rms_m", "camera_rms_m")[0] * 100}
            for rid in ids}
        numbers["untyped"] = un
        lines += [
            "", "The same fleet with the types stripped (an untyped edge: every detection a "
            "candidate for every robot with as many keypoints), same seeds:", "",
            "| detections | identity switches | wrong-robot detections | of another type | "
            "wrong-robot corrections | assigned | ambiguous | unassigned | no prediction | "
            "worst ATE ratio |",
            "|---|---|---|---|---|---|---|---|---|---|",
            _identity_row("typed", numbers) + f" {_x(worst)} |",
            _identity_row("untyped", un) + f" {_x(worst_untyped)} |",
        ]
    return "\n".join(lines) + "\n", numbers


def _identity_numbers(results: Sequence[FleetRunResult]) -> dict[str, object]:
    """The identity figures and the router's counters summed over seeds."""
    return {
        "seeds": len(results),
        "identity_switches": sum(r.identity_switches for r in results),
        "wrong_detections": sum(r.wrong_detections for r in results),
        "wrong_type_detections": sum(r.wrong_type_detections for r in results),
        "wrong_corrections": sum(r.wrong_corrections for r in results),
        "assigned": sum(r.assigned for r in results),
        "ambiguous": sum(r.ambiguous for r in results),
        "unassigned": sum(r.unassigned for r in results),
        "no_prediction": sum(r.no_prediction for r in results),
        "unknown_model": sum(r.unknown_model for r in results),
    }


def _identity_row(name: str, n: Mapping[str, object]) -> str:
    return (f"| {name} | {n['identity_switches']} | {n['wrong_detections']} | "
            f"{n['wrong_type_detections']} | {n['wrong_corrections']} | {n['assigned']} | "
            f"{n['ambiguous']} | {n['unassigned']} | {n['no_prediction']} |")


def _means(results: Sequence[FleetRunResult], rid: str, a: str, b: str
           ) -> tuple[float, float]:
    """Means over seeds (finite values) of two :class:`RobotScore` fields of ``rid``."""
    out = []
    for attr in (a, b):
        v = [getattr(r.robots[rid], attr) for r in results]
        v = [x for x in v if math.isfinite(x)]
        out.append(float(np.mean(v)) if v else math.nan)
    return out[0], out[1]


def _worst_ratio(results: Sequence[FleetRunResult]) -> float:
    ratios = [_ratio(*_means(results, rid, a, b)) for rid in results[0].robots
              for a, b in (("fused_rms_m", "alone_fused_rms_m"),
                           ("camera_rms_m", "alone_camera_rms_m"))]
    return max([x for x in ratios if math.isfinite(x)], default=math.nan)


def plot_routes(result: FleetRunResult, scenario: Scenario, path: Path) -> Path:
    """Top-down figure of one seed: the room, obstacles, cameras, every robot's true path and
    the closest approach."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    fig, ax = plt.subplots(figsize=(8, 5.2))
    lo, hi = scenario.room_min_xy_m, scenario.room_max_xy_m
    ax.plot([lo[0], hi[0], hi[0], lo[0], lo[0]], [lo[1], lo[1], hi[1], hi[1], lo[1]],
            color="0.3", lw=1)
    for box in scenario.obstacles:
        c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
        hx, hy = box.size_m[0] / 2, box.size_m[1] / 2
        corners = [(box.center_xy_m[0] + c * u - s * v, box.center_xy_m[1] + s * u + c * v)
                   for u, v in ((-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy))]
        ax.add_patch(Polygon(corners, closed=True, color="0.85"))
    for cid, cam in scenario.site.cameras.items():
        p = cam.position_world
        ax.plot(p[0], p[1], "k^", ms=6)
        ax.annotate(cid, (p[0], p[1]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    for rid, xy in result.truth_xy.items():
        line, = ax.plot(xy[:, 0], xy[:, 1], lw=1.5, label=rid)
        ax.plot(xy[0, 0], xy[0, 1], "o", color=line.get_color(), ms=5)
    d, t, a, b = result.closest
    if a and b:
        for rid in (a, b):
            x, y = result.closest_xy[rid]
            ax.plot(x, y, "x", color="red", ms=9, mew=2)
        ax.set_title(f"Fleet (seed {result.seed}): closest approach {d:.2f} m "
                     f"({a}/{b} at {t:.1f} s, red x)")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_report(results: Sequence[FleetRunResult], scenario: Scenario, out: Path,
                 config: FleetConfig) -> tuple[Path, dict[str, object]]:
    """``out``/report.md (tables, figure), fleet_results.json and fleet_routes.png."""
    out.mkdir(parents=True, exist_ok=True)
    table, numbers = fleet_table(results)
    fig = plot_routes(results[0], scenario, out / "fleet_routes.png")
    feedback = "with" if config.feedback else "without"
    title = ("two robot types crossing paths" if config.types
             else "identical robots crossing paths")
    text = (f"# Fleet: {title}\n\n"
            "Every robot's detections reach the backend merged per camera image, without a "
            "robot id; the backend's pipeline assigns them (issue #30 item 1), "
            f"{feedback} correction feedback through one robot bridge per robot. Each robot "
            "is also driven alone (same seed, same route) for the ATE ratio."
            + (" Each detection names its robot's type (a typed edge); the comparison drives "
               "the same fleet with the types stripped." if config.types else "")
            + (f" Predictions no sharper than {config.min_sigma_xy_m:g} m (a stress test)."
               if config.min_sigma_xy_m is not None else "") + "\n\n"
            + table + f"\n![routes]({fig.name})\n")
    (out / "report.md").write_text(text)
    (out / "fleet_results.json").write_text(json.dumps(
        {"config": dataclasses.asdict(config), "numbers": numbers,
         "runs": [r.summary() for r in results]}, indent=2, default=float))
    return out / "report.md", numbers
