"""Frame grabbers and the latest-frame reader thread (:mod:`edge_agent.frames`).

Checked here without cameras: OpenCV on a small MJPG video written to ``tmp_path`` (RGB out,
size, sequence numbers, injected clock, end of file, real-time pacing, errors naming the uri),
image folders (name order, BGR→RGB, grayscale / 16-bit / BGRA conversion, unreadable files
skipped and counted, end vs loop, folder errors), the RealSense grabber without
``pyrealsense2``, and :class:`LatestFrameReader` driven by small fake grabbers (newest frame
only, skipped counts, open retries with doubling back-off, re-opens after a read failure,
finite sources ending, foreign exception types, prompt stop during back-off).
"""

from __future__ import annotations

import itertools
import logging
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from edge_agent.frames import (  # noqa: E402
    Frame,
    FrameSourceError,
    ImageFolderGrabber,
    LatestFrameReader,
    OpenCVGrabber,
    ReaderStatus,
    RealSenseGrabber,
)
from protocol.errors import SmartedgeError  # noqa: E402
from tests.conftest import wait_until  # noqa: E402

VIDEO_W, VIDEO_H, VIDEO_FRAMES, VIDEO_FPS = 64, 48, 5, 10.0


def _counter_clock(start: int = 1_000_000_000, step: int = 1_000) -> Callable[[], int]:
    """A fake ``clock_ns``: ``start``, ``start + step``, ... (one value per call)."""
    it = itertools.count(start, step)
    return lambda: next(it)


@pytest.fixture
def video(tmp_path: Path) -> Path:
    """A 64x48, 10 fps, 5-frame MJPG ``.avi``: frame ``i`` is red (BGR ``(0, 0, 200)``) with
    blue ``40 * i``, so the channel order and the frame order can be read back."""
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), VIDEO_FPS,
                             (VIDEO_W, VIDEO_H))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG .avi files")
    for i in range(VIDEO_FRAMES):
        bgr = np.zeros((VIDEO_H, VIDEO_W, 3), np.uint8)
        bgr[..., 2] = 200
        bgr[..., 0] = 40 * i
        writer.write(bgr)
    writer.release()
    return path


def _read_all(grabber: OpenCVGrabber | ImageFolderGrabber, limit: int = 100) -> list[Frame]:
    frames = []
    for _ in range(limit):
        frame = grabber.read()
        if frame is None:
            break
        frames.append(frame)
    return frames


# --------------------------------------------------------------------------------------------
# OpenCVGrabber
# --------------------------------------------------------------------------------------------


def test_opencv_video_file_frames_are_rgb_sized_numbered_and_stamped(video: Path) -> None:
    """Every frame of the file comes out as (H, W, 3) uint8 RGB (red in channel 0), seq 1..N,
    stamps from the injected clock; the end of the file is ``None`` (again and again)."""
    clock = _counter_clock()
    grabber = OpenCVGrabber(str(video), realtime=False, clock_ns=clock)
    assert grabber.label == f"opencv:{video}"
    grabber.open()
    try:
        frames = _read_all(grabber)
        assert len(frames) == VIDEO_FRAMES
        for i, frame in enumerate(frames):
            assert frame.image_rgb.shape == (VIDEO_H, VIDEO_W, 3)
            assert frame.image_rgb.dtype == np.uint8
            r, g, b = frame.image_rgb[VIDEO_H // 2, VIDEO_W // 2].astype(int)
            assert abs(r - 200) <= 12 and g <= 12 and abs(b - 40 * i) <= 12  # MJPG is lossy
        assert [f.seq for f in frames] == list(range(1, VIDEO_FRAMES + 1))
        stamps = [f.stamp_ns for f in frames]
        assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
        assert all(1_000_000_000 <= s < 1_000_000_000 + 1_000 * 100 for s in stamps)
        assert grabber.read() is None
        assert grabber.read() is None
    finally:
        grabber.close()
    with pytest.raises(FrameSourceError, match="not open"):
        grabber.read()


def test_opencv_video_file_reopen_restarts_from_the_first_frame(video: Path) -> None:
    """``open()`` on an open grabber releases the old capture and starts the file again; the
    sequence number keeps counting (it numbers frames of the grabber, not of the file)."""
    grabber = OpenCVGrabber(str(video), realtime=False)
    grabber.open()
    first = grabber.read()
    grabber.open()
    again = grabber.read()
    grabber.close()
    grabber.close()  # idempotent
    assert first is not None and again is not None
    assert again.seq == first.seq + 1
    assert np.abs(again.image_rgb.astype(int) - first.image_rgb.astype(int)).max() <= 12


def test_opencv_realtime_file_is_paced_at_its_frame_rate(video: Path) -> None:
    """With ``realtime=True`` a 10 fps file delivers about one frame per 0.1 s (5 frames: at
    least ~0.4 s), without it the same file is read at once."""
    fast = OpenCVGrabber(str(video), realtime=False)
    fast.open()
    t0 = time.monotonic()
    assert len(_read_all(fast)) == VIDEO_FRAMES
    fast_s = time.monotonic() - t0
    fast.close()

    paced = OpenCVGrabber(str(video), realtime=True)
    paced.open()
    t0 = time.monotonic()
    assert len(_read_all(paced)) == VIDEO_FRAMES
    paced_s = time.monotonic() - t0
    paced.close()
    assert 0.35 <= paced_s <= 3.0, paced_s
    assert fast_s < paced_s


def test_opencv_missing_file_and_missing_device_name_the_uri(tmp_path: Path) -> None:
    """A video file that does not exist and a device path with no device behind it raise
    :class:`FrameSourceError` (a :class:`SmartedgeError`) whose message names the uri."""
    missing = tmp_path / "nope.avi"
    with pytest.raises(FrameSourceError, match="not found") as err:
        OpenCVGrabber(str(missing)).open()
    assert str(missing) in str(err.value)
    assert isinstance(err.value, SmartedgeError)

    grabber = OpenCVGrabber("/dev/video99", width=848, height=480, fps=30)
    with pytest.raises(FrameSourceError, match="cannot open") as err:
        grabber.open()
    assert "/dev/video99" in str(err.value)
    with pytest.raises(FrameSourceError, match="/dev/video99"):
        grabber.read()  # never opened


def test_opencv_file_that_is_not_a_video_is_refused(tmp_path: Path) -> None:
    """A file with a video suffix but garbage inside cannot be opened (or yields nothing):
    either way no exception other than :class:`FrameSourceError` and no frame."""
    bogus = tmp_path / "bogus.avi"
    bogus.write_bytes(b"this is not a video" * 100)
    grabber = OpenCVGrabber(str(bogus), realtime=False)
    try:
        grabber.open()
    except FrameSourceError as exc:
        assert str(bogus) in str(exc)
    else:
        assert grabber.read() is None
    finally:
        grabber.close()


# --------------------------------------------------------------------------------------------
# ImageFolderGrabber
# --------------------------------------------------------------------------------------------


def _solid_bgr(b: int, g: int, r: int, size: tuple[int, int] = (24, 16)) -> np.ndarray:
    w, h = size
    image = np.empty((h, w, 3), np.uint8)
    image[...] = (b, g, r)
    return image


def test_image_folder_reads_in_name_order_and_converts_bgr_to_rgb(tmp_path: Path) -> None:
    """Images come in file-name order (not creation order), RGB (a blue BGR PNG reads
    ``(0, 0, 255)``), with seq 1..N and stamps from the injected clock; other files are
    ignored; after the last image ``read()`` returns ``None``."""
    cv2.imwrite(str(tmp_path / "c.png"), _solid_bgr(0, 255, 0))  # green
    cv2.imwrite(str(tmp_path / "a.png"), _solid_bgr(255, 0, 0))  # blue
    cv2.imwrite(str(tmp_path / "b.bmp"), _solid_bgr(0, 0, 255))  # red
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / "sub.png").mkdir()  # a folder with an image suffix is not an image
    grabber = ImageFolderGrabber(tmp_path, rate_hz=0, clock_ns=_counter_clock(5, 5))
    assert grabber.label == f"images:{tmp_path}"
    grabber.open()
    frames = _read_all(grabber)
    assert [tuple(f.image_rgb[0, 0]) for f in frames] == [(0, 0, 255), (255, 0, 0), (0, 255, 0)]
    assert all(f.image_rgb.shape == (16, 24, 3) and f.image_rgb.dtype == np.uint8
               for f in frames)
    assert [f.seq for f in frames] == [1, 2, 3]
    assert [f.stamp_ns for f in frames] == [5, 10, 15]
    assert grabber.read() is None
    assert grabber.unreadable == 0


def test_image_folder_converts_gray_16bit_and_bgra(tmp_path: Path) -> None:
    """A grayscale PNG becomes three equal channels, a 16-bit PNG keeps its top byte, a
    16-bit colour PNG and a BGRA PNG come out as plain RGB uint8."""
    gray = np.full((10, 12), 77, np.uint8)
    deep = np.full((10, 12), 200 * 256 + 99, np.uint16)
    deep_bgr = np.zeros((10, 12, 3), np.uint16)
    deep_bgr[..., 0] = 10 * 256  # blue
    deep_bgr[..., 2] = 250 * 256 + 255  # red
    bgra = np.zeros((10, 12, 4), np.uint8)
    bgra[..., 1] = 123  # green
    bgra[..., 3] = 255
    for name, image in (("1_gray.png", gray), ("2_deep.png", deep), ("3_deep_bgr.png", deep_bgr),
                        ("4_bgra.png", bgra)):
        assert cv2.imwrite(str(tmp_path / name), image)
    grabber = ImageFolderGrabber(tmp_path, rate_hz=0)
    grabber.open()
    frames = _read_all(grabber)
    assert len(frames) == 4 and grabber.unreadable == 0
    assert all(f.image_rgb.shape == (10, 12, 3) and f.image_rgb.dtype == np.uint8
               for f in frames)
    assert tuple(frames[0].image_rgb[3, 4]) == (77, 77, 77)
    assert tuple(frames[1].image_rgb[3, 4]) == (200, 200, 200)
    assert tuple(frames[2].image_rgb[3, 4]) == (250, 0, 10)
    assert tuple(frames[3].image_rgb[3, 4]) == (0, 123, 0)


def test_image_folder_skips_and_counts_unreadable_images(tmp_path: Path,
                                                         caplog: pytest.LogCaptureFixture) -> None:
    """A ``.png`` of garbage bytes (and a float32 TIFF, an unsupported pixel type) are logged
    as errors naming the file, counted in ``unreadable`` and skipped; the good images around
    them still come out with consecutive sequence numbers."""
    cv2.imwrite(str(tmp_path / "a.png"), _solid_bgr(1, 2, 3))
    (tmp_path / "b.png").write_bytes(b"\x89PNG garbage, not really a png" * 10)
    assert cv2.imwrite(str(tmp_path / "c.tiff"), np.full((8, 8, 3), 0.5, np.float32))
    cv2.imwrite(str(tmp_path / "d.png"), _solid_bgr(4, 5, 6))
    grabber = ImageFolderGrabber(tmp_path, rate_hz=0)
    grabber.open()
    with caplog.at_level(logging.ERROR, logger="edge_agent.frames"):
        frames = _read_all(grabber)
    assert [tuple(f.image_rgb[0, 0]) for f in frames] == [(3, 2, 1), (6, 5, 4)]
    assert [f.seq for f in frames] == [1, 2]
    assert grabber.unreadable == 2
    logged = "\n".join(r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR)
    assert str(tmp_path / "b.png") in logged and str(tmp_path / "c.tiff") in logged
    assert "skipped" in logged


def test_image_folder_end_versus_loop(tmp_path: Path) -> None:
    """Without ``loop`` the folder is read once, then ``None``; with ``loop`` it starts over
    (a, b, a, b, a...) and the sequence number keeps increasing."""
    cv2.imwrite(str(tmp_path / "a.png"), _solid_bgr(0, 0, 10))
    cv2.imwrite(str(tmp_path / "b.png"), _solid_bgr(0, 0, 20))
    once = ImageFolderGrabber(tmp_path, rate_hz=0)
    once.open()
    assert len(_read_all(once)) == 2
    assert once.read() is None

    looping = ImageFolderGrabber(tmp_path, rate_hz=0, loop=True)
    looping.open()
    frames = [looping.read() for _ in range(5)]
    assert all(f is not None for f in frames)
    assert [int(f.image_rgb[0, 0, 0]) for f in frames if f] == [10, 20, 10, 20, 10]
    assert [f.seq for f in frames if f] == [1, 2, 3, 4, 5]
    looping.close()


def test_image_folder_is_paced_at_its_rate(tmp_path: Path) -> None:
    """``rate_hz=20``: 4 images take at least ~0.15 s (the first comes at once)."""
    for i in range(4):
        cv2.imwrite(str(tmp_path / f"{i}.png"), _solid_bgr(i, i, i))
    grabber = ImageFolderGrabber(tmp_path, rate_hz=20.0)
    grabber.open()
    t0 = time.monotonic()
    assert len(_read_all(grabber)) == 4
    elapsed = time.monotonic() - t0
    assert 0.13 <= elapsed <= 3.0, elapsed


def test_image_folder_missing_or_empty_folder_errors_name_the_folder(tmp_path: Path) -> None:
    """A folder that does not exist, a file instead of a folder, and a folder without images
    raise :class:`FrameSourceError` naming the folder."""
    missing = tmp_path / "missing"
    with pytest.raises(FrameSourceError, match="not found") as err:
        ImageFolderGrabber(missing).open()
    assert str(missing) in str(err.value)

    a_file = tmp_path / "file.png"
    cv2.imwrite(str(a_file), _solid_bgr(0, 0, 0))
    with pytest.raises(FrameSourceError, match="not found"):
        ImageFolderGrabber(a_file).open()

    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.txt").write_text("no images here")
    with pytest.raises(FrameSourceError, match="no images") as err:
        ImageFolderGrabber(empty).open()
    assert str(empty) in str(err.value)


def test_image_folder_of_only_unreadable_images_fails_naming_the_folder(
        tmp_path: Path) -> None:
    """Without ``loop`` a folder of garbage ``.png`` files counts every file as unreadable and
    raises FrameSourceError naming the folder (the reader then reports it in the status)."""
    for name in ("a.png", "b.jpg"):
        (tmp_path / name).write_bytes(b"garbage" * 20)
    grabber = ImageFolderGrabber(tmp_path, rate_hz=0)
    grabber.open()
    with pytest.raises(FrameSourceError, match="none of its") as info:
        grabber.read()
    assert str(tmp_path) in str(info.value)
    assert grabber.unreadable == 2


def test_looping_folder_of_only_unreadable_images_does_not_hang(tmp_path: Path) -> None:
    """A looping folder whose images are all unreadable should fail (``FrameSourceError``)
    or return, not spin in ``read()`` forever logging the same files again and again."""
    (tmp_path / "a.png").write_bytes(b"garbage" * 20)
    grabber = ImageFolderGrabber(tmp_path, rate_hz=100.0, loop=True)  # paced: no hot spin
    grabber.open()
    outcome: list[object] = []

    def read() -> None:
        try:
            outcome.append(grabber.read())
        except FrameSourceError as exc:
            outcome.append(exc)

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    thread.join(1.0)
    hung = thread.is_alive()
    grabber.loop = False  # let the stuck read() reach the end of the list and return
    thread.join(2.0)
    assert not hung, f"read() still running after 1 s ({grabber.unreadable} unreadable reads)"


# --------------------------------------------------------------------------------------------
# RealSenseGrabber
# --------------------------------------------------------------------------------------------


def test_realsense_without_pyrealsense2_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    """Opening a RealSense without ``pyrealsense2`` raises :class:`FrameSourceError` naming
    the missing package; reading a grabber that is not open says it is not open."""
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails even if installed
    grabber = RealSenseGrabber("123456")
    assert grabber.label == "realsense:123456"
    assert RealSenseGrabber().label == "realsense:first"
    with pytest.raises(FrameSourceError, match="pyrealsense2"):
        grabber.open()
    with pytest.raises(FrameSourceError, match="not open"):
        grabber.read()
    grabber.close()


# --------------------------------------------------------------------------------------------
# LatestFrameReader with fake grabbers
# --------------------------------------------------------------------------------------------


def _frame(seq: int) -> Frame:
    return Frame(np.full((4, 6, 3), seq % 256, np.uint8), 1_000 * seq, seq)


class ScriptGrabber:
    """A fake grabber following a script.

    ``opens``: what each ``open()`` call does, in order (an exception instance to raise, or
    ``None`` to succeed; past the end: succeed). ``reads``: per successful open, a list of
    items: an int (a frame with that seq), an exception instance (raised), ``"end"`` (return
    ``None``) or ``"block"`` (a live camera waiting: until :attr:`released` is set, then
    ``None``). ``on_open`` is called at the start of each ``open()`` (to look at the reader's
    status then)."""

    def __init__(self, opens: list[BaseException | None] | None = None,
                 reads: list[list[object]] | None = None,
                 on_open: Callable[[], None] | None = None, label: str = "fake:cam") -> None:
        self.label = label
        self._opens = list(opens or [])
        self._reads: Iterator[list[object]] = iter(reads or [])
        self._current: list[object] = []
        self.on_open = on_open
        self.open_calls: list[float] = []
        self.close_calls = 0
        self.released = threading.Event()

    def open(self) -> None:
        self.open_calls.append(time.monotonic())
        if self.on_open is not None:
            self.on_open()
        outcome = self._opens.pop(0) if self._opens else None
        if outcome is not None:
            raise outcome
        self._current = list(next(self._reads, ["block"]))

    def read(self) -> Frame | None:
        item = self._current.pop(0) if self._current else "block"
        if isinstance(item, BaseException):
            raise item
        if item == "end":
            return None
        if item == "block":
            self.released.wait(10.0)
            return None
        assert isinstance(item, int)
        return _frame(item)

    def close(self) -> None:
        self.close_calls += 1


def _stop(reader: LatestFrameReader, grabber: ScriptGrabber) -> None:
    """Let a blocked fake ``read()`` return, then stop the reader."""
    grabber.released.set()
    reader.stop()


def _wait_state(reader: LatestFrameReader, state: str, timeout_s: float = 5.0) -> ReaderStatus:
    assert wait_until(lambda: reader.status().state == state, timeout_s), reader.status()
    return reader.status()


def test_reader_hands_over_only_the_newest_frame_and_counts_skipped() -> None:
    """Five frames grabbed before the worker looks: ``take()`` gives the 5th, the other four
    count as skipped, the next ``take()`` gives ``None``; a finite source ends in ``ended``
    and its grabber is closed."""
    grabber = ScriptGrabber(reads=[[1, 2, 3, 4, 5, "end"]])
    reader = LatestFrameReader(grabber)
    assert reader.status() == ReaderStatus()  # opening, nothing yet
    assert reader.take() is None
    reader.start()
    try:
        status = _wait_state(reader, "ended")
        assert (status.grabbed, status.skipped, status.failures, status.reopens) == (5, 4, 0, 0)
        assert status.error == ""
        frame = reader.take()
        assert frame is not None and frame.seq == 5
        assert reader.take() is None
        assert grabber.close_calls >= 1
        assert len(grabber.open_calls) == 1
    finally:
        reader.stop()
    assert reader.status().state == "stopped"


def test_reader_take_between_frames_skips_nothing() -> None:
    """A worker that takes every frame before the next arrives sees all of them in order and
    nothing counts as skipped."""
    gate = threading.Semaphore(0)

    class Gated(ScriptGrabber):
        def read(self) -> Frame | None:
            gate.acquire(timeout=5.0)
            return super().read()

    reader = LatestFrameReader(Gated(reads=[[1, 2, 3, "end"]])).start()
    seen: list[int] = []
    try:
        for _ in range(3):
            gate.release()
            assert wait_until(lambda: reader.status().grabbed > len(seen), 5.0)
            frame = reader.take()
            assert frame is not None
            seen.append(frame.seq)
        gate.release()
        status = _wait_state(reader, "ended")
    finally:
        reader.stop()
    assert seen == [1, 2, 3]
    assert (status.grabbed, status.skipped) == (3, 0)


def test_reader_retries_a_failing_open_with_doubling_backoff() -> None:
    """``open()`` fails twice, then works: the status says ``retrying`` with the error text
    and ``retry_in_s`` 0.05 then 0.1 (doubling) between tries, ``failures == 2`` and no
    re-open is counted (the source was never open); then ``ok`` with frames and no error."""
    snapshots: list[ReaderStatus] = []
    reader: LatestFrameReader | None = None

    def look() -> None:
        assert reader is not None
        snapshots.append(reader.status())

    grabber = ScriptGrabber(
        opens=[FrameSourceError("fake:cam: no such camera"),
               FrameSourceError("fake:cam: still no camera"), None],
        reads=[[7, 8]], on_open=look)
    reader = LatestFrameReader(grabber, backoff_s=0.05, max_backoff_s=1.0)
    reader.start()
    try:
        status = _wait_state(reader, "ok")
        assert wait_until(lambda: reader.status().grabbed == 2, 5.0)
        status = reader.status()
    finally:
        _stop(reader, grabber)
    assert len(snapshots) == 3
    assert snapshots[0].state == "opening" and snapshots[0].failures == 0
    assert (snapshots[1].state, snapshots[1].failures, snapshots[1].retry_in_s) == \
        ("retrying", 1, pytest.approx(0.05))
    assert snapshots[1].error == "fake:cam: no such camera"
    assert (snapshots[2].state, snapshots[2].failures, snapshots[2].retry_in_s) == \
        ("retrying", 2, pytest.approx(0.1))
    assert snapshots[2].error == "fake:cam: still no camera"
    gaps = np.diff(grabber.open_calls)
    assert gaps[0] >= 0.045 and gaps[1] >= 0.095, gaps  # the waits really happened
    assert (status.state, status.error, status.failures, status.reopens) == ("ok", "", 2, 0)
    assert status.retry_in_s == 0.0
    frame = reader.take()
    assert frame is not None and frame.seq == 8


def test_reader_backoff_is_capped_at_max_backoff() -> None:
    """An ``open()`` that always fails: ``retry_in_s`` goes 0.01, 0.02, 0.04, 0.04, ...
    (doubling up to ``max_backoff_s``)."""
    delays: list[float] = []
    reader: LatestFrameReader | None = None

    def look() -> None:
        assert reader is not None
        st = reader.status()
        if st.failures:
            delays.append(st.retry_in_s)

    grabber = ScriptGrabber(opens=[FrameSourceError("fake:cam: down")] * 50, on_open=look)
    reader = LatestFrameReader(grabber, backoff_s=0.01, max_backoff_s=0.04)
    reader.start()  # after the assignment: ``look`` reads ``reader``
    try:
        assert wait_until(lambda: len(delays) >= 5, 5.0)
    finally:
        reader.stop()
    assert delays[:5] == pytest.approx([0.01, 0.02, 0.04, 0.04, 0.04])


def test_reader_reopens_after_a_read_failure() -> None:
    """``read()`` raises :class:`FrameSourceError` mid-stream: the status shows the error,
    the grabber is closed and opened again (``reopens == 1``), frames flow again (the error is
    cleared) and the source then ends normally."""
    snapshots: list[ReaderStatus] = []
    reader: LatestFrameReader | None = None

    def look() -> None:
        assert reader is not None
        snapshots.append(reader.status())

    grabber = ScriptGrabber(
        reads=[[1, 2, FrameSourceError("fake:cam: unplugged")], [3, 4, "end"]], on_open=look)
    reader = LatestFrameReader(grabber, backoff_s=0.02)
    reader.start()  # after the assignment: ``look`` reads ``reader``
    try:
        status = _wait_state(reader, "ended")
    finally:
        reader.stop()
    assert (status.grabbed, status.failures, status.reopens) == (4, 1, 1)
    assert status.error == ""  # cleared by the successful re-open
    again = snapshots[1]  # what the status said while waiting to re-open
    assert (again.state, again.error, again.grabbed, again.reopens) == \
        ("retrying", "fake:cam: unplugged", 2, 0)
    assert len(grabber.open_calls) == 2
    assert grabber.close_calls >= 2  # after the failure, and at the end
    frame = reader.take()
    assert frame is not None and frame.seq == 4


def test_reader_survives_unexpected_exception_types() -> None:
    """A driver raising ``RuntimeError`` in ``read()`` and ``OSError`` in ``open()`` does not
    kill the thread: both are reported with the grabber's label and the exception type, and
    the reader carries on."""
    errors: list[str] = []
    reader: LatestFrameReader | None = None

    def look() -> None:
        assert reader is not None
        if reader.status().error:
            errors.append(reader.status().error)

    grabber = ScriptGrabber(
        opens=[None, OSError("ioctl failed")],
        reads=[[1, RuntimeError("driver exploded")], [2, "block"]], on_open=look)
    reader = LatestFrameReader(grabber, backoff_s=0.01)
    reader.start()  # after the assignment: ``look`` reads ``reader``
    try:
        assert wait_until(lambda: reader.status().grabbed == 2, 5.0), reader.status()
        status = reader.status()
        assert status.state == "ok"
        assert reader._thread.is_alive()
    finally:
        _stop(reader, grabber)
    assert errors[:2] == ["fake:cam: RuntimeError: driver exploded",
                          "fake:cam: OSError: ioctl failed"]
    assert (status.failures, status.reopens) == (2, 1)


def test_reader_stop_is_prompt_during_backoff() -> None:
    """``stop()`` during a long back-off (5 s) returns at once, the thread is gone, the state
    is ``stopped`` and the grabber was closed."""
    grabber = ScriptGrabber(opens=[FrameSourceError("fake:cam: down")] * 10)
    reader = LatestFrameReader(grabber, backoff_s=5.0).start()
    _wait_state(reader, "retrying")
    t0 = time.monotonic()
    reader.stop()
    assert time.monotonic() - t0 < 1.0
    assert not reader._thread.is_alive()
    assert reader.status().state == "stopped"
    assert len(grabber.open_calls) == 1
    assert grabber.close_calls >= 1
