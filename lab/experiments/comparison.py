"""The paper's reference figures, and finished runs of ``smartedge evaluate paper`` side by side
with them (``smartedge evaluate compare``).

The figures are the paper's (ICRA 2023): Table I (translation / heading error at the waypoints
by number of cameras), experiment 2 (RMS translation error with and without correction
feedback), Table III (robustness) and the map coverage of Sec. IV-C. The experiments' own
tables print them next to the measured values; :func:`compare_markdown` reads the
``results.json`` / ``feedback_results.json`` of finished output folders.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Final

#: experiment 2 (Sec. IV-B, Fig. 7): RMS translation error (cm) over the whole route (3x
#: Traj. 3) of the robot's localization without and with correction feedback, and fused
PAPER_EXP2_ROBOT_WITHOUT_FEEDBACK_CM: Final = 17.5
PAPER_EXP2_ROBOT_WITH_FEEDBACK_CM: Final = 5.51
PAPER_EXP2_FUSED_CM: Final = 3.34
#: Table III (Sec. IV-D): runs of the cluttered route per condition, and the outcomes
#: (waypoint not reached, emergency stop, success) without and with correction feedback
PAPER_TABLE3_RUNS: Final = 5
PAPER_TABLE3_WITHOUT_FEEDBACK: Final = (3, 1, 1)
PAPER_TABLE3_WITH_FEEDBACK: Final = (0, 0, 5)
#: Table III: mean travelled distance (m) at a failure without feedback
PAPER_TABLE3_FAILURE_DISTANCE_M: Final = 38
#: Sec. IV-C: share of the surfaces with semantic information, static sensors alone (~50 %)
#: and after the robot's exploration (> 90 %)
PAPER_COVERAGE: Final = {"static": 0.50, "with_robot": 0.90}

#: the headline figures of :func:`compare_markdown` (Table I average row / per camera count,
#: Table II, experiments 2 and 3)
PAPER_FIGURES: Final[dict[str, str]] = {
    "Robot (avg)": "19.1 cm / 1.11°",
    "Cameras (raw), 1 cam": "13.8 cm / 3.39°",
    "Cameras (raw), 2 cams": "2.59 cm / 0.97°",
    "Cameras (raw), 4 cams": "2.88 cm / 1.02°",
    "Cameras (5 frames), 1 cam": "7.77 cm",
    "Cameras (5 frames), >= 2 cams": "2.58 cm / 0.86°",
    "Fused (avg)": "2.93 cm / 0.88°",
    "Table II Fused Avg.": "n/a",
    "Exp. 2 robot w/o / w/ feedback":
        f"{PAPER_EXP2_ROBOT_WITHOUT_FEEDBACK_CM:g} / {PAPER_EXP2_ROBOT_WITH_FEEDBACK_CM:g} cm",
    "Exp. 2 fused": f"{PAPER_EXP2_FUSED_CM:g} cm",
    "Table III w/ feedback success": f"{PAPER_TABLE3_WITH_FEEDBACK[2]} / {PAPER_TABLE3_RUNS}",
}


def paper_table3_outcomes(with_feedback: bool) -> str:
    """The paper's Table III row as ``"3/5, 1/5, 1/5"`` (WP not reached, emergency stop,
    success)."""
    counts = PAPER_TABLE3_WITH_FEEDBACK if with_feedback else PAPER_TABLE3_WITHOUT_FEEDBACK
    return ", ".join(f"{n}/{PAPER_TABLE3_RUNS}" for n in counts)


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
