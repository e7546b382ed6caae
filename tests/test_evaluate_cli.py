"""``smartedge evaluate``: ate prints evo's APE numbers; paper writes tables and plots."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core.geometry import rotation_z
from core.trajectory import Trajectory, write_tum
from lab.evaluate import main


def _write_pair(tmp_path: Path) -> tuple[Path, Path]:
    rng = np.random.default_rng(4)
    t = np.arange(300) * 0.1
    xyth = np.column_stack([np.cos(0.1 * t) * 4, np.sin(0.13 * t) * 3, 0.2 * t])
    gt = Trajectory.from_planar(t, xyth)
    noisy = xyth + rng.normal(0, [0.05, 0.05, 0.01], xyth.shape)
    noisy[:, :2] = noisy[:, :2] @ rotation_z(0.5)[:2, :2].T + [1.0, -2.0]
    noisy[:, 2] += 0.5
    est = Trajectory.from_planar(t[::2] + 0.003, noisy[::2])
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", est)
    return tmp_path / "gt.tum", tmp_path / "est.tum"


def _stats(text: str) -> dict[str, float]:
    section = text.split("APE w.r.t. rotation")[0]
    return {
        m.group(1): float(m.group(2))
        for m in re.finditer(
            r"^\s*(max|mean|median|min|rmse|sse|std)\s+([-\d.e+]+)\s*$", section, re.M
        )
    }


def test_ate_matches_evo_ape_cli(tmp_path: Path, capsys) -> None:
    gt, est = _write_pair(tmp_path)
    assert main(["ate", str(gt), str(est), "--align"]) == 0
    ours = _stats(capsys.readouterr().out)
    evo_ape = Path(sys.executable).with_name("evo_ape")
    if not evo_ape.exists():
        pytest.skip("evo_ape not installed next to this python")
    proc = subprocess.run(
        [str(evo_ape), "tum", str(gt), str(est), "--align"],
        capture_output=True,
        text=True,
        timeout=60,
        env={"HOME": str(tmp_path), "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"},
    )
    assert proc.returncode == 0, proc.stderr
    theirs = _stats(proc.stdout)
    assert set(theirs) == {"max", "mean", "median", "min", "rmse", "sse", "std"}
    for key, value in theirs.items():
        assert ours[key] == pytest.approx(value, abs=1e-6), key


def test_ate_reports_bad_file_with_line(tmp_path: Path, capsys) -> None:
    gt, _ = _write_pair(tmp_path)
    bad = tmp_path / "bad.tum"
    bad.write_text("0 0 0 0 0 0 0 1\n1 2\n")
    assert main(["ate", str(gt), str(bad)]) == 1
    assert "bad.tum:2" in capsys.readouterr().err


def test_paper_reduced_run_writes_tables_and_plots(tmp_path: Path, capsys) -> None:
    out = tmp_path / "paper"
    rc = main(
        [
            "paper",
            "--out",
            str(out),
            "--experiments",
            "1",
            "--runs",
            "1",
            "--trajectories",
            "traj3",
            "--stop-s",
            "2.0",
            "--camera-rate",  # a third of the site's 15 Hz: the tables, not their numbers
            "5",
        ]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "[1/2]" in text and "[2/2]" in text  # progress lines
    t1 = (out / "table1.md").read_text()
    for row in ("Robot", "Cameras (raw)", "Cameras (1 frame)", "Cameras (5 frames)", "Fused"):
        assert f"| {row} |" in t1
    assert "±" in t1
    t2 = (out / "table2.md").read_text()
    assert "| Robot |" in t2 and "traj3" in t2
    for png in ("fig6_map.png", "fig6_trajectories.png", "fig6_error_over_distance.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
