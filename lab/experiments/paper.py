"""``smartedge evaluate paper``: the paper's experiments (Sec. IV) on the simulated lab, one after
the other, and the report that collects them.

:func:`run_paper` loads the scenario (with the dwell time and camera rate of the
:class:`~lab.experiments.config.PaperConfig`), builds one world and one detection source
for all runs, runs the experiments ``config.experiments`` names (1: accuracy, 2: correction
feedback, 3: robustness, 4: semantic mapping), writes each one's files and ``report.md`` into
the output folder and returns a :class:`PaperReport`. The independent runs of experiments 1-3
go to ``config.jobs`` worker processes (:mod:`lab.experiments.parallel`), each with its
own world and detection source built the same way; the results do not depend on it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

from lab.experiments.accuracy import (
    RunResult,
    accuracy_tables,
    run_pose_accuracy,
    write_experiment1,
)
from lab.experiments.config import (
    PaperConfig,
    default_fusion_factory,
    describe_detections,
    make_detector,
)
from lab.experiments.feedback import (
    FeedbackRun,
    failure_model,
    feedback_table,
    plot_feedback,
    robustness_table,
    run_correction_feedback,
    run_robustness,
    run_summary,
)
from simulation.scenario import PAPER_SCENARIO, Scenario, load_scenario
from simulation.world import World

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class PaperReport:
    """What :func:`run_paper` produced. The Markdown of an experiment that did not run is
    ``""``, its runs and numbers are empty."""

    #: experiment 1: every run (trajectory, direction, iteration, calibration draw)
    accuracy_runs: list[RunResult]
    #: Table I: translation / heading error at the waypoints by number of cameras
    table1_markdown: str
    #: Table I's numbers: {source: {camera count or "average": {t_mean_cm, t_std_cm,
    #: r_mean_deg, r_std_deg, count}}}
    table1_numbers: dict[str, dict[str, dict[str, float]]]
    #: Table II: RMS translation error per trajectory
    table2_markdown: str
    #: Table II's numbers: {source: {trajectory or "average": RMS translation error, cm}}
    table2_numbers: dict[str, dict[str, float]]
    #: the consistency of the reported covariances (mean NEES per camera count)
    nees_markdown: str
    #: whether the Fused rows had a pose graph
    fusion_available: bool
    #: experiment 2: the long route without and with correction feedback, per seed
    feedback_runs: list[FeedbackRun]
    feedback_markdown: str
    #: experiment 3: the robustness runs without, then with feedback (Table III)
    robustness_runs: list[FeedbackRun]
    robustness_markdown: str
    #: experiment 4: coverage, label accuracy and consistency of the semantic map
    mapping_markdown: str
    #: every file written into the output folder
    files_written: list[Path]
    #: wall-clock time of the whole run, s
    wall_s: float

    def markdown_sections(self) -> list[str]:
        """The tables of the experiments that ran, in the paper's order."""
        return [text for text in (self.table1_markdown, self.table2_markdown,
                                  self.nees_markdown, self.feedback_markdown,
                                  self.robustness_markdown, self.mapping_markdown) if text]


def run_paper(config: PaperConfig, out_dir: str | Path,
              progress: Callable[[str], None] | None = None,
              scenario: Scenario | None = None) -> PaperReport:
    """Run the experiments of ``config`` on ``scenario`` (default: the one ``config`` names)
    and write their files into ``out_dir``: experiment 1 ``table1.md``, ``table2.md``,
    ``nees.md``, ``results.json``, ``samples.csv``, plots and TUM files; experiment 2
    ``experiment2.md`` and Fig. 7; experiment 3 ``table3.md``; 2 or 3
    ``feedback_results.json``; experiment 4 the map files; always ``report.md``.
    ``progress`` gets one line per run (default: the log)."""
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
        results = run_pose_accuracy(sc, names, config, factory, world, detector, say)
        tables = accuracy_tables(results, fusion_available, config.align)
        t1_md, t1 = tables.table1_markdown, tables.table1
        t2_md, t2 = tables.table2_markdown, tables.table2
        nees_md = tables.nees_markdown
        files += write_experiment1(out, sc, config, results, tables, detector)
    fb_runs: list[FeedbackRun] = []
    fb_md = ""
    fb_numbers: dict[str, float] = {}
    if 2 in config.experiments:
        say(f"paper experiment 2: {config.long_route} without and with correction feedback, "
            f"{config.feedback_seeds} seed(s)")
        fb_runs = run_correction_feedback(sc, config, factory, world, detector, say)
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
        rb_runs = run_robustness(sc, config, factory, world, detector, say)
        rb_md, rb_numbers = robustness_table(rb_runs)
        (out / "table3.md").write_text(rb_md, encoding="utf-8")
        files.append(out / "table3.md")
    map_md = ""
    if 4 in config.experiments:
        # open3d and the renderer are imported only when the mapping experiment runs
        from lab.experiments.mapping import run_semantic_mapping

        map_md, map_files = run_semantic_mapping(sc, config, factory, world, detector, out, say)
        files += map_files
    if 2 in config.experiments or 3 in config.experiments:
        (out / "feedback_results.json").write_text(json.dumps({
            "scenario": sc.name, "seed": config.seed, "experiment2": fb_numbers,
            "experiment2_runs": [run_summary(r) for r in fb_runs],
            "experiment3": rb_numbers,
            "experiment3_runs": [run_summary(r) for r in rb_runs],
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
    return PaperReport(
        accuracy_runs=results, table1_markdown=t1_md, table1_numbers=t1,
        table2_markdown=t2_md, table2_numbers=t2, nees_markdown=nees_md,
        fusion_available=fusion_available, feedback_runs=fb_runs, feedback_markdown=fb_md,
        robustness_runs=rb_runs, robustness_markdown=rb_md, mapping_markdown=map_md,
        files_written=files, wall_s=wall)
