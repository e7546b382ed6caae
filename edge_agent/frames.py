"""Where an edge agent's images come from: grabbers behind one interface, and a reader thread
that always hands over the newest frame.

A :class:`Grabber` opens a device, stream, file or folder and returns :class:`Frame` s (RGB
uint8 with the capture stamp in the sensor clock: the camera's timestamp where the source has
one, else the time of the grab). :class:`LatestFrameReader` runs one grabber in a background
thread (blocking I/O stays out of the service's worker loop), keeps only the newest frame and
counts the ones the worker never took; a grabber that fails to open or stops delivering is
reported in :meth:`LatestFrameReader.status` and retried with exponential back-off, and never
stops the service.

Grabbers: :class:`OpenCVGrabber` (V4L2 device index or path, RTSP/HTTP URL, video file),
:class:`ImageFolderGrabber` (a folder of images, paced at a rate), :class:`RealSenseGrabber`
(Intel RealSense colour stream, with depth aligned to it on request, through ``pyrealsense2``,
optional). The simulation's renderer
is registered as a source from the top floor.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final, Protocol

import numpy as np

from protocol.errors import SmartedgeError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES: Final = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")


class FrameSourceError(SmartedgeError):
    """A grabber cannot open or read its source (the message names the device, URL or file)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Frame:
    """One image: ``image_rgb`` (H, W, 3) uint8, ``stamp_ns`` capture time in the sensor clock,
    ``seq`` the grabber's frame counter; ``depth_m`` (H, W) float32 depth aligned to the colour
    image (z in the colour camera's optical frame, metres; 0, inf or NaN = no depth), ``None``
    from a source without depth."""

    image_rgb: np.ndarray
    stamp_ns: int
    seq: int
    depth_m: np.ndarray | None = None


class Grabber(Protocol):
    """Blocking frame input. ``open()`` raises :class:`FrameSourceError`; ``read()`` returns the
    next frame, ``None`` at the end of a finite source (a file, a folder), or raises
    :class:`FrameSourceError` when the source fails; ``close()`` releases it."""

    label: str

    def open(self) -> None: ...

    def read(self) -> Frame | None: ...

    def close(self) -> None: ...


def _to_rgb(image: np.ndarray, what: str) -> np.ndarray:
    import cv2

    if image is None or not isinstance(image, np.ndarray) or image.size == 0:
        raise FrameSourceError(f"{what}: empty image")
    if image.dtype != np.uint8:
        if image.dtype == np.uint16:
            image = (image >> 8).astype(np.uint8)
        else:
            raise FrameSourceError(f"{what}: unsupported pixel type {image.dtype}")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    raise FrameSourceError(f"{what}: unsupported image shape {image.shape}")


class OpenCVGrabber:
    """``cv2.VideoCapture``: ``uri`` is a device index (``"0"``), a device path
    (``/dev/video0``), a stream URL (``rtsp://``, ``http://``) or a video file. ``width`` /
    ``height`` / ``fps`` are requested from devices (None: the device's default). Video files
    play at their own frame rate (``realtime``) or as fast as they are read, once or
    (``loop``) over and over. Stamps: the time
    of the grab (``CLOCK_REALTIME``), which is what a live camera's frame is closest to."""

    def __init__(self, uri: str, *, width: int | None = None, height: int | None = None,
                 fps: float | None = None, realtime: bool = True, loop: bool = False,
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.uri = str(uri)
        self.loop = loop
        self.label = f"opencv:{self.uri}"
        self.width, self.height, self.fps = width, height, fps
        self.realtime = realtime
        self._clock_ns = clock_ns
        self._cap: Any = None
        self._seq = 0
        self._is_file = False
        self._period_s = 0.0
        self._next_s = 0.0

    def open(self) -> None:
        import cv2

        self.close()
        source: int | str = int(self.uri) if self.uri.isdigit() else self.uri
        self._is_file = isinstance(source, str) and "://" not in source and \
            not source.startswith("/dev/")
        if self._is_file and not Path(source).is_file():  # type: ignore[arg-type]
            raise FrameSourceError(f"{self.uri}: video file not found")
        cap = cv2.VideoCapture(source)
        if not cap.isOpened():
            cap.release()
            raise FrameSourceError(f"{self.uri}: OpenCV cannot open this device, stream or file")
        if not self._is_file:
            if self.width:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
            if self.height:
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
            if self.fps:
                cap.set(cv2.CAP_PROP_FPS, self.fps)
        fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
        self._period_s = 1.0 / fps if self._is_file and self.realtime and 0 < fps < 1000 else 0.0
        self._next_s = time.monotonic()
        self._cap = cap
        log.info("%s: opened (%s)", self.uri, "file" if self._is_file else "live")

    def read(self) -> Frame | None:
        if self._cap is None:
            raise FrameSourceError(f"{self.uri}: not open")
        if self._period_s:
            delay = self._next_s - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            self._next_s = max(self._next_s + self._period_s, time.monotonic() - self._period_s)
        ok, image = self._cap.read()
        if not ok and self._is_file and self.loop and self._seq > 0:
            import cv2

            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)  # back to the first frame
            ok, image = self._cap.read()
        stamp = self._clock_ns()
        if not ok:
            if self._is_file:
                return None
            raise FrameSourceError(f"{self.uri}: no frame (device unplugged or stream ended)")
        self._seq += 1
        return Frame(_to_rgb(image, self.uri), stamp, self._seq)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class ImageFolderGrabber:
    """The images of a folder in name order, one every ``1 / rate_hz`` seconds (``rate_hz``
    0: as fast as read), once or looping. An image that cannot be read is logged and counted
    in :attr:`unreadable`, and skipped; a folder none of whose images can be read raises
    :class:`FrameSourceError`."""

    def __init__(self, folder: str | Path, *, rate_hz: float = 10.0, loop: bool = False,
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.folder = Path(folder)
        self.label = f"images:{self.folder}"
        self.rate_hz = rate_hz
        self.loop = loop
        self._clock_ns = clock_ns
        self._files: list[Path] = []
        self._index = 0
        self._seq = 0
        self._next_s = 0.0
        self.unreadable = 0
        self.last_error = ""

    def open(self) -> None:
        if not self.folder.is_dir():
            raise FrameSourceError(f"{self.folder}: image folder not found")
        self._files = sorted(p for p in self.folder.iterdir()
                             if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
        if not self._files:
            raise FrameSourceError(f"{self.folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
        self._index = 0
        self._next_s = time.monotonic()

    def read(self) -> Frame | None:
        import cv2

        failed_in_a_row = 0
        while True:
            if failed_in_a_row >= len(self._files):
                raise FrameSourceError(f"{self.folder}: none of its {len(self._files)} images "
                                       f"can be read ({self.last_error})")
            if self._index >= len(self._files):
                if not self.loop:
                    if self._seq == 0 and self.unreadable:
                        raise FrameSourceError(f"{self.folder}: none of its images can be "
                                               f"read ({self.last_error})")
                    return None
                self._index = 0
            path = self._files[self._index]
            self._index += 1
            if self.rate_hz > 0:
                delay = self._next_s - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                self._next_s = max(self._next_s + 1.0 / self.rate_hz, time.monotonic())
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            stamp = self._clock_ns()
            try:
                rgb = _to_rgb(image, str(path))
            except FrameSourceError as exc:
                self.unreadable += 1
                failed_in_a_row += 1
                self.last_error = str(exc)
                log.error("%s (unreadable image, skipped)", exc)
                continue
            self._seq += 1
            return Frame(rgb, stamp, self._seq)

    def close(self) -> None:
        self._files = []


class RealSenseGrabber:
    """The colour stream of an Intel RealSense camera (the paper's D455) through
    ``pyrealsense2`` (``pip install pyrealsense2``). Stamps: the frame's own timestamp in the
    host-synchronised ("global") time domain, in nanoseconds. ``depth``: also stream depth,
    aligned to the colour image by the SDK (``rs.align``), into :attr:`Frame.depth_m` in metres
    (the device's depth scale applied; 0 = no depth)."""

    def __init__(self, serial: str | None = None, *, width: int = 848, height: int = 480,
                 fps: int = 30, timeout_ms: int = 2000, depth: bool = False) -> None:
        self.serial = serial
        self.label = f"realsense:{serial or 'first'}"
        self.width, self.height, self.fps = width, height, fps
        self.timeout_ms = timeout_ms
        self.depth = depth
        self._pipe: Any = None
        self._align: Any = None
        self._depth_scale_m = 0.001
        self._seq = 0

    def open(self) -> None:
        try:
            import pyrealsense2 as rs  # type: ignore[import-not-found]
        except ImportError:
            raise FrameSourceError("RealSense: pyrealsense2 is not installed "
                                   "(pip install pyrealsense2)") from None
        self.close()
        cfg = rs.config()
        if self.serial:
            cfg.enable_device(self.serial)
        cfg.enable_stream(rs.stream.color, self.width, self.height, rs.format.rgb8, self.fps)
        if self.depth:
            cfg.enable_stream(rs.stream.depth, self.width, self.height, rs.format.z16, self.fps)
        pipe = rs.pipeline()
        try:
            profile = pipe.start(cfg)
        except RuntimeError as exc:
            what = "colour and depth streams" if self.depth else "colour stream"
            raise FrameSourceError(f"{self.label}: cannot start the {what}: {exc}") from None
        if self.depth:
            self._depth_scale_m = float(profile.get_device().first_depth_sensor()
                                        .get_depth_scale())
            self._align = rs.align(rs.stream.color)
        self._pipe = pipe

    def read(self) -> Frame | None:
        if self._pipe is None:
            raise FrameSourceError(f"{self.label}: not open")
        try:
            frames = self._pipe.wait_for_frames(self.timeout_ms)
        except RuntimeError as exc:
            raise FrameSourceError(f"{self.label}: no frame: {exc}") from None
        depth_m = None
        if self._align is not None:
            try:
                frames = self._align.process(frames)
            except RuntimeError as exc:
                raise FrameSourceError(f"{self.label}: depth alignment failed: {exc}") from None
            depth = frames.get_depth_frame()
            if depth:
                raw = np.asanyarray(depth.get_data())
                depth_m = raw.astype(np.float32) * np.float32(self._depth_scale_m)
        color = frames.get_color_frame()
        if not color:
            raise FrameSourceError(f"{self.label}: frame set without colour")
        self._seq += 1
        image = np.asanyarray(color.get_data()).copy()
        return Frame(image, int(color.get_timestamp() * 1e6), self._seq, depth_m)

    def close(self) -> None:
        if self._pipe is not None:
            with contextlib.suppress(RuntimeError):
                self._pipe.stop()
            self._pipe = None
        self._align = None


@dataclasses.dataclass
class ReaderStatus:
    """What :class:`LatestFrameReader` reports. ``state``: ``opening``, ``ok``, ``retrying``
    (the source failed; next try after ``retry_in_s``), ``ended`` (a finite source is done) or
    ``stopped``; ``error``: the last failure; counters of frames grabbed, frames replaced
    before the worker took them (``skipped``), failures and re-opens."""

    state: str = "opening"
    error: str = ""
    grabbed: int = 0
    skipped: int = 0
    failures: int = 0
    reopens: int = 0
    retry_in_s: float = 0.0


class LatestFrameReader:
    """Runs ``grabber`` in a daemon thread; :meth:`take` returns the newest frame not yet
    taken. Failures are retried after ``backoff_s`` doubling up to ``max_backoff_s`` (reset
    by the first good frame after a re-open). ``lossless``: wait until each frame is taken
    before reading the next (offline folders and files: every frame processed, none skipped)."""

    def __init__(self, grabber: Grabber, *, backoff_s: float = 0.5,
                 max_backoff_s: float = 10.0, lossless: bool = False) -> None:
        self.grabber = grabber
        self.lossless = lossless
        self._taken = threading.Event()
        self._taken.set()
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self._lock = threading.Lock()
        self._frame: Frame | None = None
        self._status = ReaderStatus()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"grab {grabber.label}",
                                        daemon=True)

    def start(self) -> LatestFrameReader:
        self._thread.start()
        return self

    def take(self) -> Frame | None:
        with self._lock:
            frame, self._frame = self._frame, None
        if frame is not None:
            self._taken.set()
        return frame

    def status(self) -> ReaderStatus:
        with self._lock:
            return dataclasses.replace(self._status)

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        self._taken.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
        if not self._thread.is_alive():
            with self._lock:
                self._status.state = "stopped"
        else:
            log.warning("%s: the grab thread did not stop within %.1f s (a blocking driver "
                        "call); it is a daemon and ends with the process", self.grabber.label,
                        timeout_s)

    def _set(self, **fields: Any) -> None:
        with self._lock:
            for k, v in fields.items():
                setattr(self._status, k, v)

    def _run(self) -> None:
        delay = self.backoff_s
        opened_once = False
        while not self._stop.is_set():
            try:
                self.grabber.open()
                if opened_once:
                    with self._lock:
                        self._status.reopens += 1
                opened_once = True
                self._set(state="ok", error="", retry_in_s=0.0)
                first = True
                while not self._stop.is_set():
                    if self.lossless:
                        while not self._taken.wait(0.1):
                            if self._stop.is_set():
                                return
                    frame = self.grabber.read()
                    if frame is not None and first:
                        delay = self.backoff_s  # a stream that delivers again: reset back-off
                        first = False
                    if frame is None:
                        self._set(state="ended")
                        log.info("%s: end of the source", self.grabber.label)
                        self.grabber.close()
                        return
                    with self._lock:
                        if self._frame is not None:
                            self._status.skipped += 1
                        self._frame = frame
                        self._status.grabbed += 1
                        self._taken.clear()
            except Exception as exc:  # a driver can raise anything: report, back off, retry
                msg = str(exc) if isinstance(exc, FrameSourceError) else \
                    f"{self.grabber.label}: {type(exc).__name__}: {exc}"
                with self._lock:
                    self._status.failures += 1
                    self._status.state = "retrying"
                    self._status.error = msg
                    self._status.retry_in_s = delay
                log.error("%s (retrying in %.1f s)", msg, delay)
                with contextlib.suppress(Exception):
                    self.grabber.close()
                if self._stop.wait(delay):
                    break
                delay = min(delay * 2.0, self.max_backoff_s)
        with contextlib.suppress(Exception):
            self.grabber.close()
