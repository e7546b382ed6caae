"""``smartedge evaluate``: trajectory metrics and the paper's experiments.

::

    smartedge evaluate ate GT.tum EST.tum [--align] [--correct-scale] [--max-diff S]
    smartedge evaluate ate GT.tum REC.mcap --est-key smartedge/SITE/robot/ID/pose [--align]
    smartedge evaluate paper --out DIR [--runs N] [--seed S] [--trajectories 1,2,3]
                             [--experiments 1,2,3,4] [--feedback-seeds K] [--robustness-runs R]
                             [--detections noise|cnn] [--camera-rate HZ] [--model DIR] [--jobs N]
    smartedge evaluate keypoints --dataset LABELS.json [--images DIR] [--count N]
    smartedge evaluate keypoints [--model DIR] [--seed S] [--count N] [--calibrate] [--flip]
                                 [--detector-flip] [--breakdown] [--held-out-variations]
                                 [--far-band] [--record]
    smartedge evaluate keypoint-choice [--scenario FILE] [--sigma-px PX] [--add N] [--pairs]
    smartedge evaluate fleet [--robots N] [--runs N] [--seed S] [--out DIR] [--quick]
                             [--no-feedback] [--min-sigma-m M] [--types]
    smartedge evaluate compare NAME=DIR [NAME=DIR ...]
    smartedge evaluate calibration --out DIR [--quick] [--runs N] [--drive-s S] [--no-table]

``ate`` prints the APE statistics of ``evo_ape tum GT.tum EST.tum --align`` (translation part,
metres); ``paper`` runs the simulated experiments of Sec. IV (:mod:`lab.experiments`)
and writes Table I / Table II (Markdown) and Fig. 6-like plots (PNG) into DIR (detections from
the noise model, or with ``--detections cnn`` from rendered images through the edge's ONNX
models), then experiment 2
(correction feedback on 3x Traj. 3, Fig. 7), experiment 3 (robustness, Table III), experiment 4
(collaborative semantic mapping: coverage from the static cameras alone and after the robot's
route, label accuracy, consistency with and without feedback, a top-down map), and
``report.md`` with all four.
``keypoints`` renders a fresh held-out set (seed S, N views each of randomized scenes and of the
site's cameras) and prints the detector's AP@0.5 and the keypoint errors of the ONNX models
(default: the shipped ones), one figure per line with its name; with
``--held-out-variations`` N views rendered with settings never used in training
(:data:`simulation.scenes.HELD_OUT_VARIATION`) instead: detector recall per distance band,
false detections per image, AP@0.5, keypoint median error and PCK@2/5px; ``--record`` also
writes the figures into the evaluated models' cards.
``fleet`` drives N identical robots on crossing routes through the backend's pipeline (unnamed
detections assigned to robots) with correction feedback, and each robot alone with the same
seed (:mod:`lab.experiments.fleet`): identity switches, wrong-robot detections and
corrections, unassigned/ambiguous detections, per-robot ATE against the robot alone;
``--types``: two types (two HSR-like robots and a box base) with typed detections, and the same
fleet with the types stripped as the comparison (wrong-type detections, ambiguous counts).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from core.trajectory import Trajectory, TrajectoryFileError, read_tum
from lab.evaluation.metrics import ape, format_stats
from protocol.errors import SmartedgeError


def _trajectory(path: str, key: str | None) -> Trajectory:
    """A TUM file, or with ``key`` the poses of that key / topic of an MCAP recording."""
    if key is None:
        if path.endswith(".mcap"):
            raise TrajectoryFileError(path, None, "a recording: name the poses with --gt-key / "
                                      "--est-key (a smartedge key or a ROS pose topic)")
        return read_tum(path)
    from smartedge.commands.export import read_poses

    return read_poses(path, key)


def _ate(args: argparse.Namespace) -> int:
    try:
        ref = _trajectory(args.gt, args.gt_key)
        est = _trajectory(args.est, args.est_key)
        result = ape(
            ref, est, align=args.align, correct_scale=args.correct_scale, max_diff_s=args.max_diff
        )
    except SmartedgeError as exc:  # file, recording, key or metrics problems, named
        print(f"smartedge evaluate ate: {exc}", file=sys.stderr)
        return 1
    if args.align and args.correct_scale:
        how = "(with Sim(3) Umeyama alignment)"
    elif args.align:
        how = "(with SE(3) Umeyama alignment)"
    elif args.correct_scale:
        how = "(scale corrected)"
    else:
        how = "(not aligned)"
    print(f"APE w.r.t. translation part (m)\n{how}\n")
    print(format_stats(result.translation_stats))
    print(f"\nmatched poses: {len(result.ref_index)}")
    if args.correct_scale:
        print(f"scale correction: {result.alignment.scale:.6f}")
    print("\nAPE w.r.t. rotation angle (deg)\n")
    print(format_stats(result.rotation_stats_deg))
    return 0


def _paper(args: argparse.Namespace) -> int:
    from lab.experiments import PaperConfig, run_paper

    trajectories = tuple(t.strip() for t in args.trajectories.split(",") if t.strip())
    try:
        experiments = tuple(sorted({int(e) for e in args.experiments.split(",") if e.strip()}))
    except ValueError:
        experiments = ()
    if not experiments or not set(experiments) <= {1, 2, 3, 4}:
        print("smartedge evaluate paper: --experiments takes a list of 1, 2, 3, 4",
              file=sys.stderr)
        return 2
    calibration_seeds = None
    if args.calibration_seeds:
        try:
            calibration_seeds = tuple(int(v) for v in args.calibration_seeds.split(",")
                                      if v.strip())
        except ValueError:
            calibration_seeds = ()
        if not calibration_seeds:
            print("smartedge evaluate paper: --calibration-seeds takes a list of integers",
                  file=sys.stderr)
            return 2
    config = PaperConfig(
        experiments=experiments,
        feedback_seeds=args.feedback_seeds,
        robustness_runs=args.robustness_runs,
        runs_per_direction=args.runs,
        seed=args.seed,
        trajectories=trajectories or None,
        scenario_path=args.scenario,
        stop_s=args.stop_s,
        detections=args.detections,
        camera_rate_hz=args.camera_rate,
        model_dir=args.model,
        threads=args.threads,
        far_band=args.far_band,
        sensor_noise_dn=args.sensor_noise,
        calibration_seeds=calibration_seeds,
        jobs=args.jobs,
    )
    try:
        report = run_paper(config, args.out, progress=lambda line: print(line, flush=True))
    except (ValueError, OSError, SmartedgeError) as exc:
        print(f"smartedge evaluate paper: {exc}", file=sys.stderr)
        return 1
    for text in report.markdown_sections():
        print(text)
    print(f"wrote {args.out}")
    return 0


def _compare(args: argparse.Namespace) -> int:
    from pathlib import Path

    from lab.experiments import compare_markdown

    runs = []
    for spec in args.runs:
        name, sep, folder = spec.partition("=")
        if not sep:
            name, folder = Path(spec).name, spec
        if not (Path(folder) / "results.json").exists() and \
                not (Path(folder) / "feedback_results.json").exists():
            print(f"smartedge evaluate compare: {folder}: no results.json or "
                  "feedback_results.json (an `evaluate paper --out` folder?)", file=sys.stderr)
            return 1
        runs.append((name, folder))
    print(compare_markdown(runs, with_paper=not args.no_paper), end="")
    return 0


def _keypoints(args: argparse.Namespace) -> int:
    from edge_agent.model_cards import ModelError
    from lab.evaluation.keypoints import evaluate_keypoints

    if args.dataset:
        return _keypoints_on_dataset(args)
    if args.count < 1:
        print("smartedge evaluate keypoints: --count must be >= 1", file=sys.stderr)
        return 2
    if args.record and args.calibrate:
        print("smartedge evaluate keypoints: --record writes evaluation figures; --calibrate "
              "writes its table into the keypoint card by itself", file=sys.stderr)
        return 2
    if args.held_out_variations:
        from lab.evaluation.keypoints import evaluate_held_out_variations
        from simulation.scenes import RandomizationError

        try:
            held = evaluate_held_out_variations(args.model, seed=args.seed, count=args.count,
                                                scenario_path=args.scenario,
                                                threads=args.threads, flip=args.flip,
                                                detector_flip=args.detector_flip,
                                                far_band=args.far_band,
                                                progress=lambda line: print(line, flush=True))
        except (ModelError, OSError, ValueError, RandomizationError) as exc:
            print(f"smartedge evaluate keypoints: {exc}", file=sys.stderr)
            return 1
        for line in held.lines():
            print(line)
        print(f"({held.views} views in {held.wall_s:.0f} s)")
        if args.record:
            return _record(args, {"held-out renderer variations": held.figures}, held.views)
        return 0
    if args.calibrate:
        from lab.evaluation.keypoints import calibrate_keypoints

        try:
            calibrate_keypoints(args.model, count=args.count, scenario_path=args.scenario,
                                threads=args.threads,
                                progress=lambda line: print(line, flush=True))
        except (ModelError, OSError, ValueError) as exc:
            print(f"smartedge evaluate keypoints: {exc}", file=sys.stderr)
            return 1
        return 0
    try:
        result = evaluate_keypoints(args.model, seed=args.seed, count=args.count,
                                    scenario_path=args.scenario, threads=args.threads,
                                    flip=args.flip, detector_flip=args.detector_flip,
                                    breakdown=args.breakdown, far_band=args.far_band,
                                    progress=lambda line: print(line, flush=True))
    except (ModelError, OSError, ValueError) as exc:
        print(f"smartedge evaluate keypoints: {exc}", file=sys.stderr)
        return 1
    for line in result.lines():
        print(line)
    print(f"({result.views} views in {result.wall_s:.0f} s)")
    if args.record:
        return _record(args, result.figures, result.views)
    return 0


def _keypoints_on_dataset(args: argparse.Namespace) -> int:
    """``--dataset``: the figures on a lab's labelled frames, beside the same on ``--count``
    rendered views of the site's cameras (0: none)."""
    from pathlib import Path

    from core.coco import DatasetError
    from edge_agent.model_cards import ModelError
    from lab.evaluation.keypoints import evaluate_keypoints, evaluate_on_dataset, format_figure

    if args.count < 0 or args.record or args.calibrate or args.held_out_variations:
        print("smartedge evaluate keypoints: --dataset takes --count >= 0 (rendered views "
              "beside it) and none of --record, --calibrate, --held-out-variations",
              file=sys.stderr)
        return 2
    try:
        figures, skipped, frames = evaluate_on_dataset(
            Path(args.dataset), args.model, image_root=Path(args.images) if args.images else None,
            category=args.category, threads=args.threads, flip=args.flip,
            detector_flip=args.detector_flip)
        rendered: dict[str, float] = {}
        if args.count:
            print(f"rendering {args.count} held-out views of the site's cameras (seed "
                  f"{args.seed}) for comparison", flush=True)
            rendered = evaluate_keypoints(args.model, seed=args.seed, count=args.count,
                                          modes=("site",), scenario_path=args.scenario,
                                          threads=args.threads, flip=args.flip,
                                          detector_flip=args.detector_flip).figures["site"]
    except (DatasetError, ModelError, OSError, ValueError) as exc:
        print(f"smartedge evaluate keypoints: {exc}", file=sys.stderr)
        return 1
    for why, names in skipped.items():
        for name in names:
            print(f"skipped ({why}): {name}", file=sys.stderr)
    print(f"{'figure':58s} {'dataset':>10s}" + (f" {'rendered':>10s}" if rendered else ""))
    for name in dict.fromkeys([*figures, *rendered]):
        row = f"{name:58s} {format_figure(figures.get(name, float('nan'))):>10s}"
        if rendered:
            row += f" {format_figure(rendered.get(name, float('nan'))):>10s}"
        print(row)
    left_out = sum(len(v) for v in skipped.values())
    print(f"({frames} dataset frames{f', {left_out} left out (named above)' if left_out else ''}"
          f"{f'; {args.count} rendered views' if rendered else ''})")
    return 0


def _record(args: argparse.Namespace, figures: dict[str, dict[str, float]], views: int) -> int:
    """``--record``: the figures into the evaluated models' cards, named by what ran."""
    from pathlib import Path

    from edge_agent.model_cards import ModelError
    from lab.evaluation.keypoints import record_evaluation

    what = ("held-out renderer variations" if args.held_out_variations
            else "randomized and site views")
    name = f"{what}, seed {args.seed}"
    command = ["smartedge evaluate keypoints"]
    if args.model:
        command.append("--model DIR")
    if args.held_out_variations:
        command.append("--held-out-variations")
    command += [f"--seed {args.seed}", f"--count {args.count}"]
    for flag, value in (("flip", args.flip), ("detector-flip", args.detector_flip)):
        if value is not None:
            command.append(f"--{'' if value else 'no-'}{flag}")
            name += f", {'with' if value else 'without'} the {flag.replace('-', ' ')}"
    if args.far_band:
        command.append("--far-band")
        name += ", with the far band"
    if args.scenario:
        command.append("--scenario FILE")
        name += f", scenario {Path(args.scenario).name}"
    try:
        written = record_evaluation(Path(args.model) if args.model else None, name,
                                    " ".join([*command, "--record"]), figures, views)
    except (ModelError, OSError) as exc:
        print(f"smartedge evaluate keypoints: --record: {exc}", file=sys.stderr)
        return 1
    for path in written:
        print(f"recorded as {name!r} in {path} (and its .md)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smartedge evaluate",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="what", metavar="WHAT", required=True)
    p_ate = sub.add_parser("ate", help="absolute trajectory error of EST against GT (TUM files "
                           "or MCAP recordings)")
    p_ate.add_argument("gt", help="reference trajectory (TUM, or MCAP with --gt-key)")
    p_ate.add_argument("est", help="estimated trajectory (TUM, or MCAP with --est-key)")
    p_ate.add_argument("--gt-key", default=None,
                       help="GT is a recording: its key or ROS pose topic (e.g. the mocap's)")
    p_ate.add_argument("--est-key", default=None,
                       help="EST is a recording: its key, e.g. smartedge/SITE/robot/ID/pose")
    p_ate.add_argument("--align", "-a", action="store_true", help="SE(3) Umeyama alignment")
    p_ate.add_argument(
        "--correct-scale", "-s", action="store_true", help="also estimate a scale (Sim(3))"
    )
    p_ate.add_argument(
        "--max-diff",
        type=float,
        default=0.01,
        help="max. stamp difference for associating poses, s (default 0.01)",
    )
    p_paper = sub.add_parser("paper", help="the paper's experiments on the simulated site")
    p_paper.add_argument("--out", required=True, help="output folder for tables and plots")
    p_paper.add_argument(
        "--runs", type=int, default=3, help="iterations of each trajectory and direction (paper: 3)"
    )
    p_paper.add_argument("--seed", type=int, default=0, help="base random seed")
    p_paper.add_argument(
        "--trajectories",
        default="",
        help="comma-separated trajectory names (default: all of the scenario)",
    )
    p_paper.add_argument(
        "--scenario",
        default=None,
        help="scenario file (default: simulation/sites/paper_lab.scenario.yaml)",
    )
    p_paper.add_argument(
        "--stop-s", type=float, default=None, help="override the dwell time at each waypoint, s"
    )
    p_paper.add_argument(
        "--experiments", default="1,2,3,4",
        help="which experiments: 1 Table I/II, 2 correction feedback (Fig. 7), "
        "3 robustness (Table III), 4 semantic mapping (Sec. IV-C); default 1,2,3,4",
    )
    p_paper.add_argument(
        "--feedback-seeds", type=int, default=1,
        help="experiment 2: seeds (each run without and with feedback; paper: 1)",
    )
    p_paper.add_argument(
        "--robustness-runs", type=int, default=None,
        help="experiment 3: runs per condition (default: the scenario's, paper: 5)",
    )
    p_paper.add_argument(
        "--detections", choices=("noise", "cnn"), default="noise",
        help="noise: the scenario's detector error model (default); cnn: every camera frame "
        "rendered and run through the edge's ONNX detector + keypoint models (the closed loop; "
        "about 20 min for experiment 1 on 2 cores)")
    p_paper.add_argument(
        "--camera-rate", type=float, default=None, metavar="HZ",
        help="camera frame rate (default: the scenario's, 15 Hz; 5 Hz with --detections cnn)")
    p_paper.add_argument("--model", default=None, metavar="DIR",
                         help="--detections cnn: a folder with other detector + keypoint models")
    p_paper.add_argument("--threads", type=int, default=2,
                         help="--detections cnn: onnxruntime threads (default 2)")
    p_paper.add_argument("--far-band", action=argparse.BooleanOptionalAction, default=False,
                         help="--detections cnn: with each camera's far band (the edge agent's "
                         "--far-band on) or without (default: as the edge on the CPU)")
    p_paper.add_argument("--sensor-noise", type=float, default=None, metavar="DN",
                         help="--detections cnn: per-frame image noise, digital numbers of "
                         "0-255 (default 2)")
    p_paper.add_argument(
        "--calibration-seeds", default=None, metavar="S1,S2,...",
        help="experiment 1: draw the cameras' calibration error with each seed and pool the "
        "runs (default: the scenario's one draw); the NEES of a covariance with a calibration "
        "term is an expectation over such draws")
    p_paper.add_argument(
        "--jobs", type=int, default=None, metavar="N",
        help="experiments 1-3: worker processes for their independent runs (default: one "
        "per core; 1: all in this process); the tables do not depend on it")
    p_kp = sub.add_parser("keypoints", help="detector AP and keypoint errors of the ONNX "
                          "models on fresh held-out renders")
    p_kp.add_argument("--model", help="model folder (default: the shipped models)")
    p_kp.add_argument("--dataset", metavar="DATASET.json",
                      help="instead: a lab's labelled frames (COCO keypoints, smartedge "
                      "dataset), beside --count rendered views of the site's cameras (0: none)")
    p_kp.add_argument("--images", metavar="DIR", help="with --dataset: the folder its file "
                      "names are relative to (default: the dataset file's)")
    p_kp.add_argument("--category", help="with --dataset: the robot model to score (default: "
                      "the file's only one)")
    p_kp.add_argument("--seed", type=int, default=4242,
                      help="held-out seed (default 4242; the shipped models trained on 1-2)")
    p_kp.add_argument("--count", type=int, default=300,
                      help="views per set: randomized scenes and the site's cameras (default 300)")
    p_kp.add_argument("--scenario", default=None, help="scenario file (default: the paper's lab)")
    p_kp.add_argument("--threads", type=int, default=2, help="onnxruntime threads (default 2)")
    p_kp.add_argument("--flip", action=argparse.BooleanOptionalAction, default=None,
                      help="with (--flip) or without (--no-flip) the keypoint network's "
                      "test-time flip augmentation (default: as the model's card says)")
    p_kp.add_argument("--detector-flip", action=argparse.BooleanOptionalAction, default=None,
                      help="the same for the detector (default: as its card says)")
    p_kp.add_argument("--far-band", action=argparse.BooleanOptionalAction, default=False,
                      help="with each view's camera's far band (the edge agent's --far-band "
                      "on) or without (default: as the edge on the CPU)")
    p_kp.add_argument("--breakdown", action="store_true", help="also per keypoint (bias, "
                      "spread) and per distance (common shift and scale, the rest)")
    p_kp.add_argument("--held-out-variations", action="store_true",
                      help="instead: the held-out renderer variations (settings never used in "
                      "training: other textures, occluders, lens, light; "
                      "simulation.scenes.HELD_OUT_VARIATION): recall by distance band, false "
                      "detections per image, AP@0.5, keypoint errors")
    p_kp.add_argument("--record", action="store_true",
                      help="also write the figures into the evaluated models' cards (.json "
                      "and .md; the detector's figures into its card, the keypoint figures "
                      "into the keypoint network's), named by the set, seed and options; an "
                      "earlier evaluation of the same name is replaced")
    p_kp.add_argument("--calibrate", action="store_true",
                      help="instead: measure the confidence -> pixel error table on the "
                      "validation seeds (1001/1002) and write it into the keypoint model's card "
                      "(the edge then sends per-keypoint sigmas)")
    p_cal = sub.add_parser("calibration", help="the site calibration (intrinsics, board "
                           "extrinsics, the robot as the target) against the simulator's true "
                           "cameras, and Table I with each calibrated site file")
    p_cal.add_argument("--out", required=True, help="output folder (report, picture, site "
                       "files, the drive's recording)")
    p_cal.add_argument("--quick", action="store_true",
                       help="one camera's intrinsics, a short board walk, a 90 s drive, Table I "
                       "on traj1 only")
    p_cal.add_argument("--seed", type=int, default=0, help="base seed (default 0)")
    p_cal.add_argument("--scenario", default=None,
                       help="scenario file (default: the paper's lab)")
    p_cal.add_argument("--drive-s", type=float, default=None,
                       help="seconds of the robot's calibration drive (default 300; --quick 90)")
    p_cal.add_argument("--runs", type=int, default=None,
                       help="Table I: runs of each trajectory and direction (default 1)")
    p_cal.add_argument("--trajectories", default="",
                       help="Table I: comma-separated trajectories (default: all; --quick traj1)")
    p_cal.add_argument("--no-table", action="store_true", help="skip Table I")
    p_cal.add_argument("--jobs", type=int, default=None,
                       help="Table I: worker processes (default: one per core)")
    p_kc = sub.add_parser("keypoint-choice", help="which keypoints on the robot's rigid base "
                          "make its heading observable (Cramer-Rao, leave one out, candidates "
                          "added greedily)")
    p_kc.add_argument("--scenario", default=None, help="scenario file (default: the paper's lab; "
                      "its stop poses at 8 headings each, its site's cameras)")
    p_kc.add_argument("--sigma-px", type=float, default=0.5,
                      help="pixel noise per keypoint (default 0.5, the shipped network's "
                      "held-out median error)")
    p_kc.add_argument("--add", type=int, default=4, help="candidates to add (default 4)")
    p_kc.add_argument("--pairs", action="store_true", help="add candidates in left/right "
                      "mirror pairs, as a keypoint network trained on mirrored crops needs")
    p_fl = sub.add_parser("fleet", help="identical robots crossing paths: identity switches, "
                          "wrong-robot corrections, per-robot ATE against the robot alone")
    p_fl.add_argument("--robots", type=int, default=3, help="robots (1-3, default 3)")
    p_fl.add_argument("--runs", type=int, default=3, help="seeds (default 3)")
    p_fl.add_argument("--seed", type=int, default=3, help="first seed (default 3)")
    p_fl.add_argument("--out", default=None, help="folder for report.md, fleet_results.json "
                      "and fleet_routes.png (default: print only)")
    p_fl.add_argument("--quick", action="store_true", help="one seed, the first 12 simulated "
                      "seconds (the robots' closest approaches)")
    p_fl.add_argument("--no-feedback", action="store_true",
                      help="no correction feedback through the robot bridges")
    p_fl.add_argument("--min-sigma-m", type=float, default=None, metavar="M",
                      help="floor on every robot's predicted position uncertainty (a stress "
                      "test: vaguer predictions leave more detections ambiguous)")
    p_fl.add_argument("--types", action="store_true",
                      help="two robot types: the last robot a box base (box_c), detections "
                      "typed; also the same fleet untyped as the comparison")
    p_cmp = sub.add_parser("compare", help="side-by-side headline figures of finished "
                           "`evaluate paper` runs (Markdown)")
    p_cmp.add_argument("runs", nargs="+", metavar="NAME=DIR",
                       help="a column: its name and an `evaluate paper --out` folder")
    p_cmp.add_argument("--no-paper", action="store_true", help="omit the paper's column")
    return parser


def _keypoint_choice(args: argparse.Namespace) -> int:
    from backend_service.pipeline_config import PipelineConfig
    from lab.evaluation.keypoint_choice import (
        format_budget,
        format_choice,
        heading_budget,
        keypoint_choice,
        stop_poses,
    )
    from simulation.scenario import PAPER_SCENARIO, load_scenario

    if not args.sigma_px > 0 or args.add < 0:
        print("smartedge evaluate keypoint-choice: --sigma-px must be > 0 and --add >= 0",
              file=sys.stderr)
        return 2
    try:
        scenario = load_scenario(args.scenario or PAPER_SCENARIO)
        site = scenario.site
        cameras = [site.camera(c) for c in sorted(site.cameras)]
        poses = stop_poses([(w.x, w.y, w.theta) for w in scenario.waypoints.values()])
        choice = keypoint_choice(cameras, site.robot_model(scenario.robot_id), poses,
                                 sigma_px=args.sigma_px, add=args.add, pairs=args.pairs)
    except (SmartedgeError, ValueError) as exc:
        print(f"smartedge evaluate keypoint-choice: {exc}", file=sys.stderr)
        return 1
    errors = PipelineConfig.from_site(site).solver.error_model  # the site's pose: section
    budget = heading_budget(cameras, site.robot_model(scenario.robot_id), poses,
                            sigma_px=args.sigma_px, errors=errors)
    print(format_choice(choice))
    print(format_budget(budget, errors, args.sigma_px))
    return 0


def _fleet(args: argparse.Namespace) -> int:
    import time
    from pathlib import Path

    from lab.experiments.fleet import (
        QUICK_UNTIL_S,
        FleetConfig,
        fleet_table,
        run_fleet,
        write_report,
    )
    from simulation.scenario import load_scenario

    try:
        config = FleetConfig(robots=args.robots, runs=1 if args.quick else args.runs,
                             seed=args.seed, until_s=QUICK_UNTIL_S if args.quick else None,
                             feedback=not args.no_feedback,
                             min_sigma_xy_m=args.min_sigma_m, types=args.types)
    except ValueError as exc:
        print(f"smartedge evaluate fleet: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    try:
        scenario = load_scenario()
        results = run_fleet(config, scenario, say=lambda line: print(line, flush=True))
    except (SmartedgeError, ValueError) as exc:
        print(f"smartedge evaluate fleet: {exc}", file=sys.stderr)
        return 1
    table, _numbers = fleet_table(results)
    print(table)
    if args.out:
        report, _ = write_report(results, scenario, Path(args.out), config)
        print(f"wrote {report}")
    print(f"{time.perf_counter() - t0:.1f} s")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    if args.what == "ate":
        return _ate(args)
    if args.what == "keypoints":
        return _keypoints(args)
    if args.what == "compare":
        return _compare(args)
    if args.what == "keypoint-choice":
        return _keypoint_choice(args)
    if args.what == "fleet":
        return _fleet(args)
    if args.what == "calibration":
        from lab.experiments.calibration import main as calibration_main

        return calibration_main(args)
    if args.runs < 1 or args.feedback_seeds < 1 or (
            args.robustness_runs is not None and args.robustness_runs < 1) or (
            args.jobs is not None and args.jobs < 1):
        print("smartedge evaluate paper: --runs, --feedback-seeds, --robustness-runs and "
              "--jobs must be >= 1", file=sys.stderr)
        return 2
    return _paper(args)


if __name__ == "__main__":
    raise SystemExit(main())
