"""``smartedge bench reliability``: a smoke run of the harness with one fast probe (odometry
stamped 2**63-1 against the whole system as processes on Zenoh loopback), and its CLI."""

from __future__ import annotations

from pathlib import Path

import pytest

from smartedge.bench import BENCHES
from smartedge.reliability import PROBES, main

pytest.importorskip("zenoh")
pytest.importorskip("gtsam")


def test_registered_as_a_bench() -> None:
    assert BENCHES["reliability"][:2] == ("smartedge.reliability", "main")
    assert {"baseline", "a", "e", "f", "h", "i", "j"} <= set(PROBES)
    for probe in PROBES.values():
        assert probe.before and probe.fault[0] < probe.fault[1] <= probe.run_s


def test_unknown_probe_is_an_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--probes", "zz"])
    assert exc.value.code == 2
    assert "unknown probe" in capsys.readouterr().err


@pytest.mark.slow
def test_one_probe_runs_and_passes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["--probes", "e", "--seconds", "14", "--startup-s", "8", "--out",
                 str(tmp_path), "--progress-s", "5"])
    out = capsys.readouterr().out
    assert code == 0, out[-3000:]
    row = next(line for line in out.splitlines() if line.startswith("| (e)"))
    assert "`odometry_future` 1" in row and "crashes: 0" in row and row.endswith("|")
    assert "| pass: " in row
    assert "[e] t=" in out  # progress lines
    assert (tmp_path / "e" / "backend.log").exists()
