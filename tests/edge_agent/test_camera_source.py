"""The edge agent's camera path: :class:`EdgePipeline` on rendered frames, the ``--source
camera`` plug-in built through the edge agent's own parser (image folders, RealSense and
device errors, bad model folders, usage errors), and the edge agent as a CLI process
publishing :class:`RobotDetections` over real Zenoh on loopback.

Checked: messages carry the frame's camera id, stamp, seq and size, the model id and
well-formed keypoints; a frame of another size than the calibration is warned about once;
the node publishes best-effort detections on the camera's detections key, records per-stage
latencies and skipped frames, reports ``ok`` while frames flow and ``degraded`` (with the
reason) when the source ended or fails; bad options and models fail at start with clear
errors; the CLI stops cleanly on SIGTERM.
"""

from __future__ import annotations

import logging
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
cv2 = pytest.importorskip("cv2")

from core.runtime import Outgoing  # noqa: E402
from edge_agent.frames import Frame, LatestFrameReader  # noqa: E402
from edge_agent.model_cards import ModelError  # noqa: E402
from edge_agent.models import RobotKeypointPipeline  # noqa: E402
from edge_agent.pipeline import EdgePipeline, StageLatency  # noqa: E402
from edge_agent.service import EdgeAgentNode, build_node, build_parser  # noqa: E402
from edge_agent.sources import CameraFrameSource  # noqa: E402
from protocol import codec, keys  # noqa: E402
from protocol.errors import UnknownIdError, UsageError  # noqa: E402
from protocol.messages import RobotDetections, ServiceStatus  # noqa: E402
from tests.conftest import REPO_ROOT, free_port, wait_until  # noqa: E402

SITE = REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"
SITE_NAME, CAMERA, WIDTH, HEIGHT, K = "paper_lab", "cam1", 848, 480, 12
N_IMAGES = 3


# --------------------------------------------------------------------------------------------
# fixtures and helpers
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def rendered() -> list[np.ndarray]:
    """Three rendered 848x480 RGB views of the paper lab with the robot in view."""
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    gen = SampleGenerator(load_scenario(), "site", seed=5)
    images = []
    for i in range(12):
        sample = gen(i)
        if sample.robots[0].bbox_xyxy is not None:
            images.append(sample.image_rgb)
        if len(images) == N_IMAGES:
            return images
    pytest.fail(f"fewer than {N_IMAGES} site views with the robot among the first 12")


@pytest.fixture
def image_dir(tmp_path: Path, rendered: list[np.ndarray]) -> Path:
    """A folder of the rendered views as PNG files (``000.png``...)."""
    folder = tmp_path / "images"
    folder.mkdir()
    for i, rgb in enumerate(rendered):
        assert cv2.imwrite(str(folder / f"{i:03d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return folder


@pytest.fixture
def models(tiny_models: Path) -> RobotKeypointPipeline:
    """The tiny trained detector + keypoint models, one onnxruntime thread."""
    return RobotKeypointPipeline.from_folder(tiny_models, threads=1)


def _args(*extra: str, site: Path | None = SITE) -> list[str]:
    """Edge agent arguments for cam1 of the paper lab with ``--source camera``."""
    head = ["--site", str(site)] if site is not None else []
    return [*head, "--camera", CAMERA, "--source", "camera", "--threads", "1", *extra]


def _build(*extra: str) -> EdgeAgentNode:
    return build_node(build_parser().parse_args(_args(*extra)))


def _tick_until(node: EdgeAgentNode, done: Callable[[list[Outgoing]], bool],
                timeout_s: float = 20.0) -> list[Outgoing]:
    """Tick ``node`` (wall clock) until ``done(all outputs so far)``; returns the outputs."""
    out: list[Outgoing] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        out.extend(node.tick(time.time_ns()))
        if done(out):
            return out
        time.sleep(0.005)
    raise AssertionError(f"timed out after {len(out)} outputs; state {node.state()}")


def _grab_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("grab ") and t.is_alive()]


@pytest.fixture
def nodes() -> Iterator[list[EdgeAgentNode]]:
    """Nodes appended here are closed after the test (their reader threads stop)."""
    built: list[EdgeAgentNode] = []
    yield built
    for node in built:
        node.close()


def _check_detections(msg: RobotDetections, model_id: str, width: int = WIDTH,
                      height: int = HEIGHT) -> None:
    assert isinstance(msg, RobotDetections)
    assert msg.camera_id == CAMERA
    assert (msg.image_width, msg.image_height) == (width, height)
    assert msg.model_id == model_id and msg.model_id
    for det in msg.detections:
        assert det.keypoints_px.shape == (K, 2) and np.all(np.isfinite(det.keypoints_px))
        assert det.keypoint_scores.shape == (K,)
        assert np.all((det.keypoint_scores >= 0) & (det.keypoint_scores <= 1))
        assert 0.0 <= det.score <= 1.0
        x0, y0, x1, y1 = det.bbox_xyxy
        assert -0.5 <= x0 <= x1 <= width - 0.5 and -0.5 <= y0 <= y1 <= height - 0.5
    again = codec.decode(codec.encode(msg), RobotDetections)  # what the backend will read
    assert (again.seq, again.stamp_ns, len(again.detections)) == \
        (msg.seq, msg.stamp_ns, len(msg.detections))


# --------------------------------------------------------------------------------------------
# EdgePipeline
# --------------------------------------------------------------------------------------------


def test_pipeline_turns_a_rendered_frame_into_robot_detections(
        models: RobotKeypointPipeline, rendered: list[np.ndarray]) -> None:
    """A rendered frame gives a valid :class:`RobotDetections`: camera id, the frame's stamp,
    seq and size, the models' id, (12, 2) keypoints with scores in [0, 1], boxes inside the
    image, the robot id asked for; the latencies are measured."""
    pipe = EdgePipeline(CAMERA, models, min_score=0.0, max_robots=2, robot_id="hsr",
                        expected_size=(WIDTH, HEIGHT))
    assert pipe.model_id == models.model_id and "/" in pipe.model_id
    frame = Frame(rendered[0], 1_234_567_890_123, 42)
    msg, lat = pipe.process(frame)
    _check_detections(msg, models.model_id)
    assert (msg.stamp_ns, msg.seq) == (1_234_567_890_123, 42)
    # min_score 0: the detector's best peaks are kept unless their box is degenerate
    assert 1 <= len(msg.detections) <= 2
    assert all(d.robot_id == "hsr" for d in msg.detections)
    assert isinstance(lat, StageLatency)
    assert lat.detector_s > 0 and lat.keypoints_s > 0 and lat.encode_s >= 0


def test_pipeline_without_detections_still_reports_the_frame(
        models: RobotKeypointPipeline, rendered: list[np.ndarray]) -> None:
    """Nothing above ``min_score``: an empty message ("no robot seen") with the frame's
    stamp, seq and size."""
    pipe = EdgePipeline(CAMERA, models, min_score=1.01)
    msg, _ = pipe.process(Frame(rendered[1], 7, 3))
    _check_detections(msg, models.model_id)
    assert msg.detections == () and (msg.stamp_ns, msg.seq) == (7, 3)


def test_pipeline_warns_once_about_a_frame_size_other_than_the_calibration(
        models: RobotKeypointPipeline, rendered: list[np.ndarray],
        caplog: pytest.LogCaptureFixture) -> None:
    """Frames of 424x240 for a camera calibrated at 848x480: one warning naming both sizes
    for two frames, and the messages carry the frame's own size."""
    small = cv2.resize(rendered[0], (WIDTH // 2, HEIGHT // 2), interpolation=cv2.INTER_AREA)
    pipe = EdgePipeline(CAMERA, models, min_score=0.0, expected_size=(WIDTH, HEIGHT))
    with caplog.at_level(logging.WARNING, logger="edge_agent.pipeline"):
        msgs = [pipe.process(Frame(small, 10 * i, i))[0] for i in (1, 2)]
        pipe.process(Frame(rendered[0], 30, 3))  # the calibrated size: no warning either
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    text = warnings[0].getMessage()
    assert CAMERA in text and "424x240" in text and "848x480" in text
    for msg in msgs:
        _check_detections(msg, models.model_id, WIDTH // 2, HEIGHT // 2)


# --------------------------------------------------------------------------------------------
# --source camera through the edge agent's parser and build_node
# --------------------------------------------------------------------------------------------


def test_image_folder_source_publishes_detections_then_reports_the_end(
        tiny_models: Path, image_dir: Path, nodes: list[EdgeAgentNode]) -> None:
    """``--images DIR --rate 0``: ticking the node yields best-effort :class:`RobotDetections`
    on ``smartedge/paper_lab/edge/cam1/detections`` until the folder is exhausted; every
    image is either published or counted as skipped; the detector, keypoint, grab and
    publish latencies are recorded; the state is then ``degraded`` saying the source ended."""
    node = _build("--images", str(image_dir), "--rate", "0", "--model", str(tiny_models))
    nodes.append(node)
    assert isinstance(node.source, CameraFrameSource)
    assert node.source.label == f"images:{image_dir}"
    reader = node.source.reader
    assert isinstance(reader, LatestFrameReader)

    def finished(out: list[Outgoing]) -> bool:
        return bool(out) and reader.status().state == "ended" and reader._frame is None

    out = _tick_until(node, finished)
    out += list(node.tick(time.time_ns()))  # nothing left
    model_id = node.source.pipeline.model_id
    assert model_id == f"{node.source.pipeline.models.keypoints.card.robot_model}/" \
        f"{tiny_models.name}"
    seqs = []
    for item in out:
        assert item.key == keys.detections_key(SITE_NAME, CAMERA)
        assert item.reliable is False
        _check_detections(item.message, model_id)
        seqs.append(item.message.seq)
    assert seqs == sorted(seqs) and seqs[-1] == N_IMAGES  # the last image is never skipped

    counters = node.stats.snapshot_counters()
    assert counters["frames"] == len(out)
    assert counters.get("frames_with_robot", 0) + counters.get("frames_without_robot", 0) == \
        len(out)
    assert len(out) + counters.get("frames_skipped", 0) == N_IMAGES
    latencies = node.stats.percentiles_ms(0.5)
    for stage in ("detector", "keypoints", "grab_to_detections", "capture_to_publish"):
        assert stage in latencies and latencies[stage] >= 0, latencies
    assert latencies["detector"] > 0

    state, detail = node.state()
    assert state == "degraded"
    assert "ended" in detail and f"source=images:{image_dir}" in detail
    assert f"frames={N_IMAGES}" in detail


def test_looping_image_folder_is_ok_while_frames_flow(
        tiny_models: Path, image_dir: Path, nodes: list[EdgeAgentNode]) -> None:
    """``--images DIR --rate 20 --loop``: the state is ``ok`` while frames flow, sequence
    numbers keep increasing past the folder's size; ``close()`` stops the reader thread."""
    node = _build("--images", str(image_dir), "--rate", "20", "--loop", "--model",
                  str(tiny_models), "--min-score", "0.0")
    nodes.append(node)
    assert wait_until(lambda: node.state()[0] == "ok", 10.0), node.state()
    out = _tick_until(node, lambda o: len(o) >= N_IMAGES + 2)
    seqs = [item.message.seq for item in out]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs) and seqs[-1] > N_IMAGES
    state, detail = node.state()
    assert state == "ok" and f"source=images:{image_dir}" in detail
    thread = node.source.reader._thread
    node.close()
    assert not thread.is_alive()


def test_folder_of_garbage_images_degrades_instead_of_raising(
        tiny_models: Path, tmp_path: Path, nodes: list[EdgeAgentNode]) -> None:
    """A folder whose images are all garbage bytes: ``build_node`` succeeds, nothing is
    published, every file is counted unreadable and the state is ``degraded`` (not ``ok``)."""
    for name in ("a.png", "b.jpg"):
        (tmp_path / name).write_bytes(b"not an image" * 50)
    node = _build("--images", str(tmp_path), "--rate", "0", "--model", str(tiny_models))
    nodes.append(node)
    assert wait_until(lambda: node.state()[0] == "degraded", 10.0), node.state()
    assert list(node.tick(time.time_ns())) == []
    assert node.source.reader.grabber.unreadable == 2
    assert "frames=0" in node.state()[1]


def test_folder_of_garbage_images_says_why_in_the_status(
        tiny_models: Path, tmp_path: Path, nodes: list[EdgeAgentNode]) -> None:
    """The degraded status of a folder of unreadable images should say that the images are
    unreadable (or name one), not only that the source ended."""
    (tmp_path / "a.png").write_bytes(b"not an image" * 50)
    node = _build("--images", str(tmp_path), "--rate", "0", "--model", str(tiny_models))
    nodes.append(node)
    assert wait_until(lambda: node.state()[0] == "degraded", 10.0), node.state()
    detail = node.state()[1]
    assert "unreadable" in detail or "a.png" in detail, detail


def test_looping_folder_of_garbage_images_is_not_reported_ok(
        tiny_models: Path, tmp_path: Path, nodes: list[EdgeAgentNode]) -> None:
    """``--loop`` on a folder of unreadable images should not report ``ok`` forever while
    no frame ever comes."""
    (tmp_path / "a.png").write_bytes(b"not an image" * 50)
    node = _build("--images", str(tmp_path), "--rate", "50", "--loop", "--model",
                  str(tiny_models))
    nodes.append(node)
    assert wait_until(lambda: node.state()[0] == "degraded", 5.0), node.state()
    assert "none of its" in node.state()[1] and str(tmp_path) in node.state()[1]


@pytest.mark.parametrize("extra, needle", [
    (("--realsense",), "pyrealsense2"),
    (("--realsense", "012345"), "pyrealsense2"),
    (("--device", "/dev/video99"), "/dev/video99"),
])
def test_camera_that_cannot_open_is_reported_and_retried(
        tiny_models: Path, nodes: list[EdgeAgentNode], monkeypatch: pytest.MonkeyPatch,
        extra: tuple[str, ...], needle: str) -> None:
    """A RealSense without ``pyrealsense2`` or a device path with no device: ``build_node``
    succeeds, the state is ``degraded`` with the error and the retry delay, nothing is
    published, and ``close()`` stops the retrying thread promptly."""
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    node = _build(*extra, "--model", str(tiny_models))
    nodes.append(node)
    assert wait_until(lambda: node.source.reader.status().failures >= 1, 10.0)
    state, detail = node.state()
    assert state == "degraded" and needle in detail and "retry in" in detail, detail
    assert node.source.reader.status().state == "retrying"
    assert list(node.tick(time.time_ns())) == []
    thread = node.source.reader._thread
    t0 = time.monotonic()
    node.close()
    assert time.monotonic() - t0 < 1.5 and not thread.is_alive()


def test_video_file_device_is_processed(tiny_models: Path, tmp_path: Path,
                                        rendered: list[np.ndarray],
                                        nodes: list[EdgeAgentNode]) -> None:
    """``--device clip.avi`` (a video file): its frames are processed into detections with
    the video's frame size."""
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (WIDTH, HEIGHT))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG .avi files")
    for rgb in rendered:
        writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    writer.release()
    node = _build("--device", str(path), "--model", str(tiny_models))
    nodes.append(node)
    out = _tick_until(node, lambda o: node.source.reader.status().state == "ended" and
                      node.source.reader._frame is None and bool(o))
    for item in out:
        _check_detections(item.message, node.source.pipeline.model_id)
    assert node.state()[0] == "degraded" and "ended" in node.state()[1]


def test_video_file_device_loops_with_loop(tiny_models: Path, tmp_path: Path,
                                           nodes: list[EdgeAgentNode]) -> None:
    """``--device clip.avi --loop`` should play the file again instead of ending."""
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 50.0, (64, 48))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG .avi files")
    for i in range(3):
        writer.write(np.full((48, 64, 3), 60 * i, np.uint8))
    writer.release()
    node = _build("--device", str(path), "--loop", "--model", str(tiny_models))
    nodes.append(node)
    reader = node.source.reader
    wait_until(lambda: reader.status().grabbed >= 6 or reader.status().state == "ended", 5.0)
    assert reader.status().grabbed >= 6, reader.status()


def test_bad_model_folder_fails_at_start_naming_the_file(
        tiny_models: Path, image_dir: Path, tmp_path: Path) -> None:
    """A ``--model`` folder that does not exist, or whose ``detector.onnx`` is garbage,
    makes ``build_node`` raise :class:`ModelError` naming the folder / file, and no reader
    thread is left running."""
    before = set(_grab_threads())
    missing = tmp_path / "no_models"
    with pytest.raises(ModelError, match="not found") as err:
        _build("--images", str(image_dir), "--model", str(missing))
    assert str(missing) in str(err.value)

    broken = tmp_path / "broken"
    broken.mkdir()
    for kind in ("detector", "keypoints"):
        for suffix in (".onnx", ".json"):
            shutil.copy(tiny_models / f"{kind}{suffix}", broken / f"{kind}{suffix}")
    (broken / "detector.onnx").write_bytes(b"\x08\x07 definitely not protobuf" * 64)
    with pytest.raises(ModelError) as err:
        _build("--images", str(image_dir), "--model", str(broken))
    assert str(broken / "detector.onnx") in str(err.value)
    assert set(_grab_threads()) == before


def test_camera_source_usage_errors(tiny_models: Path, image_dir: Path) -> None:
    """``--source camera`` without an input names ``--device``, ``--images`` and
    ``--realsense``; without ``--site`` it says ``--site`` is needed; an unknown camera id
    names the known ones. All are raised by ``build_node`` before any thread starts."""
    before = set(_grab_threads())
    with pytest.raises(UsageError) as err:
        _build("--model", str(tiny_models))
    assert all(opt in str(err.value) for opt in ("--device", "--images", "--realsense"))

    args = build_parser().parse_args(_args("--images", str(image_dir), site=None))
    with pytest.raises(UsageError, match="--site"):
        build_node(args)

    args = build_parser().parse_args(_args("--images", str(image_dir)))
    args.camera = "cam9"
    with pytest.raises(UnknownIdError, match="cam9") as err:
        build_node(args)
    assert "cam1" in str(err.value)
    assert set(_grab_threads()) == before


def test_input_options_are_mutually_exclusive(image_dir: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """``--images`` and ``--device`` together are refused by the parser (exit code 2)."""
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(_args("--images", str(image_dir), "--device", "0"))
    assert exc.value.code == 2
    assert "not allowed with" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# the CLI over real Zenoh on loopback
# --------------------------------------------------------------------------------------------


def test_edge_agent_cli_publishes_detections_over_zenoh(tiny_models: Path, image_dir: Path,
                                                        tmp_path: Path) -> None:
    """``smartedge edge-agent --source camera --images DIR --rate 5 --loop`` as a process:
    a real Zenoh subscriber on loopback receives :class:`RobotDetections` for cam1 and an
    ``ok`` status naming the image source; SIGTERM stops the process with exit code 0."""
    zenoh = pytest.importorskip("zenoh")
    from core.session import loopback_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    received: list[RobotDetections] = []
    statuses: list[ServiceStatus] = []
    lock = threading.Lock()

    def on_detections(sample: object) -> None:
        msg = codec.decode(sample.payload.to_bytes(), RobotDetections)  # type: ignore[attr-defined]
        with lock:
            received.append(msg)

    def on_status(sample: object) -> None:
        msg = codec.decode(sample.payload.to_bytes(), ServiceStatus)  # type: ignore[attr-defined]
        with lock:
            statuses.append(msg)

    log_path = tmp_path / "edge-agent.log"
    log_file = log_path.open("wb")
    session = zenoh.open(loopback_config(listen=[endpoint]))
    proc: subprocess.Popen[bytes] | None = None
    try:
        subs = [
            session.declare_subscriber(keys.detections_key(SITE_NAME, CAMERA), on_detections),
            session.declare_subscriber(keys.status_key(SITE_NAME, "edge-agent", CAMERA),
                                       on_status),
        ]
        proc = subprocess.Popen(
            [sys.executable, "-m", "smartedge", "edge-agent", *_args(
                "--images", str(image_dir), "--rate", "5", "--loop", "--model",
                str(tiny_models), "--providers", "CPUExecutionProvider"),
             "--listen", "tcp/127.0.0.1:0", "--connect", endpoint],
            cwd=REPO_ROOT, stdout=subprocess.DEVNULL, stderr=log_file)

        def got_enough() -> bool:
            with lock:
                return len(received) >= 2 and any(s.state == "ok" for s in statuses)

        wait_until(lambda: got_enough() or proc.poll() is not None, 60.0, 0.1)
        if proc.poll() is not None or not got_enough():
            proc.kill()
            proc.wait(10)
            pytest.fail(f"{len(received)} detections, {len(statuses)} statuses, exit "
                        f"{proc.returncode}: {log_path.read_text()[-3000:]}")
        proc.send_signal(signal.SIGTERM)
        proc.wait(20)
        log_text = log_path.read_text()
        assert proc.returncode == 0, log_text[-3000:]
        assert "Traceback" not in log_text, log_text[-3000:]
        for sub in subs:
            sub.undeclare()
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(10)
        session.close()
        log_file.close()

    with lock:
        msgs, sts = list(received), list(statuses)
    for msg in msgs:
        assert msg.camera_id == CAMERA and (msg.image_width, msg.image_height) == (WIDTH, HEIGHT)
        assert msg.model_id.endswith(f"/{tiny_models.name}")
        for det in msg.detections:
            assert det.keypoints_px.shape == (K, 2)
    seqs = [m.seq for m in msgs]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    ok_status = next(s for s in sts if s.state == "ok")
    assert ok_status.service == "edge-agent" and ok_status.instance_id == CAMERA
    assert f"source=images:{image_dir}" in ok_status.detail
