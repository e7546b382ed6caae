"""Experiment 4 of ``smartedge evaluate paper``: collaborative semantic mapping (Sec. III-C,
IV-C, Fig. 7-8 of the paper) on the simulated site.

1. **Static sensors alone**: every site camera renders a few RGB-D frames (its true pose, so the
   calibration error is in them) that go through the edge's segmentation network and cloud
   builder (the deployed code: :class:`edge_agent.networks.SemanticSegmenter`,
   :func:`edge_agent.semantic_cloud.build_semantic_cloud`) into the mapper's
   :class:`mapper.mapping.SemanticMapping`, which starts from the prior model of the empty room
   (floor and walls, no semantics).
2. **After the robot's exploration route**: the robot drives ``route`` with correction feedback
   (:func:`lab.experiments.feedback.run_feedback`, the backend pipeline and the robot
   bridge as in experiment 2); its head RGB-D camera, rendered at the robot's true pose, gives a
   cloud at ``robot_cloud_rate_hz`` in the base frame, placed with the fused pose, aligned by ICP
   and fused.
3. **Scores** against the renderer's ground truth (every static surface sampled with its class,
   less what nobody can see: bottoms and the floor under furniture): coverage (share of the
   surface voxels with semantic information), label accuracy of the covered ones, per class.
4. **Consistency (Fig. 7)**: each robot cloud placed with the robot's own localization, without
   and with feedback (the same route and seed), and with the fused pose, against the final
   map: fitness and inlier RMSE as placed, and the offset ICP finds.

Outputs: ``mapping.md``, ``mapping.json``, ``semantic_map_topdown.png``, ``semantic_map.npz``
and ``semantic_map.ply`` in the output folder.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from backend_service.pipeline import FusionFactory
from core.geometry import se3_from_planar, wrap_angle_array
from core.history import StampedHistory
from lab.experiments.comparison import PAPER_COVERAGE
from lab.experiments.config import PaperConfig, paper_pipeline_config
from lab.experiments.feedback import FeedbackRun, run_feedback
from mapper.alignment import align_to_map, consistency
from mapper.map_io import save_map_npz, write_map_ply
from mapper.mapping import PLACEMENTS, MappingConfig, SemanticMapping, interpolate_pose
from mapper.semantic_map import SemanticMapConfig, SemanticVoxelMap, pack_voxel_keys
from protocol.messages import PoseEstimate, SemanticCloud
from protocol.semantic_classes import (
    NO_SEMANTICS_COLOR,
    SEMANTIC_CLASS_COLORS,
    SEMANTIC_CLASS_ID,
    SEMANTIC_CLASSES,
)
from simulation.detections import DetectionSimulator
from simulation.runner import run_seed
from simulation.scenario import Scenario
from simulation.world import World

log = logging.getLogger(__name__)

#: ground-truth surface sampling: points per (spacing)^2 (several per 5 cm voxel)
GT_SPACING_M: Final = 0.02
#: what counts as agreeing with the map in the consistency measure (as placed, no ICP)
CONSISTENCY_DISTANCE_M: Final = 0.10
#: a robot cloud reaches the mapper this long after its stamp (segmentation on the robot, Wi-Fi)
CLOUD_DELAY_NS: Final = 300_000_000


@dataclasses.dataclass(frozen=True)
class MappingExperimentConfig:
    """``route``: the robot's exploration route; ``seed``: its run seed; ``frames_per_camera``:
    RGB-D frames each static camera contributes; ``robot_cloud_rate_hz``: the head camera's
    cloud rate (the paper's HSR: ~1 Hz); ``consistency_rate_hz``: clouds per second of each
    run used for the consistency comparison; ``threads``: onnxruntime threads;
    ``model``: another segmentation model (ONNX); ``max_route_s``: stop the route early
    (``None``: the whole route); ``compare_placements``: also fuse the robot's clouds with the
    other placement rule (:data:`mapper.mapping.PLACEMENTS`) for the comparison."""

    route: str = "robustness_route"
    seed: int = 0
    frames_per_camera: int = 3
    robot_cloud_rate_hz: float = 1.0
    consistency_rate_hz: float = 0.5
    threads: int = 2
    model: str | None = None
    max_route_s: float | None = None
    compare_placements: bool = True


@dataclasses.dataclass(frozen=True)
class MapScores:
    """Coverage and label accuracy of a map against the ground truth; per class too."""

    coverage: float
    accuracy: float
    labelled_voxels: int
    off_surface_share: float
    per_class: dict[str, tuple[float, float, int]]  # name -> (coverage, accuracy, GT voxels)


@dataclasses.dataclass(frozen=True)
class GroundTruth:
    """The site's static surfaces as voxels: the mean (V, 3) of the surface samples in each
    voxel and its majority class (V,); and the prior model (points, normals) of the empty
    room."""

    points: np.ndarray
    labels: np.ndarray
    prior_points: np.ndarray
    prior_normals: np.ndarray


def ground_truth(scenario: Any, voxel_size_m: float, texture_seed: int = 0) -> GroundTruth:
    """Ground-truth surface voxels of the scenario's site (floor, walls, furniture; the faces
    that touch the floor and the floor under furniture left out) and the prior model (floor and
    walls sampled, the paper's empty room)."""
    from simulation.scenes import site_geometry, surface_samples

    geometry = site_geometry(scenario, seed=texture_seed)
    pts, nrm, cls = surface_samples(geometry.objects, GT_SPACING_M, seed=1)
    keep = nrm[:, 2] > -0.5  # bottom faces stand on the floor
    floor = cls == SEMANTIC_CLASS_ID["floor"]
    for box in scenario.obstacles:
        c = np.asarray(box.center_xy_m, dtype=np.float64)
        half = 0.5 * np.asarray(box.size_m[:2], dtype=np.float64)
        cos, sin = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
        d = pts[:, :2] - c
        local = np.column_stack([cos * d[:, 0] + sin * d[:, 1], -sin * d[:, 0] + cos * d[:, 1]])
        under = np.all(np.abs(local) < half, axis=1)
        keep &= ~(floor & under)
    pts, cls = pts[keep], cls[keep]
    keys = pack_voxel_keys(np.floor(pts / voxel_size_m).astype(np.int64))
    ukeys, inv, counts = np.unique(keys, return_inverse=True, return_counts=True)
    c = len(SEMANTIC_CLASSES)
    votes = np.bincount(inv * c + cls, minlength=len(ukeys) * c).reshape(len(ukeys), c)
    means = np.column_stack([np.bincount(inv, weights=pts[:, a], minlength=len(ukeys))
                             for a in range(3)]) / counts[:, None]
    empty = (SEMANTIC_CLASS_ID["floor"], SEMANTIC_CLASS_ID["wall"])
    prior_p, prior_n, _ = surface_samples(geometry.objects, GT_SPACING_M, seed=2, classes=empty)
    return GroundTruth(means, votes.argmax(axis=1), prior_p, prior_n)


def write_prior_model(scenario: Any, path: Path, voxel_size_m: float = 0.05) -> Path:
    """The simulated site's prior geometric model for the mapper: the empty room (floor and
    walls, no furniture, no semantics) as a PLY point cloud with normals (one point per voxel;
    what a lab would export from its building model)."""
    from simulation.scenes import site_geometry, surface_samples

    empty = (SEMANTIC_CLASS_ID["floor"], SEMANTIC_CLASS_ID["wall"])
    points, normals, _ = surface_samples(site_geometry(scenario).objects, GT_SPACING_M, seed=2,
                                         classes=empty)
    room = SemanticVoxelMap.from_prior_points(points, SemanticMapConfig(voxel_size_m=voxel_size_m),
                                              normals)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_map_ply(room, path)
    return path


def map_scores(m: SemanticVoxelMap, gt: GroundTruth) -> MapScores:
    """Coverage: share of the ground-truth surface voxels with a labelled map voxel within one
    voxel size (voxel means compared, so a surface lying on a voxel face, like the floor at
    z = 0, counts once whichever side its noisy points fell on); accuracy: share of the
    covered ones whose nearest labelled voxel has the true class; and the share of the map's
    labelled voxels farther than one voxel size from every true surface."""
    from scipy.spatial import cKDTree

    tol = m.config.voxel_size_m
    sem = m.has_semantics()
    means, labels = m.means()[sem], m.labels()[sem]
    per_class: dict[str, tuple[float, float, int]] = {}
    if len(means) == 0:
        for cid in np.unique(gt.labels):
            per_class[SEMANTIC_CLASSES[cid]] = (0.0, math.nan,
                                                int(np.count_nonzero(gt.labels == cid)))
        return MapScores(0.0, math.nan, 0, math.nan, per_class)
    dist, nearest = cKDTree(means).query(gt.points, distance_upper_bound=tol)
    covered = np.isfinite(dist)
    right = np.zeros(len(gt.points), dtype=bool)
    right[covered] = labels[nearest[covered]] == gt.labels[covered]
    for cid in np.unique(gt.labels):
        mine = gt.labels == cid
        hit = covered & mine
        per_class[SEMANTIC_CLASSES[cid]] = (
            float(np.mean(covered[mine])),
            float(np.mean(right[hit])) if hit.any() else math.nan, int(np.count_nonzero(mine)))
    off, _ = cKDTree(gt.points).query(means, distance_upper_bound=tol)
    return MapScores(
        coverage=float(np.mean(covered)),
        accuracy=float(np.mean(right[covered])) if covered.any() else math.nan,
        labelled_voxels=len(means),
        off_surface_share=float(np.mean(~np.isfinite(off))),
        per_class=per_class)


@dataclasses.dataclass
class ConsistencyRow:
    """Robot observations against the map, one placement: mean fitness / inlier RMSE as
    placed (within :data:`CONSISTENCY_DISTANCE_M`), mean ICP offset, clouds used."""

    placement: str
    fitness: float
    rmse_m: float
    icp_offset_m: float
    icp_yaw_deg: float
    clouds: int


@dataclasses.dataclass
class MappingReport:
    """What :func:`run_mapping` measured (see the module docstring)."""

    static: MapScores
    with_robot: MapScores
    robot_clouds: int
    robot_clouds_fused: int
    rejected: dict[str, int]
    alignment_offsets_m: list[float]
    consistency: list[ConsistencyRow]
    segmentation_ms: float
    cloud_points_mean: float
    wall_s: float
    files: list[Path] = dataclasses.field(default_factory=list)
    #: placement rule -> (scores after the route, robot clouds fused)
    placements: dict[str, tuple[MapScores, int]] = dataclasses.field(default_factory=dict)


class _CloudSource:
    """Rendered RGB-D frames → segmentation → semantic clouds (the edge's code path)."""

    def __init__(self, scenario: Any, config: MappingExperimentConfig) -> None:
        from edge_agent.networks import SemanticSegmenter
        from simulation.site_cameras import SiteCameraRenderer

        self.scenario = scenario
        self.renderer = SiteCameraRenderer(scenario)
        self.segmenter = SemanticSegmenter(config.model, threads=config.threads)
        robot_model = scenario.site.robot_model(scenario.robot_id)
        self.head = getattr(robot_model, "head_camera", None)
        if self.head is None:
            raise ValueError(f"robot model of {scenario.robot_id!r} has no head_camera in "
                             f"{scenario.site.source_path}: the robot cannot map")
        self.seg_ms: list[float] = []
        self.points: list[int] = []

    def _cloud(self, color: np.ndarray, depth: np.ndarray, camera: Any, **kw: Any
               ) -> SemanticCloud:
        from edge_agent.semantic_cloud import build_semantic_cloud

        t0 = time.perf_counter()
        seg = self.segmenter(color)
        self.seg_ms.append((time.perf_counter() - t0) * 1e3)
        cloud = build_semantic_cloud(seg, depth, camera, **kw)
        self.points.append(len(cloud.points_xyz))
        return cloud

    def static_cloud(self, camera_id: str, robot_pose: np.ndarray, stamp_ns: int, seq: int,
                     rng: np.random.Generator) -> SemanticCloud:
        """One frame of a site camera (rendered at its true pose) as the edge publishes it: in
        the world frame through the camera's calibration (the site file's)."""
        out = self.renderer.render_output(camera_id, robot_pose)
        color = self.renderer.add_noise(out.color_rgb, rng)
        depth = self.renderer.depth_noise.apply(out.depth_m, rng)
        calibrated = self.scenario.site.camera(camera_id)
        return self._cloud(color, depth, calibrated, sensor_id=camera_id, stamp_ns=stamp_ns,
                           seq=seq, frame_id=self.scenario.site.world_frame,
                           T_frame_sensor=calibrated.T_world_cam)

    def robot_cloud(self, true_pose: np.ndarray, stamp_ns: int, seq: int,
                    rng: np.random.Generator) -> SemanticCloud:
        """The head camera's cloud in the robot base frame, rendered at the true pose."""
        out = self.renderer.render_head(self.head, true_pose)
        color = self.renderer.add_noise(out.color_rgb, rng)
        depth = self.renderer.depth_noise.apply(out.depth_m, rng)
        return self._cloud(color, depth, self.head.camera_model("head"),
                           sensor_id=self.scenario.robot_id, stamp_ns=stamp_ns, seq=seq,
                           frame_id="base_link", T_frame_sensor=self.head.T_base_cam)

    def release(self) -> None:
        self.renderer.release()


def _pose_at(stamps_ns: np.ndarray, poses: np.ndarray, stamp_ns: int) -> np.ndarray:
    """(x, y, theta) at ``stamp_ns`` interpolated in a run's log (NaN rows skipped)."""
    ok = np.all(np.isfinite(poses), axis=1)
    s, p = stamps_ns[ok].astype(np.float64), poses[ok]
    theta = np.unwrap(p[:, 2])
    t = float(stamp_ns)
    return np.array([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1]),
                     float(wrap_angle_array(np.interp(t, s, theta)))])


def _cloud_stamps(run: FeedbackRun, rate_hz: float, max_s: float | None) -> list[int]:
    start, end = int(run.stamps_ns[0]), int(run.stamps_ns[-1])
    if max_s is not None:
        end = min(end, start + round(max_s * 1e9))
    step = round(1e9 / rate_hz)
    return list(range(start + step, end, step))


def _placed(cloud: SemanticCloud, pose: np.ndarray) -> np.ndarray:
    T = se3_from_planar(*(float(v) for v in pose))
    return cloud.points_xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]


def run_mapping(scenario: Any, config: MappingExperimentConfig, out_dir: str | Path, *,
                runs: tuple[FeedbackRun, FeedbackRun] | None = None,
                run_route: Callable[[bool], FeedbackRun] | None = None,
                say: Callable[[str], None] | None = None) -> MappingReport:
    """Run experiment 4 (module docstring). ``runs``: the route's (without, with feedback)
    :class:`~lab.experiments.feedback.FeedbackRun` if already simulated, else ``run_route``
    (feedback → run) simulates them."""
    say = say or (lambda line: log.info("%s", line))
    wall0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    site = scenario.site
    mcfg = MappingConfig.from_site(site)
    gt = ground_truth(scenario, mcfg.map.voxel_size_m)
    mapping = SemanticMapping(site, mcfg, prior_points_world=gt.prior_points,
                              prior_normals_world=gt.prior_normals)
    say(f"mapping: {len(gt.points)} ground-truth surface voxels of {mcfg.map.voxel_size_m} m, "
        f"prior model (floor + walls) {len(mapping.map)} voxels")
    source = _CloudSource(scenario, config)
    rng = np.random.default_rng([config.seed, 44])
    start_ns = scenario.start_stamp_ns
    try:
        if runs is None:
            if run_route is None:
                raise ValueError("run_mapping needs the route's runs or run_route")
            runs = (run_route(False), run_route(True))
        run_nofb, run_fb = runs
        first_pose = run_fb.ground_truth[0]
        for cid in site.cameras:
            for k in range(config.frames_per_camera):
                stamp = start_ns + k * 1_000_000_000
                cloud = source.static_cloud(cid, first_pose, stamp, k, rng)
                res = mapping.on_cloud(cloud, "edge", cid, stamp)
                if not res.accepted:
                    log.warning("static cloud of %s rejected: %s", cid, res.reason)
        static = map_scores(mapping.map, gt)
        say(f"mapping: static sensors alone: coverage {static.coverage:.1%}, label accuracy "
            f"{static.accuracy:.1%} ({len(site.cameras)} cameras x {config.frames_per_camera} "
            f"frames)")
        static_map = mapping.map.copy()

        # the robot's exploration: clouds placed with the fused pose, ICP-gated, fused; the
        # mapper has the fused poses the backend published up to the cloud's arrival
        published = run_fb.published_fused
        fed = 0
        offsets: list[float] = []
        stamps = _cloud_stamps(run_fb, config.robot_cloud_rate_hz, config.max_route_s)
        accepted = 0
        clouds_fb: dict[int, SemanticCloud] = {}
        for seq, stamp in enumerate(stamps):
            while fed < len(published) and published[fed, 0] <= stamp + CLOUD_DELAY_NS:
                t, x, y, th = published[fed]
                mapping.on_pose(PoseEstimate(scenario.robot_id, int(t), fed, float(x), float(y),
                                             float(th), np.eye(3) * 1e-4, "fused"))
                fed += 1
            true_pose = _pose_at(run_fb.stamps_ns, run_fb.ground_truth, stamp)
            cloud = source.robot_cloud(true_pose, stamp, seq, rng)
            clouds_fb[stamp] = cloud
            res = mapping.on_cloud(cloud, "robot", scenario.robot_id, stamp)
            accepted += res.accepted
            if res.alignment is not None and math.isfinite(res.alignment.inlier_rmse_m):
                offsets.append(res.alignment.offset_m)
            if (seq + 1) % 50 == 0:
                say(f"mapping: {seq + 1}/{len(stamps)} robot clouds, {accepted} fused, "
                    f"coverage {map_scores(mapping.map, gt).coverage:.1%}")
        with_robot = map_scores(mapping.map, gt)
        say(f"mapping: after the robot's route ({config.route}, {len(stamps)} clouds, "
            f"{accepted} fused): coverage {with_robot.coverage:.1%}, label accuracy "
            f"{with_robot.accuracy:.1%}")
        placements = {mcfg.placement: (with_robot, accepted)}
        if config.compare_placements:
            # the same clouds and poses once more, from the static map, with the other rule
            for other in PLACEMENTS:
                if other in placements:
                    continue
                alt = SemanticMapping(site, dataclasses.replace(mcfg, placement=other),
                                      initial_map=static_map.copy())
                for t, x, y, th in published:
                    alt.on_pose(PoseEstimate(scenario.robot_id, int(t), 0, float(x), float(y),
                                             float(th), np.eye(3) * 1e-4, "fused"))
                fused_n = sum(alt.on_cloud(c, "robot", scenario.robot_id, s).accepted
                              for s, c in clouds_fb.items())
                placements[other] = (map_scores(alt.map, gt), fused_n)
                sc_ = placements[other][0]
                say(f"mapping: placement {other}: coverage {sc_.coverage:.1%}, label accuracy "
                    f"{sc_.accuracy:.1%}, off the surfaces {sc_.off_surface_share:.1%}")

        # consistency (Fig. 7): robot observations placed by each pose source vs the map
        final_points, final_normals = mapping.map.means(), mapping.map.normals()
        occupied = mapping.map.occupied()
        final_points, final_normals = final_points[occupied], final_normals[occupied]
        rows = []
        fused_poses: StampedHistory[PoseEstimate] = StampedHistory(out_of_order="insert")
        for t, x, y, th in published:
            fused_poses.insert(int(t), PoseEstimate(scenario.robot_id, int(t), 0, float(x),
                                                    float(y), float(th), np.eye(3), "fused"))
        sources = (("robot localization, without feedback", run_nofb, "robot"),
                   ("robot localization, with feedback", run_fb, "robot"),
                   ("fused pose (smartedge)", run_fb, "fused"),
                   ("true pose (reference)", run_fb, "truth"))
        for name, run, which in sources:
            fits, rmses, offs, yaws = [], [], [], []
            for seq, stamp in enumerate(_cloud_stamps(run, config.consistency_rate_hz,
                                                      config.max_route_s)):
                if run is run_fb and stamp in clouds_fb:
                    cloud = clouds_fb[stamp]
                else:
                    true_pose = _pose_at(run.stamps_ns, run.ground_truth, stamp)
                    cloud = source.robot_cloud(true_pose, stamp, seq, rng)
                if which == "fused":
                    p = interpolate_pose(fused_poses, stamp, 10**9)
                    if p is None:
                        continue
                    pose = np.array(p)
                elif which == "truth":
                    pose = _pose_at(run.stamps_ns, run.ground_truth, stamp)
                else:
                    pose = _pose_at(run.stamps_ns, run.robot, stamp)
                pts = _placed(cloud, pose)
                fit, rmse = consistency(pts, final_points, CONSISTENCY_DISTANCE_M)
                fits.append(fit)
                rmses.append(rmse)
                icp = align_to_map(pts, final_points, final_normals, mcfg.alignment)
                if math.isfinite(icp.inlier_rmse_m):
                    offs.append(icp.offset_m)
                    yaws.append(abs(icp.yaw_deg))
            rows.append(ConsistencyRow(name, _mean(fits), _mean(rmses), _mean(offs),
                                       _mean(yaws), len(fits)))
            say(f"mapping: consistency, {name}: fitness {rows[-1].fitness:.3f}, RMSE "
                f"{rows[-1].rmse_m * 100:.2f} cm, ICP offset {rows[-1].icp_offset_m * 100:.1f} cm")
        counters = mapping.counter_snapshot()
        report = MappingReport(
            static=static, with_robot=with_robot, robot_clouds=len(stamps),
            robot_clouds_fused=accepted,
            rejected={k.removeprefix("map.rejected."): v for k, v in counters.items()
                      if k.startswith("map.rejected.")},
            alignment_offsets_m=offsets, consistency=rows,
            segmentation_ms=_mean(source.seg_ms), cloud_points_mean=_mean(source.points),
            wall_s=time.perf_counter() - wall0, placements=placements)
        report.files = write_mapping_outputs(out, report, mapping.map, static_map, scenario)
        report.wall_s = time.perf_counter() - wall0
        return report
    finally:
        source.release()


def run_semantic_mapping(sc: Scenario, config: PaperConfig, factory: FusionFactory | None,
                    world: World, detector: DetectionSimulator, out: Path,
                    say: Callable[[str], None]) -> tuple[str, list[Path]]:
    """Experiment 4 as ``smartedge evaluate paper`` runs it: the static cameras' clouds, then
    the robot's exploration route (``config.mapping_route``, the same seed without and with
    feedback, :func:`~lab.experiments.feedback.run_feedback`) with its head camera's
    clouds, into the mapper's semantic map (:func:`run_mapping`). Returns the Markdown and the
    files written into ``out``."""
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


def _mean(values: Sequence[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def _pct(v: float) -> str:
    return "n/a" if not math.isfinite(v) else f"{100 * v:.1f} %"


def mapping_markdown(report: MappingReport) -> str:
    s, r = report.static, report.with_robot
    lines = [
        "### Coverage and labels (Sec. IV-C)\n",
        "| Map | coverage | label accuracy | labelled voxels | labelled off the surfaces |",
        "|---|---|---|---|---|",
        f"| static sensors alone | {_pct(s.coverage)} | {_pct(s.accuracy)} | "
        f"{s.labelled_voxels} | {_pct(s.off_surface_share)} |",
        f"| after the robot's route | {_pct(r.coverage)} | {_pct(r.accuracy)} | "
        f"{r.labelled_voxels} | {_pct(r.off_surface_share)} |",
        "",
        f"Paper: ~{PAPER_COVERAGE['static']:.0%} from the static sensors, > "
        f"{PAPER_COVERAGE['with_robot']:.0%} after the robot's exploration. Robot clouds: "
        f"{report.robot_clouds}, fused after the ICP gate: {report.robot_clouds_fused}"
        + (f" (rejected: {', '.join(f'{k} {v}' for k, v in sorted(report.rejected.items()))})"
           if report.rejected else "")
        + f"; median ICP offset {_median_cm(report.alignment_offsets_m)}. Segmentation "
        f"{report.segmentation_ms:.1f} ms per frame, {report.cloud_points_mean:.0f} points per "
        "cloud.\n",
        "| Class | GT voxels | coverage (static) | coverage (with robot) | accuracy (with robot) |",
        "|---|---|---|---|---|",
    ]
    for name, (cov, acc, total) in sorted(r.per_class.items(), key=lambda kv: -kv[1][2]):
        cov_s = s.per_class.get(name, (math.nan, math.nan, 0))[0]
        lines.append(f"| {name} | {total} | {_pct(cov_s)} | {_pct(cov)} | {_pct(acc)} |")
    if len(report.placements) > 1:
        lines += ["", "Where the robot's clouds are fused (`map.placement`; the same clouds and "
                  "poses, from the static map):\n",
                  "| placement | coverage | label accuracy | labelled off the surfaces | "
                  "clouds fused |", "|---|---|---|---|---|"]
        for name, (sc, n) in report.placements.items():
            lines.append(f"| {name} | {_pct(sc.coverage)} | {_pct(sc.accuracy)} | "
                         f"{_pct(sc.off_surface_share)} | {n} |")
    lines += [
        "",
        "### Consistency of robot observations with the map (Fig. 7)\n",
        "| Placement | fitness (<= 10 cm) | inlier RMSE | ICP offset | ICP yaw | clouds |",
        "|---|---|---|---|---|---|",
    ]
    for row in report.consistency:
        lines.append(f"| {row.placement} | {row.fitness:.3f} | {row.rmse_m * 100:.2f} cm | "
                     f"{row.icp_offset_m * 100:.1f} cm | {row.icp_yaw_deg:.2f} deg | "
                     f"{row.clouds} |")
    lines.append("")
    return "\n".join(lines)


def _median_cm(values: Sequence[float]) -> str:
    return f"{np.median(values) * 100:.1f} cm" if len(values) else "n/a"


def topdown_png(m: SemanticVoxelMap, scenario: Any, path: Path, title: str) -> Path:
    """A top-down picture of the map: per column the highest voxel with semantics, in its
    class colour (prior-only columns grey), with the legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    v = m.config.voxel_size_m
    lo = np.asarray(scenario.room_min_xy_m, dtype=np.float64)
    hi = np.asarray(scenario.room_max_xy_m, dtype=np.float64)
    w, h = (np.ceil((hi - lo) / v).astype(int) + 1)
    rgb = np.full((h, w, 3), 255, dtype=np.uint8)
    idx = m.voxel_indices()
    ij = np.floor(((idx[:, :2] + 0.5) * v - lo) / v).astype(int)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    labels = m.labels()
    prior = m.is_prior() & inside & (labels < 0)
    rgb[ij[prior, 1], ij[prior, 0]] = NO_SEMANTICS_COLOR
    sem = inside & (labels >= 0)
    order = np.argsort(idx[sem, 2], kind="stable")  # low to high: the highest is drawn last
    rows = np.flatnonzero(sem)[order]
    rgb[ij[rows, 1], ij[rows, 0]] = SEMANTIC_CLASS_COLORS[labels[rows]]
    fig, ax = plt.subplots(figsize=(10, 10 * h / w + 1.2), dpi=120)
    ax.imshow(rgb, origin="lower", extent=(lo[0], lo[0] + w * v, lo[1], lo[1] + h * v),
              interpolation="nearest")
    present = sorted(set(labels[sem].tolist()))
    handles = [Patch(color=SEMANTIC_CLASS_COLORS[c] / 255.0, label=SEMANTIC_CLASSES[c])
               for c in present]
    handles.append(Patch(color=np.array(NO_SEMANTICS_COLOR) / 255.0, label="no semantics"))
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=6,
              fontsize=8, frameon=False)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def write_mapping_outputs(out: Path, report: MappingReport, final: SemanticVoxelMap,
                          static: SemanticVoxelMap, scenario: Any) -> list[Path]:
    files = [topdown_png(final, scenario, out / "semantic_map_topdown.png",
                         f"semantic map after the robot's route: coverage "
                         f"{report.with_robot.coverage:.0%}"),
             topdown_png(static, scenario, out / "semantic_map_static_topdown.png",
                         f"static sensors alone: coverage {report.static.coverage:.0%}")]
    save_map_npz(final, out / "semantic_map.npz", compress=True)
    write_map_ply(final, out / "semantic_map.ply")
    files += [out / "semantic_map.npz", out / "semantic_map.ply"]
    (out / "mapping.md").write_text(mapping_markdown(report), encoding="utf-8")
    files.append(out / "mapping.md")
    doc = {
        "static": dataclasses.asdict(report.static),
        "with_robot": dataclasses.asdict(report.with_robot),
        "robot_clouds": report.robot_clouds, "robot_clouds_fused": report.robot_clouds_fused,
        "rejected": report.rejected,
        "median_icp_offset_m": float(np.median(report.alignment_offsets_m))
        if report.alignment_offsets_m else None,
        "consistency": [dataclasses.asdict(r) for r in report.consistency],
        "placements": {k: {"scores": dataclasses.asdict(v[0]), "clouds_fused": v[1]}
                       for k, v in report.placements.items()},
        "segmentation_ms": report.segmentation_ms, "wall_s": report.wall_s,
        "paper": PAPER_COVERAGE,
    }
    (out / "mapping.json").write_text(json.dumps(doc, indent=2, default=float),
                                      encoding="utf-8")
    files.append(out / "mapping.json")
    return files
