"""Frame capture (edge_agent.capture, ``--capture``): frames named by their capture stamp,
lossless or JPEG, at the capture rate by stamp, within a disk budget that stops the capture and
not the agent, whole files only; and through the edge agent on rendered frames, the file names
are the stamps of the detections it published."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from edge_agent.capture import FrameCapture
from edge_agent.service import build_node, build_parser
from protocol.errors import UsageError
from tests.conftest import REPO_ROOT

SITE = REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"
T0 = 1_700_000_000_000_000_000


class _Counts:
    def __init__(self) -> None:
        self.counters: dict[str, int] = {}

    def count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n


def _frame(seed: int, h: int = 120, w: int = 160) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_lossless_frames_named_by_stamp_at_the_capture_rate(tmp_path: Path) -> None:
    counts = _Counts()
    cap = FrameCapture(tmp_path, "cam1", rate_hz=2.0, stats=counts)
    frames = {T0 + i * 100_000_000: _frame(i) for i in range(12)}  # 10 Hz for 1.2 s
    taken = [s for s, img in frames.items() if cap.offer(img, s)]
    cap.close()
    assert taken == [T0, T0 + 500_000_000, T0 + 1_000_000_000]  # 2 Hz by stamp
    files = sorted((tmp_path / "cam1").iterdir())
    assert [f.name for f in files] == [f"{s}.png" for s in taken]
    for s, f in zip(taken, files, strict=True):
        back = cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(back, frames[s])  # lossless, RGB kept
    assert counts.counters["frames_captured"] == 3
    assert counts.counters["capture_bytes"] == sum(f.stat().st_size for f in files)
    assert "capture 3 frames" in cap.status()


def test_jpeg_at_the_asked_quality(tmp_path: Path) -> None:
    cap = FrameCapture(tmp_path, "cam2", fmt="jpg", jpeg_quality=60)
    img = cv2.GaussianBlur(_frame(1), (9, 9), 3)
    assert cap.offer(img, T0)
    cap.close()
    path = tmp_path / "cam2" / f"{T0}.jpg"
    expected = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR),
                            [cv2.IMWRITE_JPEG_QUALITY, 60])[1].tobytes()
    assert path.read_bytes() == expected


def test_the_budget_stops_the_capture_and_counts_what_was_there(tmp_path: Path) -> None:
    size = len(cv2.imencode(".png", _frame(0))[1])
    (tmp_path / "cam1").mkdir()
    (tmp_path / "cam1" / "earlier.png").write_bytes(b"x" * size)  # a previous run's frame
    budget_mb = 3.5 * size / 2**20  # the earlier file and two more frames
    cap = FrameCapture(tmp_path, "cam1", rate_hz=100.0, budget_mb=budget_mb)
    for i in range(10):
        cap.offer(_frame(i), T0 + i * 20_000_000)
        time.sleep(0.05)  # let the writer keep up
    cap.close()
    assert cap.captured == 2
    assert "budget" in cap.stopped and "capture stopped" in cap.status()
    assert len(list((tmp_path / "cam1").glob("1*.png"))) == 2
    assert not list((tmp_path / "cam1").glob(".*"))  # no half-written file left
    assert sum(f.stat().st_size for f in (tmp_path / "cam1").iterdir()) <= budget_mb * 2**20
    assert not cap.offer(_frame(99), T0 + 10**10)  # stays stopped


def test_bad_options_are_named(tmp_path: Path) -> None:
    for kwargs, named in (({"rate_hz": 0}, "--capture-rate"), ({"budget_mb": -1},
                          "--capture-budget-mb"), ({"fmt": "bmp"}, "--capture-format"),
                          ({"jpeg_quality": 0}, "--capture-jpeg-quality")):
        with pytest.raises(ValueError, match=named):
            FrameCapture(tmp_path, "cam1", **kwargs)


@pytest.mark.usefixtures("tiny_models")
def test_the_edge_agent_captures_the_frames_it_detected_on(tiny_models: Path, tmp_path: Path
                                                           ) -> None:
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    images = tmp_path / "images"
    images.mkdir()
    gen = SampleGenerator(load_scenario(), "site", seed=5)
    for i in range(3):
        cv2.imwrite(str(images / f"{i:03d}.png"), cv2.cvtColor(gen(i).image_rgb,
                                                               cv2.COLOR_RGB2BGR))
    out = tmp_path / "capture"
    argv = ["--site", str(SITE), "--camera", "cam1", "--source", "camera", "--threads", "1",
            "--images", str(images), "--rate", "0", "--model", str(tiny_models),
            "--capture", str(out), "--capture-rate", "1000"]
    node = build_node(build_parser().parse_args(argv))
    stamps = []
    try:
        deadline = time.monotonic() + 30
        while len(stamps) < 3 and time.monotonic() < deadline:
            stamps += [o.message.stamp_ns for o in node.tick(time.time_ns())]
            time.sleep(0.005)
    finally:
        node.close()
    assert len(stamps) >= 1
    files = sorted(p.name for p in (out / "cam1").iterdir())
    assert files == sorted(f"{s}.png" for s in stamps)  # one file per frame, by its stamp
    first = cv2.imread(str(out / "cam1" / files[0]))
    assert first.shape == (480, 848, 3)  # full resolution
    assert node.stats.snapshot_counters()["frames_captured"] == len(stamps)
    assert f"capture {len(stamps)} frames" in node.state()[1]
    with pytest.raises(UsageError, match="--capture-rate"):
        build_node(build_parser().parse_args([*argv, "--capture-rate", "0"]))
