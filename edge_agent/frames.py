"""Where an edge agent's images come from: grabbers behind one interface, and a reader thread
that always hands over the newest frame.

A :class:`Grabber` opens a device, stream, file or folder and returns :class:`Frame` s (RGB
uint8 with the capture stamp in the sensor clock: the camera's timestamp where the source has
one, else the time of the grab). :class:`LatestFrameReader` runs one grabber in a background
thread (blocking I/O stays out of the service's worker loop), keeps only the newest frame and
counts the ones the worker never took; a grabber that fails to open or stops delivering is
reported in :meth:`LatestFrameReader.status` and retried with exponential back-off, and never
stops the service.

Grabbers: :class:`OpenCVGrabber` (V4L2 device index or path, RTSP/HTTP URL, video file,
GStreamer pipeline or ``csi://N`` for a Jetson's CSI camera), :class:`ImageFolderGrabber` (a
folder of images, paced at a rate), :class:`RealSenseGrabber` (Intel RealSense colour stream,
with depth aligned to it on request, through ``pyrealsense2``, optional). The simulation's
renderer is registered as a source from the top floor.

Capture stamps (the sensor clock is the host's ``CLOCK_REALTIME``, as everywhere in
smartedge) are the driver's where the device has them (:mod:`edge_agent.capture_stamps`);
video files, streams, GStreamer pipelines and image folders are stamped at the grab.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import re
import threading
import time
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path
from typing import Any, Final, Protocol

import numpy as np

from edge_agent.capture_stamps import (
    DeviceClockMapper,
    MonotonicToRealtime,
    StampFilter,
    ms_to_ns,
    realsense_stamp_ns,
    v4l2_stamp_clock,
)
from protocol.errors import SmartedgeError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES: Final = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")


class FrameSourceError(SmartedgeError):
    """A grabber cannot open or read its source (the message names the device, URL or file)."""


# --------------------------------------------------------------------------------------------
# GStreamer pipelines (a Jetson's CSI cameras)
# --------------------------------------------------------------------------------------------

_CSI_URI: Final = re.compile(r"^csi://(\d+)(?:\?flip=([0-7]))?$")


def is_gstreamer_uri(uri: str) -> bool:
    """Whether ``--device`` names a GStreamer pipeline (``a ! b ! appsink``) or a Jetson CSI
    camera (``csi://N``)."""
    return uri.startswith("csi://") or " ! " in uri or uri.rstrip().endswith("appsink")


def csi_pipeline(sensor_id: int, width: int, height: int, fps: float = 30.0,
                 flip: int = 0) -> str:
    """The GStreamer pipeline of a Jetson CSI camera (``nvarguscamerasrc``, the Argus camera
    stack of JetPack): ``width`` x ``height`` at ``fps`` as NV12 in NVMM memory, converted by
    the VIC (``nvvidconv``, ``flip`` its flip-method 0-7) to BGRx, then to BGR for OpenCV; the
    appsink keeps only the newest frame (``drop=true max-buffers=1``)."""
    rate = Fraction(fps).limit_denominator(1001)
    return (f"nvarguscamerasrc sensor-id={int(sensor_id)} ! "
            f"video/x-raw(memory:NVMM), width=(int){int(width)}, height=(int){int(height)}, "
            f"framerate=(fraction){rate.numerator}/{rate.denominator}, format=(string)NV12 ! "
            f"nvvidconv flip-method={int(flip)} ! video/x-raw, format=(string)BGRx ! "
            "videoconvert ! video/x-raw, format=(string)BGR ! "
            "appsink drop=true max-buffers=1 sync=false")


def expand_device_uri(uri: str, width: int | None, height: int | None,
                      fps: float | None) -> str:
    """``csi://N`` (optionally ``csi://N?flip=M``) → :func:`csi_pipeline` at the camera's
    resolution (``fps`` default 30); anything else unchanged. Raises
    :class:`FrameSourceError` for a malformed ``csi://`` or one without a resolution."""
    if not uri.startswith("csi://"):
        return uri
    m = _CSI_URI.match(uri)
    if m is None:
        raise FrameSourceError(f"{uri}: expected csi://N or csi://N?flip=M (N the sensor id, "
                               "M the nvvidconv flip-method 0-7)")
    if not width or not height:
        raise FrameSourceError(f"{uri}: the CSI camera needs the calibration's width and height")
    return csi_pipeline(int(m.group(1)), width, height, fps or 30.0, int(m.group(2) or 0))


def gstreamer_in_opencv(build_information: str | None = None) -> bool:
    """Whether OpenCV's video I/O was built with GStreamer (``cv2.getBuildInformation()``,
    line ``GStreamer: YES ...``). JetPack's OpenCV has it; opencv-python-headless from PyPI
    does not."""
    if build_information is None:
        import cv2

        build_information = cv2.getBuildInformation()
    m = re.search(r"^\s*GStreamer:\s*(\S+)", build_information, re.MULTILINE)
    return m is not None and m.group(1).upper() not in ("NO", "OFF")


def check_gstreamer(uri: str, build_information: str | None = None) -> None:
    """Raise :class:`FrameSourceError` naming the fix when ``uri`` is a GStreamer pipeline or
    ``csi://`` camera and this OpenCV has no GStreamer."""
    if not is_gstreamer_uri(uri) or gstreamer_in_opencv(build_information):
        return
    import cv2

    raise FrameSourceError(
        f"{uri}: a GStreamer pipeline, but this OpenCV ({cv2.__version__}, {cv2.__file__}) is "
        "built without GStreamer (cv2.getBuildInformation(): 'GStreamer: NO'; the "
        "opencv-python-headless wheel from PyPI never has it). On a Jetson use JetPack's "
        "OpenCV, which has it: a venv made with --system-site-packages and "
        "opencv-python-headless uninstalled from it (deploy/install-edge.sh --jetson yes "
        "does both); elsewhere install an OpenCV built with GStreamer (Debian/Ubuntu: "
        "python3-opencv, gstreamer1.0-plugins-good)")


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
    (``/dev/video0``), a stream URL (``rtsp://``, ``http://``), a video file, a GStreamer
    pipeline ending in ``appsink`` or ``csi://N`` (a Jetson CSI camera, :func:`csi_pipeline` at
    ``width`` x ``height``; both need an OpenCV built with GStreamer, else
    :class:`FrameSourceError` says so at open). ``width`` / ``height`` / ``fps`` are requested
    from devices (None: the device's default). Video files play at their own frame rate
    (``realtime``) or as fast as they are read, once or (``loop``) over and over.

    Stamps: a V4L2 device's frames get the driver's buffer timestamp (OpenCV's
    ``CAP_PROP_POS_MSEC`` on the V4L2 backend is ``v4l2_buffer.timestamp``, the kernel's
    ``CLOCK_MONOTONIC`` at capture) converted to ``CLOCK_REALTIME`` (:class:`MonotonicToRealtime`),
    filtered by :class:`StampFilter`; a driver whose stamps are in neither clock is stamped at
    the grab for good (logged once). Everything else (files, streams, GStreamer) is stamped at
    the grab (``clock_ns``, ``CLOCK_REALTIME``): their ``POS_MSEC`` is a position in the
    stream, not a clock. :attr:`stamp_source` says which the last frame got."""

    def __init__(self, uri: str, *, width: int | None = None, height: int | None = None,
                 fps: float | None = None, realtime: bool = True, loop: bool = False,
                 clock_ns: Callable[[], int] = time.time_ns,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self.uri = str(uri)
        self.loop = loop
        self.label = f"opencv:{self.uri}"
        self.width, self.height, self.fps = width, height, fps
        self.realtime = realtime
        self._clock_ns = clock_ns
        self._monotonic_ns = monotonic_ns
        self._cap: Any = None
        self._seq = 0
        self._is_file = False
        self._period_s = 0.0
        self._next_s = 0.0
        self.stamps = StampFilter(self.label)
        #: the clock of the driver's stamps: ``monotonic``, ``realtime``, ``None`` (not known
        #: yet, or the grab time is used: not a V4L2 device, or a clock of its own)
        self.driver_clock: str | None = None
        self._driver_stamps = False
        self._to_realtime: MonotonicToRealtime | None = None

    @property
    def stamp_source(self) -> str:
        """``driver`` or ``grab``: where the last frame's stamp came from."""
        return self.stamps.stamp_source

    @property
    def stamps_refused(self) -> int:
        return self.stamps.refused

    def open(self) -> None:
        import cv2

        self.close()
        check_gstreamer(self.uri)
        gstreamer = is_gstreamer_uri(self.uri)
        if gstreamer:
            source: int | str = expand_device_uri(self.uri, self.width, self.height, self.fps)
        else:
            source = int(self.uri) if self.uri.isdigit() else self.uri
        self._is_file = not gstreamer and isinstance(source, str) and "://" not in source and \
            not source.startswith("/dev/")
        if self._is_file and not Path(source).is_file():  # type: ignore[arg-type]
            raise FrameSourceError(f"{self.uri}: video file not found")
        cap = cv2.VideoCapture(source, cv2.CAP_GSTREAMER) if gstreamer else \
            cv2.VideoCapture(source)
        if not cap.isOpened():
            cap.release()
            what = ("GStreamer pipeline (gst-launch-1.0 with the same pipeline, fakesink in "
                    "place of appsink, shows why)" if gstreamer else "device, stream or file")
            raise FrameSourceError(f"{self.uri}: OpenCV cannot open this {what}")
        if not self._is_file and not gstreamer:
            if self.width:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
            if self.height:
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
            if self.fps:
                cap.set(cv2.CAP_PROP_FPS, self.fps)
        fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
        self._period_s = 1.0 / fps if self._is_file and self.realtime and 0 < fps < 1000 else 0.0
        self._next_s = time.monotonic()
        backend = _backend_name(cap)
        self._driver_stamps = backend == "V4L2" and not self._is_file and not gstreamer
        self.driver_clock = None
        self.stamps.reset()
        self._to_realtime = MonotonicToRealtime(monotonic_ns=self._monotonic_ns,
                                                realtime_ns=self._clock_ns) \
            if self._driver_stamps else None
        self._cap = cap
        log.info("%s: opened (%s, backend %s; stamps: %s)", self.uri,
                 "file" if self._is_file else "live", backend or "?",
                 "the driver's where plausible" if self._driver_stamps else "grab time")

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
        if self._driver_stamps:
            stamp = self._driver_stamp(stamp)
        self._seq += 1
        return Frame(_to_rgb(image, self.uri), stamp, self._seq)

    def _driver_stamp(self, grab_ns: int) -> int:
        """The frame's stamp from the V4L2 buffer timestamp, or ``grab_ns``."""
        import cv2

        msec = self._cap.get(cv2.CAP_PROP_POS_MSEC)
        if not math.isfinite(msec) or msec <= 0:  # 0: none yet / the driver gives none
            return self.stamps.choose(None, grab_ns)
        raw_ns = ms_to_ns(msec)
        if self.driver_clock is None:
            self.driver_clock = v4l2_stamp_clock(raw_ns, self._monotonic_ns(), grab_ns)
            if self.driver_clock is None:
                self._driver_stamps = False
                log.warning("%s: the driver's frame stamps (%.3f s) are neither in "
                            "CLOCK_MONOTONIC nor in CLOCK_REALTIME; frames are stamped at the "
                            "grab", self.uri, raw_ns * 1e-9)
                return self.stamps.choose(None, grab_ns)
            log.info("%s: frame stamps from the driver (V4L2 buffer timestamps, %s clock)",
                     self.uri, self.driver_clock)
        if self.driver_clock == "monotonic":
            assert self._to_realtime is not None
            return self.stamps.choose(self._to_realtime(raw_ns), grab_ns, raw_ns)
        return self.stamps.choose(raw_ns, grab_ns)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def _backend_name(cap: Any) -> str:
    """The capture's backend (``V4L2``, ``FFMPEG``, ``GSTREAMER``, ...; ``""`` if unknown)."""
    try:
        return str(cap.getBackendName())
    except Exception:  # cv2.error when the backend has no name
        return ""


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
    ``pyrealsense2`` (``pip install pyrealsense2``). Stamps: the colour frame's metadata
    (``get_timestamp()``, milliseconds, in the domain ``get_frame_timestamp_domain()`` names,
    :func:`realsense_stamp_ns`), filtered by :class:`StampFilter`; :attr:`stamp_source` says
    whether the last frame got it or the grab time. ``depth``: also stream depth,
    aligned to the colour image by the SDK (``rs.align``), into :attr:`Frame.depth_m` in metres
    (the device's depth scale applied; 0 = no depth)."""

    def __init__(self, serial: str | None = None, *, width: int = 848, height: int = 480,
                 fps: int = 30, timeout_ms: int = 2000, depth: bool = False,
                 clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.serial = serial
        self.label = f"realsense:{serial or 'first'}"
        self.width, self.height, self.fps = width, height, fps
        self.timeout_ms = timeout_ms
        self.depth = depth
        self._clock_ns = clock_ns
        self._pipe: Any = None
        self._align: Any = None
        self._depth_scale_m = 0.001
        self._seq = 0
        self.stamps = StampFilter(self.label)
        self._hardware_clock = DeviceClockMapper()
        self._last_device_ns: int | None = None

    @property
    def stamp_source(self) -> str:
        return self.stamps.stamp_source

    @property
    def stamps_refused(self) -> int:
        return self.stamps.refused

    def stamp(self, stamp_ms: float, domain: Any, grab_ns: int) -> int:
        """The stamp of a colour frame with metadata ``stamp_ms`` in ``domain`` (an
        ``rs.timestamp_domain`` or its name) that arrived at ``grab_ns``."""
        name = str(domain).rsplit(".", 1)[-1]
        device_ns = ms_to_ns(stamp_ms) if math.isfinite(stamp_ms) else None
        if name == "hardware_clock" and device_ns is not None:
            if self._last_device_ns is not None and device_ns < self._last_device_ns:
                self._hardware_clock.reset()  # the camera's counter wrapped or restarted
            self._last_device_ns = device_ns
        driver_ns = realsense_stamp_ns(stamp_ms, name, grab_ns, self._hardware_clock)
        return self.stamps.choose(driver_ns, grab_ns, device_ns)

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
        self.stamps.reset()
        self._hardware_clock.reset()
        self._last_device_ns = None

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
        grab_ns = self._clock_ns()
        self._seq += 1
        image = np.asanyarray(color.get_data()).copy()
        stamp = self.stamp(color.get_timestamp(), color.get_frame_timestamp_domain(), grab_ns)
        return Frame(image, stamp, self._seq, depth_m)

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
