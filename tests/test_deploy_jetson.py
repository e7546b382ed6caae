"""``deploy/install-edge.sh`` on a Jetson (JetPack 6): a venv that sees the system's packages,
JetPack's OpenCV (with GStreamer) in place of opencv-python-headless, NVIDIA's onnxruntime-gpu
in place of the CPU-only onnxruntime, and a report of what the board will run on.

The dry run shows the steps; the staged run (``--root``) executes them with pip and the system
python replaced at the process boundary by scripts that log their arguments (no board, no
downloads here), and the real interpreter for everything else (the site check, the report).
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT

DEPLOY = REPO_ROOT / "deploy"
SITE = DEPLOY / "site.example.yaml"
GPU_WHEEL = "onnxruntime_gpu-1.23.0-cp310-cp310-linux_aarch64.whl"


def _run(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["bash", str(DEPLOY / "install-edge.sh"), *args],
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, **(env or {})})


def test_dry_run_shows_the_jetson_python_steps_in_order(tmp_path: Path) -> None:
    root = tmp_path / "root"
    proc = _run("--dry-run", "--root", str(root), "--site", str(SITE), "--backend-host",
                "backend.lab", "--jetson", "yes", "--ort-wheel", GPU_WHEEL, "--ort-index",
                "https://index.example/jp6", "cam_sw")
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert not root.exists()
    steps = [
        f"-m venv {root}/opt/smartedge --system-site-packages",
        "pip install --quiet --upgrade",
        "pip uninstall -y opencv-python-headless; pip install 'numpy>=1.24,<2'",
        "pip uninstall --quiet -y onnxruntime onnxruntime-gpu",
        f"pip install --quiet --extra-index-url https://index.example/jp6 {GPU_WHEEL}",
        "jetson-gpu.conf",
    ]
    at = [out.find(step) for step in steps]
    assert all(i >= 0 for i in at) and at == sorted(at), out


def test_other_boards_get_none_of_it(tmp_path: Path) -> None:
    proc = _run("--dry-run", "--root", str(tmp_path / "root"), "--site", str(SITE),
                "--backend-host", "backend.lab", "--jetson", "no", "cam_sw")
    assert proc.returncode == 0, proc.stderr
    for word in ("--system-site-packages", "opencv-python-headless", "onnxruntime-gpu",
                 "jetson-gpu.conf →"):
        assert word not in proc.stdout


def _logging_python(path: Path, log: Path, *, pip_ok: bool = True, gstreamer: bool = True
                    ) -> None:
    """A python at ``path`` that logs its arguments to ``log``; ``-m pip`` and the GStreamer
    probe (``-c`` code naming GStreamer) are answered here, the rest runs the real
    interpreter."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        "#!/bin/sh\n"
        f'echo "$0 $*" >> {shlex.quote(str(log))}\n'
        f'if [ "$1" = -m ] && [ "$2" = pip ]; then exit {0 if pip_ok else 1}; fi\n'
        f'case "$2" in *GStreamer*) exit {0 if gstreamer else 1} ;; esac\n'
        f'exec {shlex.quote(sys.executable)} "$@"\n')
    path.chmod(0o755)


def test_staged_jetson_install_switches_the_venv_and_replaces_opencv_and_onnxruntime(
        tmp_path: Path) -> None:
    root = tmp_path / "root"
    log = tmp_path / "calls.log"
    venv = root / "opt" / "smartedge"
    _logging_python(venv / "bin" / "python", log)
    (venv / "pyvenv.cfg").write_text("home = /usr/bin\ninclude-system-site-packages = false\n"
                                     "version = 3.10.12\n")
    system_python = tmp_path / "system" / "python3"
    _logging_python(system_python, log, gstreamer=True)
    proc = _run("--root", str(root), "--site", str(SITE), "--backend-host", "backend.lab",
                "--jetson", "yes", "--ort-wheel", GPU_WHEEL, "--no-start", "cam_sw",
                env={"PYTHON": str(system_python)})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "include-system-site-packages = true" in (venv / "pyvenv.cfg").read_text()
    calls = [line.split(" ", 1)[1] for line in log.read_text().splitlines()
             if "-m pip" in line]
    assert calls[0] == "-m pip install --quiet --upgrade pip"
    assert calls[1].startswith("-m pip install --quiet --upgrade ") and \
        calls[1].endswith("[edge]")
    assert calls[2:] == ["-m pip install --quiet numpy>=1.24,<2",
                         "-m pip uninstall --quiet -y opencv-python-headless",
                         "-m pip uninstall --quiet -y onnxruntime onnxruntime-gpu",
                         f"-m pip install --quiet {GPU_WHEEL}"]
    # the report of what the board runs on, from the venv's real onnxruntime and OpenCV
    assert "install-edge.sh: onnxruntime " in proc.stdout and "GStreamer" in proc.stdout
    if "TensorrtExecutionProvider" not in proc.stdout:
        assert "no TensorRT provider: the networks run on" in proc.stdout


def test_staged_jetson_install_without_a_gstreamer_opencv_keeps_the_wheel(
        tmp_path: Path) -> None:
    root = tmp_path / "root"
    log = tmp_path / "calls.log"
    _logging_python(root / "opt" / "smartedge" / "bin" / "python", log)
    system_python = tmp_path / "system" / "python3"
    _logging_python(system_python, log, gstreamer=False)
    proc = _run("--root", str(root), "--site", str(SITE), "--backend-host", "backend.lab",
                "--jetson", "yes", "--no-start", "cam_sw", env={"PYTHON": str(system_python)})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "has no OpenCV with GStreamer" in proc.stdout and "csi://N" in proc.stdout
    calls = log.read_text()
    assert "opencv-python-headless" not in calls and "uninstall" not in calls
    # the logging pip answers `pip show onnxruntime-gpu` with success: a GPU build was there,
    # and a re-run without --ort-wheel has just replaced it with the CPU wheel: said loudly
    assert "-m pip show onnxruntime-gpu" in calls
    assert "WARNING: onnxruntime-gpu was installed" in proc.stdout
    assert "Re-run with --ort-wheel" in proc.stdout


def test_install_edge_is_shellcheck_clean() -> None:
    if shutil.which("shellcheck") is None:
        pytest.skip("shellcheck is not installed")
    proc = subprocess.run(["shellcheck", "-x", "-S", "warning", "deploy/install-edge.sh"],
                          cwd=REPO_ROOT, capture_output=True, text=True, timeout=60)
    own = [line for line in proc.stdout.splitlines() if line.startswith("In deploy/install-edge")]
    assert not own, proc.stdout
