"""Capture stamps from the camera driver and GStreamer/CSI inputs (#28 item 5).

The clock conversions are pure functions and small classes with injected clocks. The grabber
paths use a fake only at the OS boundary: ``cv2.VideoCapture`` replaced by an object that
returns scripted property values (a V4L2 device cannot exist here); a real OpenCV capture of a
video file shows the file path is unchanged (grab time, ``stamp_source=grab``). GStreamer: this
machine's pip OpenCV has none, so the clear error is checked for real, and the CSI pipeline
expansion as text.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from edge_agent import frames as frames_module  # noqa: E402
from edge_agent.capture_stamps import (  # noqa: E402
    STAMP_DRIVER,
    STAMP_GRAB,
    DeviceClockMapper,
    MonotonicToRealtime,
    StampFilter,
    monotonic_realtime_offset_ns,
    realsense_stamp_ns,
    v4l2_stamp_clock,
)
from edge_agent.frames import (  # noqa: E402
    FrameSourceError,
    OpenCVGrabber,
    RealSenseGrabber,
    check_gstreamer,
    csi_pipeline,
    expand_device_uri,
    gstreamer_in_opencv,
    is_gstreamer_uri,
)
from edge_agent.sources import runtime_detail  # noqa: E402

MS = 1_000_000  # ns
S = 1_000_000_000  # ns
#: the fake machine's clocks: CLOCK_MONOTONIC starts at 5000 s (uptime), CLOCK_REALTIME at
#: 2026-11-27 in ns since the epoch
MONO0 = 5_000 * S
REAL0 = 1_795_737_600 * S


class FakeClocks:
    """A machine's two clocks that advance together; :meth:`step_realtime` is NTP stepping
    the wall clock (the monotonic clock does not move)."""

    def __init__(self) -> None:
        self.mono = MONO0
        self.real = REAL0

    def advance(self, ns: int) -> None:
        self.mono += ns
        self.real += ns

    def step_realtime(self, ns: int) -> None:
        self.real += ns

    def monotonic_ns(self) -> int:
        return self.mono

    def realtime_ns(self) -> int:
        return self.real


# --------------------------------------------------------------------------------------------
# conversions
# --------------------------------------------------------------------------------------------


def test_offset_uses_the_narrowest_bracket() -> None:
    """Reads: (mono 100, real 1100, mono 160) then (200, 1205, 210): the second bracket is the
    narrowest, offset = 1205 - 205 = 1000."""
    mono = iter([100, 160, 200, 210, 300, 390])
    real = iter([1100, 1205, 1340])
    assert monotonic_realtime_offset_ns(lambda: next(mono), lambda: next(real), samples=3) \
        == 1000


def test_monotonic_to_realtime_refreshes_after_an_ntp_step() -> None:
    clocks = FakeClocks()
    conv = MonotonicToRealtime(1.0, monotonic_ns=clocks.monotonic_ns,
                               realtime_ns=clocks.realtime_ns)
    assert conv.offset_ns == REAL0 - MONO0
    assert conv(MONO0 + 20 * MS) == REAL0 + 20 * MS
    clocks.advance(500 * MS)
    clocks.step_realtime(-3 * S)  # NTP steps the wall clock back 3 s
    assert conv(clocks.mono) == clocks.real + 3 * S  # not refreshed yet (0.5 s old)
    clocks.advance(600 * MS)  # the offset is now 1.1 s old: measured again
    assert conv(clocks.mono - 10 * MS) == clocks.real - 10 * MS


def test_device_clock_mapper_finds_the_offset_from_the_smallest_delay() -> None:
    rng = np.random.default_rng(7)
    offset = 123_456_789_000
    mapper = DeviceClockMapper(window=50)
    errors = []
    for i in range(200):
        device = 1_000 * S + i * 33 * MS
        delay = int(rng.uniform(0.2, 8.0) * MS)  # USB transfer + scheduling, never negative
        host = mapper(device, device + offset + delay)
        errors.append(host - (device + offset))
    # after a few frames the mapped stamp is within the smallest recent delay of the truth
    assert all(0 <= e <= 8 * MS for e in errors)
    assert np.median(errors[50:]) < 0.6 * MS
    mapper.reset()
    assert mapper(5 * S, 5 * S + offset + 2 * MS) == 5 * S + offset + 2 * MS


@pytest.mark.parametrize(("stamp", "clock"), [
    (MONO0 - 20 * MS, "monotonic"),
    (REAL0 - 20 * MS, "realtime"),
    (42 * S, None),  # a clock of its own
])
def test_v4l2_stamp_clock(stamp: int, clock: str | None) -> None:
    assert v4l2_stamp_clock(stamp, MONO0, REAL0) == clock


# --------------------------------------------------------------------------------------------
# StampFilter
# --------------------------------------------------------------------------------------------


def test_stamp_filter_takes_plausible_driver_stamps_and_refuses_the_rest(
        caplog: pytest.LogCaptureFixture) -> None:
    f = StampFilter("cam", max_age_s=1.0, future_tolerance_s=0.005)
    grab = REAL0
    assert f.choose(grab - 30 * MS, grab) == grab - 30 * MS and f.stamp_source == STAMP_DRIVER
    grab += 33 * MS
    assert f.choose(grab - 30 * MS, grab) == grab - 30 * MS
    caplog.set_level(logging.WARNING, logger="edge_agent.frames")
    grab += 33 * MS
    # backwards: before the previous driver stamp
    assert f.choose(grab - 100 * MS, grab) == grab and f.stamp_source == STAMP_GRAB
    assert (f.backwards, f.jumps) == (1, 0)
    grab += 33 * MS
    # repeated (the same buffer stamp twice) counts as backwards too
    last = grab - 20 * MS
    assert f.choose(last, grab) == last
    assert f.choose(last, grab + 33 * MS) == grab + 33 * MS and f.backwards == 2
    grab += 66 * MS
    # a stamp from the future and one far older than the grab: jumps
    assert f.choose(grab + 50 * MS, grab) == grab
    grab += 33 * MS
    assert f.choose(grab - 3 * S + 200 * S, grab) == grab  # later than the previous, but future
    assert f.jumps == 2
    f.reset()
    assert f.choose(grab - 2 * S, grab) == grab and f.jumps == 3  # older than max_age
    assert f.refused == 5
    # the driver gives none: the grab time, not counted as refused
    assert f.choose(None, grab + S) == grab + S and f.refused == 5
    assert f.stamp_source == STAMP_GRAB
    assert "went backwards" in caplog.text  # the first refusal is logged


# --------------------------------------------------------------------------------------------
# OpenCVGrabber with a fake VideoCapture (a V4L2 device)
# --------------------------------------------------------------------------------------------


class FakeCapture:
    """``cv2.VideoCapture`` at the OS boundary: a backend name, frames, and per read the
    ``CAP_PROP_POS_MSEC`` the driver reports; each read advances ``clocks`` by 33 ms first."""

    opened: ClassVar[list[FakeCapture]] = []

    def __init__(self, clocks: FakeClocks, backend: str, pos_msec: list[float],
                 source: Any, api: int | None = None) -> None:
        self.clocks = clocks
        self.backend = backend
        self.pos_msec = list(pos_msec)
        self.source, self.api = source, api
        self.current = 0.0
        self.props: dict[int, float] = {}
        FakeCapture.opened.append(self)

    def isOpened(self) -> bool:  # OpenCV's names
        return True

    def getBackendName(self) -> str:
        return self.backend

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        if prop == cv2.CAP_PROP_POS_MSEC:
            return self.current
        return self.props.get(prop, 0.0)

    def read(self) -> tuple[bool, np.ndarray | None]:
        if not self.pos_msec:
            return False, None
        self.clocks.advance(33 * MS)
        self.current = self.pos_msec.pop(0)
        return True, np.zeros((48, 64, 3), np.uint8)

    def release(self) -> None:
        pass


@pytest.fixture
def fake_capture(monkeypatch: pytest.MonkeyPatch
                 ) -> Iterator[Callable[[str, list[float]], FakeClocks]]:
    """Install a :class:`FakeCapture` factory as ``cv2.VideoCapture``; returns a function
    ``(backend, pos_msec per read) -> the fake machine's clocks``."""
    FakeCapture.opened = []

    def install(backend: str, pos_msec: list[float]) -> FakeClocks:
        clocks = FakeClocks()
        monkeypatch.setattr(cv2, "VideoCapture",
                            lambda source, api=None: FakeCapture(clocks, backend, pos_msec,
                                                                 source, api))
        return clocks

    yield install


def _grabber(uri: str, clocks: FakeClocks) -> OpenCVGrabber:
    return OpenCVGrabber(uri, width=64, height=48, clock_ns=clocks.realtime_ns,
                         monotonic_ns=clocks.monotonic_ns)


def test_v4l2_device_frames_carry_the_driver_stamp_in_realtime(fake_capture: Any) -> None:
    """Buffer timestamps 12 ms before each read (in CLOCK_MONOTONIC) come out as realtime
    stamps 12 ms before the grab; a stamp that goes backwards gives that frame the grab time
    and is counted; the status words name the source."""
    mono_ms = [(MONO0 + (i + 1) * 33 * MS - 12 * MS) / MS for i in range(4)]
    mono_ms[2] = mono_ms[1] - 5.0  # the driver's clock goes back once
    clocks = fake_capture("V4L2", mono_ms)
    grabber = _grabber("/dev/video0", clocks)
    grabber.open()
    stamps, sources = [], []
    for _ in range(4):
        frame = grabber.read()
        assert frame is not None
        stamps.append(frame.stamp_ns)
        sources.append(grabber.stamp_source)
    grabs = [REAL0 + (i + 1) * 33 * MS for i in range(4)]
    assert stamps[0] == grabs[0] - 12 * MS and stamps[1] == grabs[1] - 12 * MS
    assert stamps[2] == grabs[2]  # refused: the grab time
    assert stamps[3] == grabs[3] - 12 * MS
    assert sources == [STAMP_DRIVER, STAMP_DRIVER, STAMP_GRAB, STAMP_DRIVER]
    assert grabber.driver_clock == "monotonic" and grabber.stamps.backwards == 1
    assert runtime_detail(None, grabber) == "stamp_source=driver stamps_refused=1"


def test_v4l2_driver_without_stamps_or_in_a_clock_of_its_own_gets_the_grab_time(
        fake_capture: Any, caplog: pytest.LogCaptureFixture) -> None:
    clocks = fake_capture("V4L2", [0.0, 0.0])
    grabber = _grabber("0", clocks)
    grabber.open()
    frame = grabber.read()
    assert frame is not None and frame.stamp_ns == clocks.real
    assert grabber.stamp_source == STAMP_GRAB and grabber.stamps_refused == 0
    caplog.set_level(logging.WARNING, logger="edge_agent.frames")
    clocks = fake_capture("V4L2", [42_000.0, 42_033.0])  # 42 s: neither clock
    grabber = _grabber("/dev/video2", clocks)
    grabber.open()
    first, second = grabber.read(), grabber.read()
    assert first is not None and second is not None
    assert (first.stamp_ns, second.stamp_ns) == (REAL0 + 33 * MS, REAL0 + 66 * MS)
    assert grabber.driver_clock is None and grabber.stamp_source == STAMP_GRAB
    assert "neither in CLOCK_MONOTONIC nor in CLOCK_REALTIME" in caplog.text


def test_realtime_v4l2_stamps_are_taken_as_they_are(fake_capture: Any) -> None:
    clocks = fake_capture("V4L2", [(REAL0 + 33 * MS - 7 * MS) / MS])
    grabber = _grabber("/dev/video0", clocks)
    grabber.open()
    frame = grabber.read()
    # OpenCV hands the stamp over as a double of milliseconds: since the epoch that is good
    # to a fraction of a microsecond
    assert frame is not None and abs(frame.stamp_ns - (REAL0 + 26 * MS)) < 1_000
    assert grabber.driver_clock == "realtime" and grabber.stamp_source == STAMP_DRIVER


def test_streams_are_stamped_at_the_grab_whatever_pos_msec_says(fake_capture: Any) -> None:
    """An RTSP stream through FFmpeg: ``POS_MSEC`` is the position in the stream, not a
    clock; frames get the grab time."""
    clocks = fake_capture("FFMPEG", [(MONO0 + 20 * MS) / MS, (MONO0 + 53 * MS) / MS])
    grabber = _grabber("rtsp://camera.local/stream", clocks)
    grabber.open()
    frame = grabber.read()
    assert frame is not None and frame.stamp_ns == REAL0 + 33 * MS
    assert grabber.stamp_source == STAMP_GRAB


def test_a_real_video_file_is_stamped_at_the_grab_as_before(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG .avi files")
    for i in range(3):
        writer.write(np.full((48, 64, 3), 60 * i, np.uint8))
    writer.release()
    ticks = itertools.count(REAL0, 1_000)
    grabber = OpenCVGrabber(str(path), realtime=False, clock_ns=lambda: next(ticks))
    grabber.open()
    try:
        stamps = []
        while (frame := grabber.read()) is not None:
            stamps.append(frame.stamp_ns)
    finally:
        grabber.close()
    assert stamps == [REAL0, REAL0 + 1_000, REAL0 + 2_000]  # the injected grab clock
    assert grabber.stamp_source == STAMP_GRAB and grabber.driver_clock is None
    assert runtime_detail(None, grabber) == "stamp_source=grab"


# --------------------------------------------------------------------------------------------
# RealSense metadata stamps
# --------------------------------------------------------------------------------------------


def test_realsense_domains() -> None:
    mapper = DeviceClockMapper()
    arrival = REAL0 + 40 * MS
    assert realsense_stamp_ns((REAL0 + 10 * MS) / MS, "global_time", arrival, mapper) == \
        REAL0 + 10 * MS
    assert realsense_stamp_ns((REAL0 + 30 * MS) / MS, "system_time", arrival, mapper) == \
        REAL0 + 30 * MS
    assert realsense_stamp_ns(123_456.0, "hardware_clock", arrival, mapper) == arrival
    assert realsense_stamp_ns(0.0, "global_time", arrival, mapper) is None
    assert realsense_stamp_ns(float("nan"), "global_time", arrival, mapper) is None
    assert realsense_stamp_ns(5.0, "count", arrival, mapper) is None


def test_realsense_hardware_clock_follows_the_camera_and_survives_a_wrap() -> None:
    """The hardware clock through the mapper: frames 33 ms apart on the camera get stamps
    33 ms apart (not the jittery arrival times); a counter wrap is counted once and the mapper
    starts again."""
    grabber = RealSenseGrabber(clock_ns=lambda: 0)
    jitter = [3, 1, 6, 2, 4]
    stamps = []
    for i, j in enumerate(jitter):
        device_ms = 1_000.0 + 33.0 * i
        stamps.append(grabber.stamp(device_ms, "timestamp_domain.hardware_clock",
                                    REAL0 + i * 33 * MS + j * MS))
    assert grabber.stamp_source == STAMP_DRIVER
    assert np.diff(stamps).tolist()[1:] == [33 * MS] * 3  # once the smallest delay is seen
    wrapped = grabber.stamp(2.0, "hardware_clock", REAL0 + 5 * 33 * MS + 2 * MS)
    assert wrapped == REAL0 + 5 * 33 * MS + 2 * MS and grabber.stamps.backwards == 1
    after = grabber.stamp(35.0, "hardware_clock", REAL0 + 6 * 33 * MS + 9 * MS)
    assert after == REAL0 + 6 * 33 * MS + 2 * MS  # mapped with the new offset
    assert grabber.stamp_source == STAMP_DRIVER


# --------------------------------------------------------------------------------------------
# GStreamer / CSI
# --------------------------------------------------------------------------------------------


def test_gstreamer_detection_reads_the_build_information() -> None:
    assert gstreamer_in_opencv("Video I/O:\n    FFMPEG:   YES\n    GStreamer:   YES (1.20.3)\n")
    assert not gstreamer_in_opencv("Video I/O:\n    GStreamer:                   NO\n")
    assert not gstreamer_in_opencv("Video I/O:\n    FFMPEG: YES\n")
    this_build = cv2.getBuildInformation()
    assert gstreamer_in_opencv() == gstreamer_in_opencv(this_build)


@pytest.mark.parametrize(("uri", "expected"), [
    ("csi://0", True),
    ("v4l2src device=/dev/video0 ! videoconvert ! appsink", True),
    ("/dev/video0", False),
    ("0", False),
    ("rtsp://cam.lab/stream", False),
    ("clip.avi", False),
])
def test_gstreamer_uris(uri: str, expected: bool) -> None:
    assert is_gstreamer_uri(uri) == expected


def test_csi_expands_to_the_argus_pipeline_at_the_cameras_size() -> None:
    ntsc = 30_000 / 1_001  # 29.97 Hz as a camera reports it
    pipeline = expand_device_uri("csi://1?flip=2", 1920, 1080, ntsc)
    assert pipeline == csi_pipeline(1, 1920, 1080, ntsc, 2)
    assert pipeline.startswith("nvarguscamerasrc sensor-id=1 ! video/x-raw(memory:NVMM), ")
    assert "width=(int)1920, height=(int)1080" in pipeline
    assert "framerate=(fraction)30000/1001" in pipeline and "flip-method=2" in pipeline
    assert pipeline.endswith("appsink drop=true max-buffers=1 sync=false")
    assert "framerate=(fraction)30/1" in expand_device_uri("csi://0", 848, 480, None)
    assert expand_device_uri("/dev/video0", 848, 480, None) == "/dev/video0"
    with pytest.raises(FrameSourceError, match="expected csi://N"):
        expand_device_uri("csi://front", 848, 480, None)
    with pytest.raises(FrameSourceError, match="width and height"):
        expand_device_uri("csi://0", None, None, None)


def test_without_gstreamer_in_opencv_the_error_says_what_to_install() -> None:
    if gstreamer_in_opencv():
        pytest.skip("this OpenCV has GStreamer")
    for uri in ("csi://0", "videotestsrc ! videoconvert ! appsink"):
        with pytest.raises(FrameSourceError) as err:
            check_gstreamer(uri)
        text = str(err.value)
        assert text.startswith(f"{uri}: a GStreamer pipeline") and "GStreamer: NO" in text
        assert "opencv-python-headless" in text and "--system-site-packages" in text
        with pytest.raises(FrameSourceError, match="built without GStreamer"):
            OpenCVGrabber(uri, width=848, height=480).open()
    check_gstreamer("/dev/video0")  # not a pipeline: nothing to check


def test_edge_agent_refuses_a_csi_camera_at_start_without_gstreamer() -> None:
    from edge_agent.service import build_node, build_parser
    from protocol.errors import UsageError
    from tests.conftest import REPO_ROOT

    if gstreamer_in_opencv():
        pytest.skip("this OpenCV has GStreamer")
    args = build_parser().parse_args(["--site", str(REPO_ROOT / "simulation" / "sites" /
                                                    "paper_lab.yaml"),
                                      "--camera", "cam1", "--device", "csi://0"])
    with pytest.raises(UsageError, match="built without GStreamer"):
        build_node(args)


def test_a_pipeline_opens_through_the_gstreamer_backend(fake_capture: Any,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """With an OpenCV that reports GStreamer, ``csi://0`` opens ``cv2.VideoCapture`` with the
    expanded pipeline and ``CAP_GSTREAMER``, and frames are stamped at the grab."""
    monkeypatch.setattr(cv2, "getBuildInformation", lambda: "  GStreamer:  YES (1.20.3)\n")
    clocks = fake_capture("GSTREAMER", [20.0])
    grabber = OpenCVGrabber("csi://0", width=848, height=480, clock_ns=clocks.realtime_ns,
                            monotonic_ns=clocks.monotonic_ns)
    grabber.open()
    cap = FakeCapture.opened[-1]
    assert cap.source == csi_pipeline(0, 848, 480) and cap.api == cv2.CAP_GSTREAMER
    assert cap.props == {}  # no width/height/fps set on a pipeline: it fixes them itself
    frame = grabber.read()
    assert frame is not None and frame.stamp_ns == REAL0 + 33 * MS
    assert grabber.stamp_source == STAMP_GRAB
    assert frames_module.is_gstreamer_uri(grabber.uri)
