"""``smartedge evaluate compare``: headline figures of finished runs side by side."""

from __future__ import annotations

import json
from pathlib import Path

from lab.evaluate import main
from lab.experiments import compare_markdown


def _group(t: float, r: float, n: int) -> dict[str, float]:
    return {"t_mean_cm": t, "t_std_cm": 0.0, "r_mean_deg": r, "r_std_deg": 0.0, "count": n}


def _run(folder: Path, scale: float) -> Path:
    folder.mkdir()
    t1 = {src: {"1": _group(10 * scale, 2.0, 4), "2": _group(2 * scale, 1.0, 6),
                "4": _group(1 * scale, 0.5, 2), "average": _group(3 * scale, 1.0, 12)}
          for src in ("robot", "raw", "one_frame", "five_frames", "fused")}
    (folder / "results.json").write_text(json.dumps(
        {"table1": t1, "table2": {"fused": {"average": 4.0 * scale}}}))
    (folder / "feedback_results.json").write_text(json.dumps({
        "experiment2": {"robot_without_feedback_cm": 30.0, "robot_with_feedback_cm": 10.0,
                        "fused_cm": 2.0 * scale},
        "experiment3": {"with_feedback": {"success": 4, "runs": 5}}}))
    return folder


def test_columns_rows_and_the_weighted_multi_camera_mean(tmp_path: Path) -> None:
    a, b = _run(tmp_path / "a", 1.0), _run(tmp_path / "b", 2.0)
    md = compare_markdown([("noise", a), ("cnn", b)])
    lines = md.splitlines()
    assert lines[0] == "| figure | paper | noise | cnn |"
    row = next(ln for ln in lines if ln.startswith("| Cameras (5 frames), >= 2 cams |"))
    # (2 cm x 6 + 1 cm x 2) / 8 = 1.75 cm; (1.0 x 6 + 0.5 x 2) / 8 = 0.875 deg
    assert "| 1.75 cm / 0.88° | 3.50 cm / 0.88° |" in row and "2.58 cm / 0.86°" in row
    assert "| Table II Fused Avg. | n/a | 4.00 cm | 8.00 cm |" in md
    assert "| Table III w/ feedback success | 5 / 5 | 4 / 5 | 4 / 5 |" in md
    assert "paper" not in compare_markdown([("noise", a)], with_paper=False).splitlines()[0]


def test_cli_prints_the_table_and_refuses_other_folders(tmp_path: Path, capsys) -> None:
    a = _run(tmp_path / "a", 1.0)
    assert main(["compare", f"noise={a}", str(a)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("| figure | paper | noise | a |")
    assert main(["compare", f"x={tmp_path}"]) == 1
    assert "no results.json" in capsys.readouterr().err
