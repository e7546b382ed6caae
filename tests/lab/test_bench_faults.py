"""``smartedge bench reliability`` (the fault harness, :mod:`lab.bench.faults`): a smoke
run with one fast probe (odometry stamped 2**63-1 against the whole system as processes on
Zenoh loopback), the catalogue and its CLI."""

from __future__ import annotations

from pathlib import Path

import pytest

from lab.bench import BENCHES
from lab.bench.faults import PROBES, main

pytest.importorskip("zenoh")
pytest.importorskip("gtsam")


def test_registered_as_a_bench() -> None:
    assert BENCHES["reliability"][:2] == ("lab.bench.faults", "main")
    assert {"baseline", "forged_pose_future_stamp", "poisoned_odometry", "camera_clock_ahead",
            "oversized_nested_detections", "oversized_padded_detections",
            "backend_restart"} <= set(PROBES)
    for name, probe in PROBES.items():
        assert name == probe.name and name.isidentifier() and name.islower()
        assert probe.before and probe.sends and probe.holds
        assert probe.fault[0] < probe.fault[1] <= probe.run_s


def test_list_names_every_probe(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in lines] == list(PROBES)
    assert all("must hold: " in line for line in lines)


def test_unknown_probe_is_an_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--probes", "zz"])
    assert exc.value.code == 2
    assert "unknown probe" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--probes", "e"])  # the letters of issue 17 are gone: probes go by name


@pytest.mark.slow
def test_one_probe_runs_and_passes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["--probes", "poisoned_odometry", "--seconds", "11", "--startup-s", "8",
                 "--out", str(tmp_path), "--progress-s", "5"])
    out = capsys.readouterr().out
    assert code == 0, out[-3000:]
    row = next(line for line in out.splitlines() if line.startswith("| `poisoned_odometry`:"))
    assert "`odometry_future` 1" in row and "crashes: 0" in row and row.endswith("|")
    assert "| pass: " in row
    assert "[poisoned_odometry] t=" in out  # progress lines
    assert (tmp_path / "poisoned_odometry" / "backend.log").exists()
