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
    commands = cli.all_commands()
    assert set(cli.COMMANDS) < set(commands)
    for name in commands:
        assert name in proc.stdout


def test_the_lab_commands_come_through_the_entry_point() -> None:
    """The app's table names no lab module; the lab's commands reach ``smartedge`` only
    through the ``smartedge.commands`` entry point (pyproject.toml)."""
    from lab.commands import COMMANDS as LAB_COMMANDS

    assert not any(c.module.split(".")[0] == "lab" for c in cli.COMMANDS.values())
    assert cli.plugin_commands() == LAB_COMMANDS
    assert {"demo", "evaluate", "bench", "train", "render"} <= set(LAB_COMMANDS)


def test_a_broken_or_clashing_command_entry_point_is_logged_and_left_out(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    import importlib.metadata as md

    group = cli.COMMAND_ENTRY_POINTS
    points = [
        md.EntryPoint("gone", "no_such_module_xyz:COMMANDS", group),
        md.EntryPoint("notatable", "smartedge.cli:EXIT_BROKEN_PIPE", group),
        md.EntryPoint("clash", "smartedge.cli:COMMANDS", group),  # every name already taken
        md.EntryPoint("lab", "lab.commands:COMMANDS", group),
    ]
    monkeypatch.setattr(md, "entry_points", lambda group: [p for p in points
                                                           if p.group == group])
    with caplog.at_level(logging.WARNING, logger="smartedge.cli"):
        found = cli.plugin_commands()
    assert "demo" in found and "backend" not in found
    text = caplog.text
    assert "no_such_module_xyz" in text and "not a mapping" in text
    assert "command 'backend' is taken" in text


def test_site_check_ok_and_error_names_file_and_key(tmp_path) -> None:
    assert _run("site", "check", str(EXAMPLE_SITE)).returncode == 0
    bad = tmp_path / "bad.yaml"
    bad.write_text(EXAMPLE_SITE.read_text().replace("sync_window_ms", "sync_windw_ms"))
    proc = _run("site", "check", str(bad))
    assert proc.returncode == 1
    assert str(bad) in proc.stderr and "thresholds.sync_windw_ms" in proc.stderr


def test_edge_agent_camera_source_needs_an_input() -> None:
    """``--source camera`` (the default) without --device/--images/--realsense exits at start
    with a message naming the options and exit status 78 (EX_CONFIG), which the systemd unit
    does not restart on (not a restart loop of tracebacks)."""
    proc = _run("edge-agent", "--site", str(EXAMPLE_SITE), "--camera", "cam_sw")
    assert proc.returncode == 78
    assert "--device" in proc.stderr and "--images" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_services_reject_unknown_site_ids() -> None:
    proc = _run("edge-agent", "--camera", "cam_nope", "--source", "sim")
    assert proc.returncode == 78 and "cam_nope" in proc.stderr
    proc = _run("robot-bridge", "--site", str(EXAMPLE_SITE), "--robot", "r2d2")
    assert proc.returncode == 78 and "r2d2" in proc.stderr


def test_simulation_plugin_registers_twice_harmlessly() -> None:
    from edge_agent import service as edge_service
    from edge_agent import sources
    from robot_bridge import service as bridge_service
    from robot_bridge.adapters import registry
    from smartedge import simulated_site as plugins

    plugins.register_simulation()
    plugins.register_simulation()
    sources.register_source("sim", plugins.SIM_SOURCE)  # the same plug-in again: a no-op
    registry.register_adapter("sim", plugins.SIM_ADAPTER)
    registry.register_adapter("ros2", registry.ROS_ADAPTERS)
    assert sources.source_names() == ("camera", "ros", "sim")
    assert registry.adapter_names() == ("rmw_zenoh", "ros1", "ros2", "sim")
    # another plug-in under a taken name is a mistake, said so
    with pytest.raises(ValueError, match="already registered"):
        sources.register_source("sim", plugins.SimSourcePlugin())
    with pytest.raises(ValueError, match="already registered"):
        registry.register_adapter("sim", plugins.SimAdapterPlugin())
    # each plug-in's argument group is added once (argparse would refuse a duplicate option)
    args = edge_service.build_parser().parse_args(["--camera", "cam1", "--source", "sim"])
    assert args.sim_trajectory == "traj3"
    args = bridge_service.build_parser().parse_args(["--adapter", "ros1", "--kidnapped"])
    assert args.kidnapped and args.robot_profile is None  # the site file's ros.profile


def test_unknown_source_or_adapter_is_a_clear_argparse_error() -> None:
    proc = _run("edge-agent", "--camera", "cam1", "--source", "webcam")
    assert proc.returncode == 2
    assert "--source: invalid choice: 'webcam'" in proc.stderr
    assert "'camera'" in proc.stderr and "'sim'" in proc.stderr
    proc = _run("robot-bridge", "--adapter", "ros3")
    assert proc.returncode == 2
    assert "--adapter: invalid choice: 'ros3'" in proc.stderr
    assert all(f"'{name}'" in proc.stderr for name in ("rmw_zenoh", "ros1", "ros2", "sim"))


def test_services_alone_offer_no_simulation() -> None:
    """Without the top floor's plug-in assembly the services offer only what they ship."""
    script = (
        "import sys\n"
        "from edge_agent.service import build_parser as edge\n"
        "from robot_bridge.service import build_parser as bridge\n"
        "from edge_agent.sources import source_names\n"
        "from robot_bridge.adapters.registry import adapter_names\n"
        "assert source_names() == ('camera', 'ros'), source_names()\n"
        "assert adapter_names() == ('rmw_zenoh', 'ros1', 'ros2'), adapter_names()\n"
        "assert not [m for m in sys.modules if m.split('.')[0] in ('simulation', 'smartedge')]\n"
        "edge().parse_args(['--camera', 'c', '--source', 'sim'])\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], cwd=REPO_ROOT, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 2, proc.stderr
    assert "invalid choice: 'sim'" in proc.stderr


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


def test_a_closed_pipe_ends_the_command_without_a_traceback() -> None:
    """``smartedge site reference | head -1`` where the reader is gone before the command
    writes: the command stops with 141 (as a shell reports SIGPIPE) and no traceback."""
    proc = subprocess.Popen([sys.executable, "-m", "smartedge", "site", "reference"],
                            cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None
    proc.stdout.close()  # the reader leaves before the first line (the imports take longer)
    _, err_bytes = proc.communicate(timeout=60)
    err = err_bytes.decode()
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
    assert proc.returncode == cli.EXIT_BROKEN_PIPE


_THREADS_AFTER_A_COMMAND = """
import os, sys
from smartedge import cli
rc = cli.main(["site", "check", sys.argv[1]])
import numpy  # the command imported it: its BLAS is loaded
a = numpy.random.default_rng(0).random((600, 600))
a @ a  # large enough for OpenBLAS to split it over its threads, when it has any
print(rc, os.environ.get("OPENBLAS_NUM_THREADS"), len(os.listdir("/proc/self/task")))
"""


@pytest.mark.parametrize("preset", [None, "2"])
def test_commands_run_numpys_blas_on_one_thread_unless_told_otherwise(preset) -> None:
    # the default keeps OpenBLAS from starting its worker thread (one that busy-waits after
    # a split call: the fleet backends' latency tail); a value the user set is kept
    import os

    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if preset is not None:
        env["OPENBLAS_NUM_THREADS"] = preset
    proc = subprocess.run([sys.executable, "-c", _THREADS_AFTER_A_COMMAND, str(EXAMPLE_SITE)],
                          cwd=REPO_ROOT, capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr
    rc, value, threads = proc.stdout.split()[-3:]
    assert rc == "0"
    if preset is None:
        assert (value, threads) == ("1", "1")
    else:
        assert value == preset and int(threads) > 1  # its worker thread(s)


def test_process_defaults_do_not_override_and_say_what_they_set() -> None:
    env = {"OPENBLAS_NUM_THREADS": "4"}
    assert cli.apply_process_defaults(env) == {} and env["OPENBLAS_NUM_THREADS"] == "4"
    env = {}
    assert cli.apply_process_defaults(env) == {"OPENBLAS_NUM_THREADS": "1"} == env


def test_the_command_word_skips_global_options_and_their_values() -> None:
    assert cli.command_name(["--log-level", "DEBUG", "backend", "--site", "x"]) == "backend"
    assert cli.command_name(["--log-format", "json", "--version"]) is None
    assert cli.command_name(["--log-level=INFO", "demo"]) == "demo"
    assert cli.command_name([]) is None


def test_an_app_command_starts_without_reading_the_entry_points(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Every service start would pay for the scan of the installed packages (~0.14 s)."""
    def fail(*_args: object, **_kwargs: object) -> dict:
        raise AssertionError("entry points read for an app command")

    monkeypatch.setattr(cli, "plugin_commands", fail)
    assert cli.main(["--log-level", "WARNING", "site", "check", str(EXAMPLE_SITE)]) == 0
    with pytest.raises(AssertionError, match="entry points"):
        cli.main(["demo", "--help"])
