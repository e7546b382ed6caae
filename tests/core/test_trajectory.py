"""TUM read/write round trip and errors naming file and line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.trajectory import Trajectory, TrajectoryFileError, read_tum, write_tum


def test_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    xyth = np.column_stack([rng.normal(size=20), rng.normal(size=20), rng.uniform(-3, 3, 20)])
    traj = Trajectory.from_planar(np.arange(20) * 0.1 + 1.7e9, xyth)
    write_tum(tmp_path / "a.tum", traj)
    back = read_tum(tmp_path / "a.tum")
    np.testing.assert_allclose(back.stamps_s, traj.stamps_s, atol=1e-6)
    np.testing.assert_allclose(back.positions_m, traj.positions_m, atol=1e-8)
    np.testing.assert_allclose(back.planar()[:, 2], xyth[:, 2], atol=1e-8)


def test_evo_reads_what_we_write(tmp_path: Path) -> None:
    from evo.tools import file_interface

    traj = Trajectory.from_planar(np.arange(5.0), np.tile([1.0, 2.0, 0.5], (5, 1)))
    write_tum(tmp_path / "b.tum", traj)
    evo_traj = file_interface.read_tum_trajectory_file(str(tmp_path / "b.tum"))
    np.testing.assert_allclose(evo_traj.positions_xyz, traj.positions_m)


@pytest.mark.parametrize(
    "content,line,reason",
    [
        ("# c\n0 1 2 3 0 0 0 1\n1 2 3\n", 3, "expected 8 numbers"),
        ("0 1 2 3 0 0 0 1\n\n1 a 2 3 0 0 0 1\n", 3, "not a number"),
        ("0 1 2 3 0 0 0 0\n", 1, "quaternion is zero"),
        ("0 nan 2 3 0 0 0 1\n", 1, "NaN"),
    ],
)
def test_errors_name_file_and_line(tmp_path: Path, content: str, line: int, reason: str) -> None:
    p = tmp_path / "bad.tum"
    p.write_text(content)
    with pytest.raises(TrajectoryFileError, match=reason) as info:
        read_tum(p)
    assert info.value.line == line
    assert f"bad.tum:{line}" in str(info.value)


def test_missing_and_empty_files(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryFileError, match="cannot read"):
        read_tum(tmp_path / "nope.tum")
    (tmp_path / "e.tum").write_text("# only a comment\n")
    with pytest.raises(TrajectoryFileError, match="no poses"):
        read_tum(tmp_path / "e.tum")
