"""The smartedge command line: dispatch, clear errors, log formats."""

from __future__ import annotations

import json
import logging
import subprocess
import sys

import pytest

from smartedge import cli
from tests.conftest import EXAMPLE_SITE, REPO_ROOT


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "smartedge", *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_help_lists_every_command() -> None:
    proc = _run("--help")
    assert proc.returncode == 0
    for name in cli.COMMANDS:
        assert name in proc.stdout


def test_site_check_ok_and_error_names_file_and_key(tmp_path) -> None:
    assert _run("site", "check", str(EXAMPLE_SITE)).returncode == 0
    bad = tmp_path / "bad.yaml"
    bad.write_text(EXAMPLE_SITE.read_text().replace("sync_window_ms", "sync_windw_ms"))
    proc = _run("site", "check", str(bad))
    assert proc.returncode == 1
    assert str(bad) in proc.stderr and "thresholds.sync_windw_ms" in proc.stderr


def test_edge_agent_without_a_model_says_so() -> None:
    proc = _run("edge-agent", "--site", str(EXAMPLE_SITE), "--camera", "cam_sw")
    assert proc.returncode == 2
    assert "keypoint model" in proc.stderr and "--source sim" in proc.stderr


def test_services_reject_unknown_site_ids() -> None:
    proc = _run("edge-agent", "--camera", "cam_nope", "--source", "sim")
    assert proc.returncode == 1 and "cam_nope" in proc.stderr
    proc = _run("robot-bridge", "--site", str(EXAMPLE_SITE), "--robot", "r2d2")
    assert proc.returncode == 1 and "r2d2" in proc.stderr


def test_json_log_lines_parse(capsys: pytest.CaptureFixture[str]) -> None:
    root = logging.getLogger()
    saved = root.handlers[:]
    try:
        root.handlers.clear()
        cli._configure_logging("INFO", "json")
        try:
            raise ValueError("boom")
        except ValueError:
            logging.getLogger("smartedge.test").exception("failed %d", 3)
    finally:
        root.handlers[:] = saved
    line = capsys.readouterr().err.strip().splitlines()[-1]
    doc = json.loads(line)
    assert doc["level"] == "ERROR" and doc["msg"] == "failed 3" and "boom" in doc["exc"]
    assert doc["logger"] == "smartedge.test" and doc["ts"].endswith("Z")
