"""``smartedge evaluate calibration``: the site calibration of issue #27 measured on the simulated
paper lab against the simulator's TRUE cameras (:func:`simulation.detections.true_cameras`: the
site file's poses perturbed by the scenario's calibration error; the site file itself is the
"nominal" calibration a lab would have).

1. **Intrinsics** from rendered ChArUco views (:func:`simulation.board_views.calibration_sweep`
   through the project's renderer, the true lens), detected and calibrated as ``smartedge
   calibrate intrinsics`` does: fx, fy, cx, cy error (%) and the lens-model difference (px, the
   same rays through the true and the estimated model over the image the views covered).
2. **Extrinsics from board sightings** (:func:`simulation.board_views.board_walk`, rendered,
   detected, solved jointly): anchored by the board's pose at every stamp (a board on the robot,
   placed by its localization; here its true pose) or by one fixed board pose.
3. **The robot as the target**: a simulated drive recorded to MCAP exactly as ``smartedge
   record`` writes it, run through ``smartedge calibrate robot`` (the command's own ``main``):
   (a) every camera started 20 cm / 3 deg off, map frame from the robot's localization; (b) from
   the nominal site with ``--frame site``; (c) one camera bumped 5 cm / 1 deg, recalibrated with
   ``--camera``. Per camera the error against the truth, and the common planar offset of the
   whole set (what only the map frame's anchor can fix: docs/calibration.md).
4. **Table I** (experiment 1, noise model) with the backend given each site file - true,
   nominal, self-calibrated (b), self-calibrated (a), board-calibrated - while the simulator
   keeps the true cameras (the same runs and detections for every site file).

Writes ``calibration.md`` (tables), ``calibration.json`` (the numbers), ``calibration.png``
(per-camera errors by method, Table I by site file), the site files and the drive's recording
into the output folder.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from calibration.board import BoardDetector, CharucoBoardSpec, board_image
from calibration.board_extrinsics import BoardSighting, solve_board_extrinsics
from calibration.intrinsics import calibrate_intrinsics, model_difference_px
from calibration.site_file import write_site_with_cameras
from core.camera import CameraModel
from core.geometry import pose_error
from core.site import Site, load_site
from lab.experiments.accuracy import (
    ROW_NAMES,
    RunResult,
    accuracy_tables,
    run_pose_accuracy,
    source_errors,
)
from lab.experiments.config import PaperConfig, default_fusion_factory, make_detector
from protocol.errors import SmartedgeError
from simulation.board_views import BoardRenderer, BoardTexture, board_walk, calibration_sweep
from simulation.calibration_drive import perturbed_camera_poses, record_drive
from simulation.detections import true_cameras
from simulation.scenario import PAPER_SCENARIO, Scenario, load_scenario
from simulation.world import World

#: an A2 board (540 x 420 mm) for intrinsics, as a lab prints for ~850 px wide cameras
INTRINSICS_BOARD = CharucoBoardSpec(9, 7, 0.06, 0.045, "DICT_5X5_100")
#: an A0 board (1000 x 800 mm) with large markers: the ceiling cameras see it from 3-5 m
EXTRINSICS_BOARD = CharucoBoardSpec(5, 4, 0.2, 0.156, "DICT_4X4_50")
#: the site files Table I is run with, in the report's order
SITE_VARIANTS = ("true", "nominal", "robot_site_frame", "robot_from_20cm", "board")
SITE_NAMES = {
    "true": "true cameras",
    "nominal": "nominal site file",
    "robot_site_frame": "self-calibrated (b): --frame site",
    "robot_from_20cm": "self-calibrated (a): from 20 cm / 3°",
    "board": "board-calibrated (board pose per stamp)",
}
#: Table I sources summarised at >= 2 cameras
SUMMARY_SOURCES = ("one_frame", "five_frames", "fused")


@dataclasses.dataclass(frozen=True)
class CalibrationEvalConfig:
    """Settings of ``smartedge evaluate calibration``; :meth:`quick` is the short version."""

    seed: int = 0
    scenario_path: str | None = None
    #: intrinsics: cameras calibrated (None: all) and rendered views per camera
    intrinsics_cameras: tuple[str, ...] | None = None
    intrinsics_views: int = 30
    #: extrinsics: rounds of the board walk (one pose per camera each)
    board_rounds: int = 6
    #: the robot's drive: route, simulated seconds
    drive_route: str = "traj3x3"
    drive_s: float = 300.0
    #: (a): every camera this far off (m, deg); (c): this camera bumped this much
    start_offset: tuple[float, float] = (0.20, 3.0)
    bumped_camera: str = "cam3"
    bump: tuple[float, float] = (0.05, 1.0)
    #: Table I: trajectories (None: the scenario's), runs per direction, worker processes
    table_trajectories: tuple[str, ...] | None = None
    table_runs: int = 1
    jobs: int | None = None
    with_table: bool = True

    @classmethod
    def quick(cls, **changes: Any) -> CalibrationEvalConfig:
        """One camera's intrinsics, a short board walk, a 90 s drive, Table I on one
        trajectory (for tests and a first look)."""
        base = cls(intrinsics_cameras=("cam1",), intrinsics_views=20, board_rounds=4,
                   drive_s=90.0, table_trajectories=("traj1",), table_runs=1)
        return dataclasses.replace(base, **changes)


@dataclasses.dataclass
class CalibrationEvaluation:
    """Everything measured (``numbers`` is ``calibration.json``) and the files written."""

    numbers: dict[str, Any]
    markdown: str
    files: list[Path]
    wall_s: float


# --------------------------------------------------------------------------------------------
# pieces
# --------------------------------------------------------------------------------------------


def _texture(spec: CharucoBoardSpec, px_per_square: int) -> BoardTexture:
    img = board_image(spec, px_per_square)
    return BoardTexture(img.image, img.extent_board_m)


def evaluate_intrinsics(camera: CameraModel, views: int, seed: int) -> dict[str, Any]:
    """Render ``views`` board views through ``camera`` (the truth), detect, calibrate; the
    errors of fx, fy, cx, cy (%) and the lens model (px over the covered image)."""
    spec = INTRINSICS_BOARD
    det = BoardDetector(spec)
    t0 = time.perf_counter()
    with BoardRenderer(_texture(spec, 60), camera.width, camera.height) as br:
        images = [br.render(c, np.eye(4)).image_rgb
                  for c in calibration_sweep(camera, spec.size_m, views, seed=seed)]
    detections = [(f"view{i:02d}", det.detect(img)) for i, img in enumerate(images)]
    res = calibrate_intrinsics(detections, spec, camera.camera_id)
    truth = np.array([camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]])
    est = np.array([res.K[0, 0], res.K[1, 1], res.K[0, 2], res.K[1, 2]])
    diff = model_difference_px(camera.K, camera.dist, res.K, res.dist,
                               (camera.width, camera.height), coverage=res.coverage)
    return {
        "views_rendered": views, "views_used": len(res.views), "skipped": len(res.skipped),
        "rms_px": res.rms_px,
        "error_pct": dict(zip(("fx", "fy", "cx", "cy"),
                              (100.0 * (est / truth - 1.0)).tolist(), strict=True)),
        "model_diff_px": {"mean": float(diff.mean()), "p95": float(np.percentile(diff, 95)),
                          "max": float(diff.max())},
        "coverage": res.coverage_fraction,
        "seconds": time.perf_counter() - t0,
    }


def evaluate_board_extrinsics(truth: Mapping[str, CameraModel], rounds: int, seed: int,
                              ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Board walk rendered through the true cameras, detected, solved with each anchor; the
    per-camera errors, and the poses of the per-stamp anchor (the board-calibrated site)."""
    spec = EXTRINSICS_BOARD
    t0 = time.perf_counter()
    poses = board_walk(dict(truth), spec.size_m, rounds, seed=seed)
    first = next(iter(truth.values()))
    det = BoardDetector(spec)
    sightings: list[BoardSighting] = []
    images = 0
    with BoardRenderer(_texture(spec, 50), first.width, first.height) as br:
        for stamp, T in poses.items():
            for cid, cam in truth.items():
                images += 1
                d = det.detect(br.render(cam, T).image_rgb)
                if d.usable:
                    sightings.append(BoardSighting.from_detection(cid, stamp, d))
    out: dict[str, Any] = {"board_poses": len(poses), "images": images,
                           "sightings": len(sightings), "anchors": {}}
    solved: dict[str, np.ndarray] = {}
    for anchor, fixed in (("per_stamp", poses), ("one_fixed", {"000": poses["000"]})):
        try:
            res = solve_board_extrinsics(dict(truth), sightings, spec, fixed)
        except SmartedgeError as exc:
            out["anchors"][anchor] = {"error": str(exc)}
            continue
        cams = {}
        for cid, sol in res.cameras.items():
            dp, da = pose_error(sol.T_world_cam, truth[cid].T_world_cam)
            cams[cid] = {"position_cm": 100 * dp, "rotation_deg": da,
                         "std_cm": 100 * sol.std_position_m, "std_deg": sol.std_rotation_deg}
        out["anchors"][anchor] = {"cameras": cams, "rms_px": res.rms_px,
                                  "not_solved": sorted(set(truth) - set(res.cameras))}
        if anchor == "per_stamp":
            solved = {c: s.T_world_cam for c, s in res.cameras.items()}
    out["seconds"] = time.perf_counter() - t0
    return out, solved


def common_offset(estimated: Mapping[str, np.ndarray], true: Mapping[str, np.ndarray],
                  ) -> tuple[float, float, np.ndarray]:
    """The planar rigid motion (x, y, yaw) that best maps the estimated camera positions onto
    the true ones (least squares): (its shift at the cameras' centroid m, its yaw deg, the
    (4, 4) motion). This is the part of a calibration only the map frame's anchor decides."""
    ids = sorted(estimated)
    A = np.array([estimated[c][:2, 3] for c in ids])
    B = np.array([true[c][:2, 3] for c in ids])
    ma, mb = A.mean(axis=0), B.mean(axis=0)
    H = (A - ma).T @ (B - mb)
    yaw = math.atan2(H[0, 1] - H[1, 0], H[0, 0] + H[1, 1])
    R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    M = np.eye(4)
    M[:2, :2] = R
    M[:2, 3] = mb - R @ ma
    return float(np.linalg.norm(mb - ma)), math.degrees(yaw), M


def _errors(poses: Mapping[str, np.ndarray], truth: Mapping[str, CameraModel],
            ) -> dict[str, dict[str, float]]:
    return {c: dict(zip(("position_cm", "rotation_deg"),
                        (100 * (e := pose_error(T, truth[c].T_world_cam))[0], e[1]),
                        strict=True))
            for c, T in sorted(poses.items())}


def run_robot_calibration(argv: Sequence[str], log_path: Path) -> tuple[int, dict[str, Any],
                                                                         float]:
    """``smartedge calibrate robot`` (its ``main``, in this process) with ``argv`` plus a
    ``--report``; its output goes to ``log_path``. Returns (exit code, report, wall s)."""
    from smartedge.commands.calibrate_robot import main as robot_main

    report = log_path.with_suffix(".json")
    report.unlink(missing_ok=True)
    t0 = time.perf_counter()
    with open(log_path, "w", encoding="utf-8") as log_file, \
            contextlib.redirect_stdout(log_file), contextlib.redirect_stderr(log_file):
        code = robot_main([*argv, "--report", str(report)])
    wall = time.perf_counter() - t0
    data = json.loads(report.read_text(encoding="utf-8")) if report.exists() else {}
    return code, data, wall


def accuracy_summary(results: Sequence[RunResult]) -> dict[str, dict[str, float]]:
    """Mean translation (cm) and heading (deg) error of each camera source at waypoints seen
    by >= 2 cameras, and the sample count."""
    out: dict[str, dict[str, float]] = {}
    for src in ("robot", "raw", "paper", *SUMMARY_SOURCES):
        try:
            err = source_errors(results, src)
        except (KeyError, ValueError):
            continue
        sel = (err.num_cameras >= 2) & np.isfinite(err.translation_m)
        if not np.any(sel):
            continue
        out[src] = {"t_mean_cm": float(np.mean(err.translation_m[sel]) * 100),
                    "r_mean_deg": float(np.degrees(np.mean(np.abs(err.heading_rad[sel])))),
                    "count": int(np.sum(sel))}
    return out


# --------------------------------------------------------------------------------------------
# the evaluation
# --------------------------------------------------------------------------------------------


def run_calibration_evaluation(config: CalibrationEvalConfig, out_dir: str | Path,
                               progress: Callable[[str], None] = print,
                               ) -> CalibrationEvaluation:
    """All of the module docstring's steps; files into ``out_dir``."""
    from smartedge.commands.record import Recorder

    t_start = time.perf_counter()
    out = Path(out_dir)
    sites_dir = out / "sites"
    logs = out / "logs"
    for d in (out, sites_dir, logs):
        d.mkdir(parents=True, exist_ok=True)

    def say(line: str) -> None:
        progress(f"[{time.perf_counter() - t_start:6.1f} s] {line}")

    sc = load_scenario(config.scenario_path or PAPER_SCENARIO)
    truth = true_cameras(sc)
    T_true = {c: m.T_world_cam for c, m in truth.items()}
    site_path = Path(sc.site.source_path)
    numbers: dict[str, Any] = {"scenario": sc.name, "config": dataclasses.asdict(config)}
    numbers["nominal"] = _errors({c: m.T_world_cam for c, m in sc.site.cameras.items()}, truth)

    # 1. intrinsics -------------------------------------------------------------------------
    cams = config.intrinsics_cameras or tuple(sorted(truth))
    numbers["intrinsics"] = {}
    for k, cid in enumerate(cams):
        if cid not in truth:
            raise SmartedgeError(f"intrinsics camera {cid!r} is not in site {sc.site.name!r} "
                                 f"(cameras: {sorted(truth)})")
        r = evaluate_intrinsics(truth[cid], config.intrinsics_views, config.seed + 4 + k)
        numbers["intrinsics"][cid] = r
        e = r["error_pct"]
        say(f"intrinsics {cid}: {r['views_used']}/{r['views_rendered']} views, RMS "
            f"{r['rms_px']:.3f} px, fx {e['fx']:+.3f} % fy {e['fy']:+.3f} % cx {e['cx']:+.3f} % "
            f"cy {e['cy']:+.3f} %, lens model mean {r['model_diff_px']['mean']:.3f} px "
            f"({r['seconds']:.1f} s)")

    # 2. extrinsics from board sightings ------------------------------------------------------
    say(f"extrinsics: board walk of {config.board_rounds} rounds, rendering and detecting")
    board, board_poses = evaluate_board_extrinsics(truth, config.board_rounds, config.seed + 3)
    numbers["board_extrinsics"] = board
    for anchor, r in board["anchors"].items():
        if "cameras" in r:
            worst = max(r["cameras"].values(), key=lambda v: v["position_cm"])
            say(f"extrinsics ({anchor}): {len(r['cameras'])} cameras, worst "
                f"{worst['position_cm']:.2f} cm / "
                f"{max(v['rotation_deg'] for v in r['cameras'].values()):.3f} deg")
        else:
            say(f"extrinsics ({anchor}): {r['error']}")

    # 3. the robot as the target --------------------------------------------------------------
    mcap = out / f"drive_{config.drive_route}_{config.drive_s:.0f}s_seed{config.seed}.mcap"
    t0 = time.perf_counter()
    mcap.unlink(missing_ok=True)
    rec = Recorder(mcap)
    try:
        drive = record_drive(rec.write, sc, config.drive_route, duration_s=config.drive_s,
                             seed=config.seed)
    finally:
        rec.close()
    numbers["drive"] = {"route": config.drive_route, "duration_s": drive.duration_s,
                        "sightings": dict(drive.sightings), "seconds": time.perf_counter() - t0}
    say(f"drive: {drive.duration_s:.0f} s of {config.drive_route} recorded to {mcap.name}, "
        f"sightings {dict(sorted(drive.sightings.items()))}")
    start = perturbed_camera_poses(sc.site, *config.start_offset, seed=config.seed + 1)
    start_site = sites_dir / "start_20cm_3deg.yaml"
    write_site_with_cameras(site_path, start_site, start,
                            f"every camera moved {config.start_offset[0] * 100:.0f} cm / "
                            f"{config.start_offset[1]:g} deg from {site_path.name}")
    bumped_id = config.bumped_camera
    bumped_T = perturbed_camera_poses(sc.site, *config.bump, seed=config.seed + 3)[bumped_id]
    bumped_site = sites_dir / f"{bumped_id}_bumped.yaml"
    write_site_with_cameras(site_path, bumped_site, {bumped_id: bumped_T},
                            f"{bumped_id} moved {config.bump[0] * 100:.0f} cm / "
                            f"{config.bump[1]:g} deg from {site_path.name}")
    numbers["start"] = _errors(start, truth)
    cases = {
        "robot_from_20cm": (start_site, ["--partial"]),
        "robot_site_frame": (site_path, ["--frame", "site", "--partial"]),
        "robot_bumped": (bumped_site, ["--camera", bumped_id]),
    }
    robot: dict[str, Any] = {}
    service_sites: dict[str, Site] = {}
    for name, (given, extra) in cases.items():
        written = sites_dir / f"{name}.yaml"
        written.unlink(missing_ok=True)
        argv = ["--site", str(given), "--recording", str(mcap), "--out", str(written), *extra]
        code, report, wall = run_robot_calibration(argv, logs / f"{name}.txt")
        entry: dict[str, Any] = {"argv": ["smartedge", "calibrate", "robot", *argv],
                                 "exit_code": code, "wall_s": wall,
                                 "solver_s": report.get("seconds", {}).get("total")}
        if written.exists():
            site = load_site(written)
            poses = {c: site.cameras[c].T_world_cam for c in sorted(site.cameras)}
            if name == "robot_bumped":
                poses = {bumped_id: poses[bumped_id]}
                entry["before"] = _errors({bumped_id: bumped_T}, truth)
            else:
                service_sites[name] = site
                shift, yaw, M = common_offset(poses, T_true)
                entry["common_offset"] = {"shift_cm": 100 * shift, "yaw_deg": yaw}
                entry["offset_removed"] = _errors({c: M @ T for c, T in poses.items()}, truth)
            entry["cameras"] = _errors(poses, truth)
            entry["refused"] = {c: v["refused"] for c, v in report.get("cameras", {}).items()
                                if v.get("status") == "refused"}
            errs = entry["cameras"].values()
            say(f"robot {name}: exit {code}, {wall:.1f} s, worst "
                f"{max(v['position_cm'] for v in errs):.2f} cm / "
                f"{max(v['rotation_deg'] for v in errs):.3f} deg"
                + (f", common offset {entry['common_offset']['shift_cm']:.1f} cm / "
                   f"{entry['common_offset']['yaw_deg']:+.3f} deg"
                   if "common_offset" in entry else ""))
        else:
            entry["error"] = (logs / f"{name}.txt").read_text(encoding="utf-8")[-2000:]
            say(f"robot {name}: exit {code}, nothing written (see logs/{name}.txt)")
        robot[name] = entry
    numbers["robot"] = robot

    # 4. Table I with each site file ----------------------------------------------------------
    write_site_with_cameras(site_path, sites_dir / "true.yaml", T_true,
                            "the simulator's true cameras")
    service_sites["true"] = load_site(sites_dir / "true.yaml")
    service_sites["nominal"] = sc.site
    if board_poses:
        write_site_with_cameras(site_path, sites_dir / "board.yaml", board_poses,
                                "board-calibrated: board walk, board pose per stamp")
        service_sites["board"] = load_site(sites_dir / "board.yaml")
    numbers["table1"] = {}
    tables_md: dict[str, str] = {}
    if config.with_table:
        numbers["table1"], tables_md = _tables(sc, config, service_sites, say)

    files = [out / "calibration.md", out / "calibration.json", out / "calibration.png"]
    numbers["wall_s"] = time.perf_counter() - t_start
    markdown = report_markdown(numbers, tables_md)
    files[0].write_text(markdown, encoding="utf-8")
    files[1].write_text(json.dumps(numbers, indent=1, default=_json_default), encoding="utf-8")
    plot_errors(numbers, files[2])
    say(f"wrote {', '.join(f.name for f in files)} into {out}")
    return CalibrationEvaluation(numbers, markdown, files, numbers["wall_s"])


def _json_default(obj: object) -> object:
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(type(obj).__name__)


def _tables(sc: Scenario, config: CalibrationEvalConfig, sites: Mapping[str, Site],
            say: Callable[[str], None]) -> tuple[dict[str, Any], dict[str, str]]:
    trajectories = config.table_trajectories or tuple(sc.trajectories)
    unknown = sorted(set(trajectories) - set(sc.trajectories))
    if unknown:
        raise ValueError(f"Table I: unknown trajectories {unknown}; the scenario has "
                         f"{sorted(sc.trajectories)}")
    paper = PaperConfig(experiments=(1,), runs_per_direction=config.table_runs,
                        seed=config.seed, trajectories=trajectories, jobs=config.jobs,
                        scenario_path=config.scenario_path)
    factory = default_fusion_factory()
    world = World(sc)
    detector = make_detector(sc, world, paper)
    numbers: dict[str, Any] = {}
    markdown: dict[str, str] = {}
    for name in SITE_VARIANTS:
        site = sites.get(name)
        if site is None:
            say(f"Table I with {SITE_NAMES[name]}: no site file (its calibration wrote none)")
            continue
        say(f"Table I with {SITE_NAMES[name]}")
        results = run_pose_accuracy(sc, trajectories, paper, factory, world, detector,
                                  lambda line: say("  " + line), service_site=site)
        tables = accuracy_tables(results, factory is not None)
        numbers[name] = {"at_least_2_cameras": accuracy_summary(results),
                         "table1": tables.table1}
        markdown[name] = tables.table1_markdown
        five = numbers[name]["at_least_2_cameras"].get("five_frames", {})
        say(f"  >= 2 cameras, 5 frames: {five.get('t_mean_cm', math.nan):.2f} cm / "
            f"{five.get('r_mean_deg', math.nan):.3f} deg")
    return numbers, markdown


# --------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------


def _f(v: Any, digits: int) -> str:
    return "n/a" if v is None or not math.isfinite(float(v)) else f"{float(v):.{digits}f}"


def _per_camera_rows(numbers: Mapping[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """(method, {camera: {position_cm, rotation_deg}}) of every extrinsic calibration."""
    rows: list[tuple[str, dict[str, Any]]] = [("nominal site file", numbers["nominal"])]
    for anchor, label in (("per_stamp", "board, pose per stamp"),
                          ("one_fixed", "board, one fixed pose")):
        r = numbers["board_extrinsics"]["anchors"].get(anchor, {})
        if "cameras" in r:
            rows.append((label, r["cameras"]))
    rows.append(("start of (a): 20 cm / 3°", numbers["start"]))
    robot = numbers["robot"]
    for name, label in (("robot_from_20cm", "robot (a): from 20 cm / 3°, --frame localization"),
                        ("robot_from_20cm/offset", "robot (a), common offset removed"),
                        ("robot_site_frame", "robot (b): from nominal, --frame site"),
                        ("robot_bumped", "robot (c): bumped camera, --camera")):
        base, _, part = name.partition("/")
        r = robot.get(base, {})
        key = "offset_removed" if part else "cameras"
        if key in r:
            rows.append((label, r[key]))
    return rows


def report_markdown(numbers: Mapping[str, Any], tables_md: Mapping[str, str]) -> str:
    """``calibration.md``: every figure of the evaluation as Markdown tables."""
    lines = [f"# Calibration on the simulated {numbers['scenario']} against the true cameras",
             "", f"Wall time {numbers['wall_s']:.0f} s. Errors are against the simulator's "
             "true camera poses (the site file perturbed by the scenario's calibration error).",
             "", "## Intrinsics from rendered ChArUco views", "",
             "| camera | views used | RMS px | fx % | fy % | cx % | cy % | lens model mean px "
             "| p95 px | max px | coverage |", "|---|" + "---|" * 10]
    for cid, r in numbers["intrinsics"].items():
        e, d = r["error_pct"], r["model_diff_px"]
        lines.append(f"| {cid} | {r['views_used']}/{r['views_rendered']} | {r['rms_px']:.3f} | "
                     f"{e['fx']:+.3f} | {e['fy']:+.3f} | {e['cx']:+.3f} | {e['cy']:+.3f} | "
                     f"{d['mean']:.3f} | {d['p95']:.3f} | {d['max']:.3f} | "
                     f"{100 * r['coverage']:.0f} % |")
    b = numbers["board_extrinsics"]
    lines += ["", "## Camera poses by method (error vs the true pose: cm / deg)", "",
              f"Board walk: {b['board_poses']} board poses, {b['sightings']} usable sightings "
              f"of {b['images']} images. Drive: {numbers['drive']['duration_s']:.0f} s of "
              f"{numbers['drive']['route']}, sightings {numbers['drive']['sightings']}.", ""]
    rows = _per_camera_rows(numbers)
    cams = sorted(numbers["nominal"])
    lines += ["| method | " + " | ".join(cams) + " | worst |", "|---|" + "---|" * (len(cams) + 1)]
    for label, per in rows:
        cells = [f"{per[c]['position_cm']:.2f} / {per[c]['rotation_deg']:.3f}" if c in per
                 else "-" for c in cams]
        worst = (f"{max(v['position_cm'] for v in per.values()):.2f} / "
                 f"{max(v['rotation_deg'] for v in per.values()):.3f}")
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {worst} |")
    lines += ["", "Board std (reported 1-sigma, cm / deg): " + "; ".join(
        f"{anchor}: " + ", ".join(f"{c} {v['std_cm']:.2f} / {v['std_deg']:.3f}"
                                  for c, v in r["cameras"].items())
        for anchor, r in b["anchors"].items() if "cameras" in r), ""]
    lines += ["### The robot-based runs", "",
              "| run | exit | wall s | common map-frame offset | refused | command |",
              "|---|---|---|---|---|---|"]
    for name, r in numbers["robot"].items():
        off = r.get("common_offset")
        off_s = f"{off['shift_cm']:.1f} cm / {off['yaw_deg']:+.3f}°" if off else "-"
        argv = " ".join(Path(a).name if "/" in a else a for a in r["argv"])
        lines.append(f"| {name} | {r['exit_code']} | {r['wall_s']:.1f} | {off_s} | "
                     f"{', '.join(r.get('refused', {})) or '-'} | `{argv}` |")
    lines += ["", "The common offset is the planar motion (x, y, yaw) that best maps the "
              "calibrated camera positions onto the true ones; with `--frame localization` it is "
              "the robot localization's mean error over the drive, which no drive can remove "
              "(docs/calibration.md, \"Which map frame\").", ""]
    if numbers.get("table1"):
        lines += ["## Table I with each site file (simulator: the true cameras)", "",
                  "Mean error at waypoints seen by >= 2 cameras, cm / deg "
                  "(ratio to the true cameras' figure).", "",
                  "| site file given to the backend | " + " | ".join(
                      ROW_NAMES[s] for s in SUMMARY_SOURCES) + " |",
                  "|---|" + "---|" * len(SUMMARY_SOURCES)]
        ref = numbers["table1"].get("true", {}).get("at_least_2_cameras", {})
        for name in SITE_VARIANTS:
            t = numbers["table1"].get(name)
            if t is None:
                continue
            cells = []
            for s in SUMMARY_SOURCES:
                v = t["at_least_2_cameras"].get(s)
                if v is None:
                    cells.append("n/a")
                    continue
                r0 = ref.get(s, {}).get("t_mean_cm")
                ratio = f" ({v['t_mean_cm'] / r0:.2f}x)" if r0 else ""
                cells.append(f"{v['t_mean_cm']:.2f} / {v['r_mean_deg']:.3f}{ratio}")
            lines.append(f"| {SITE_NAMES[name]} | " + " | ".join(cells) + " |")
        for name in SITE_VARIANTS:
            if name in tables_md:
                lines += ["", f"### Table I, {SITE_NAMES[name]}", "", tables_md[name].strip()]
    return "\n".join(lines) + "\n"


def plot_errors(numbers: Mapping[str, Any], path: Path) -> None:
    """Per-camera position and rotation error by method (log scale), and Table I at >= 2
    cameras by site file."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = _per_camera_rows(numbers)
    cams = sorted(numbers["nominal"])
    with_table = bool(numbers.get("table1"))
    fig, axes = plt.subplots(1, 3 if with_table else 2, figsize=(15 if with_table else 10, 4.8),
                             dpi=100)
    colours = plt.get_cmap("tab10")
    width = 0.8 / len(rows)
    for k, (key, unit) in enumerate((("position_cm", "position error, cm"),
                                     ("rotation_deg", "rotation error, deg"))):
        ax = axes[k]
        for j, (label, per) in enumerate(rows):
            xs = [i + (j - len(rows) / 2 + 0.5) * width for i, c in enumerate(cams) if c in per]
            ys = [max(per[c][key], 1e-4) for c in cams if c in per]
            ax.bar(xs, ys, width, color=colours(j % 10), label=label)
        target = 1.5 if k == 0 else 0.15
        ax.axhline(target, color="k", ls="--", lw=0.8)
        ax.text(-0.45, target * 1.12, f"target {target}", fontsize=7)
        ax.set_yscale("log")
        ax.set_xticks(range(len(cams)), cams)
        ax.set_title(f"camera pose vs the truth: {unit}", fontsize=9)
    if with_table:
        ax = axes[2]
        names = [n for n in SITE_VARIANTS if n in numbers["table1"]]
        for j, src in enumerate(SUMMARY_SOURCES):
            ys = [numbers["table1"][n]["at_least_2_cameras"].get(src, {}).get("t_mean_cm",
                                                                              math.nan)
                  for n in names]
            ax.bar(np.arange(len(names)) + (j - 1) * 0.27, ys, 0.27, label=ROW_NAMES[src])
        ax.set_xticks(range(len(names)), [SITE_NAMES[n].split(":")[0].replace(
            " (board pose per stamp)", "") for n in names], rotation=20, fontsize=7, ha="right")
        ax.set_yscale("log")
        ax.set_ylabel("mean translation error, cm (log)")
        ax.set_title("Table I, >= 2 cameras, by site file given to the backend", fontsize=9)
        ax.legend(fontsize=7)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=7)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    fig.savefig(path)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# command line (``smartedge evaluate calibration``)
# --------------------------------------------------------------------------------------------


def config_from_args(args: argparse.Namespace) -> CalibrationEvalConfig:
    """The settings the command line asks for (ValueError on bad values)."""
    changes: dict[str, Any] = {"seed": args.seed, "scenario_path": args.scenario,
                               "jobs": args.jobs, "with_table": not args.no_table}
    if args.drive_s is not None:
        if not args.drive_s > 0:
            raise ValueError("--drive-s must be > 0")
        changes["drive_s"] = args.drive_s
    if args.runs is not None:
        if args.runs < 1:
            raise ValueError("--runs must be >= 1")
        changes["table_runs"] = args.runs
    if args.jobs is not None and args.jobs < 1:
        raise ValueError("--jobs must be >= 1")
    names = tuple(t.strip() for t in args.trajectories.split(",") if t.strip())
    if names:
        changes["table_trajectories"] = names
    if args.quick:
        return CalibrationEvalConfig.quick(**changes)
    return CalibrationEvalConfig(**changes)


def main(args: argparse.Namespace) -> int:
    """Run the evaluation for parsed arguments; print the report. Exit 0, 1 on an error."""
    try:
        config = config_from_args(args)
        result = run_calibration_evaluation(config, args.out,
                                            progress=lambda line: print(line, flush=True))
    except (ValueError, OSError, SmartedgeError) as exc:
        print(f"smartedge evaluate calibration: {exc}", file=sys.stderr, flush=True)
        return 1
    print(result.markdown)
    print(f"wrote {args.out} in {result.wall_s:.0f} s")
    return 0
