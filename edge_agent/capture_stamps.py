"""Capture stamps: when a frame was exposed, in the sensor clock (the host's ``CLOCK_REALTIME``,
as everywhere in smartedge).

A V4L2 device's frames carry the driver's buffer timestamp (``CLOCK_MONOTONIC``, taken when the
frame was captured, not when it was read), converted with the monotonic → realtime offset
(:class:`MonotonicToRealtime`, measured at open and every second; :func:`v4l2_stamp_clock`
tells the two clocks apart); a RealSense frame its metadata stamp (global or system time as
is, the camera's hardware clock through :class:`DeviceClockMapper`;
:func:`realsense_stamp_ns`). :class:`StampFilter` refuses a driver stamp that goes backwards or
jumps (counted; the frame gets the grab time) and says which source the last frame used
(``stamp_source`` = ``driver`` or ``grab``). The grabbers that use them are
:mod:`edge_agent.frames`'.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable
from typing import Final

log = logging.getLogger(__name__)

#: where a frame's stamp came from (``stamp_source`` in the status): the driver or the grab
STAMP_DRIVER: Final = "driver"
STAMP_GRAB: Final = "grab"


def monotonic_realtime_offset_ns(monotonic_ns: Callable[[], int] = time.monotonic_ns,
                                 realtime_ns: Callable[[], int] = time.time_ns,
                                 samples: int = 5) -> int:
    """``CLOCK_REALTIME - CLOCK_MONOTONIC`` in nanoseconds: of ``samples`` reads of the
    realtime clock, each between two monotonic reads, the one with the narrowest bracket (the
    least disturbed by a context switch), against the bracket's middle."""
    best: tuple[int, int] | None = None
    for _ in range(max(1, samples)):
        m0 = monotonic_ns()
        r = realtime_ns()
        m1 = monotonic_ns()
        if best is None or m1 - m0 < best[0]:
            best = (m1 - m0, r - (m0 + m1) // 2)
    assert best is not None
    return best[1]


def ms_to_ns(stamp_ms: float) -> int:
    """A driver's stamp in milliseconds (a double: OpenCV's ``CAP_PROP_POS_MSEC``, RealSense's
    ``get_timestamp()``) → integer nanoseconds, rounded to the microsecond: the drivers count
    microseconds, and a double of milliseconds since the epoch holds no finer digit."""
    return round(float(stamp_ms) * 1e3) * 1_000


class MonotonicToRealtime:
    """``CLOCK_MONOTONIC`` stamps (V4L2 buffers) → ``CLOCK_REALTIME`` (smartedge's sensor
    clock). The offset is measured when created (at the grabber's open) and again when it is
    older than ``refresh_s``: NTP slews or steps the realtime clock, the monotonic clock never
    jumps, so a stamp converted with a fresh offset lands where the wall clock is now."""

    def __init__(self, refresh_s: float = 1.0, *,
                 monotonic_ns: Callable[[], int] = time.monotonic_ns,
                 realtime_ns: Callable[[], int] = time.time_ns) -> None:
        self.refresh_ns = int(refresh_s * 1e9)
        self._monotonic_ns = monotonic_ns
        self._realtime_ns = realtime_ns
        self._measured_at = 0
        self.offset_ns = 0
        self.refresh()

    def refresh(self) -> int:
        self.offset_ns = monotonic_realtime_offset_ns(self._monotonic_ns, self._realtime_ns)
        self._measured_at = self._monotonic_ns()
        return self.offset_ns

    def __call__(self, stamp_monotonic_ns: int) -> int:
        if self._monotonic_ns() - self._measured_at >= self.refresh_ns:
            self.refresh()
        return int(stamp_monotonic_ns) + self.offset_ns


class DeviceClockMapper:
    """A device's free-running clock (a RealSense's hardware clock) → the host's realtime
    clock: ``host = device + offset``, the offset being the smallest ``arrival - device`` of the
    last ``window`` frames (the transfer delay is never negative, so the smallest difference is
    the closest to the true offset; the window lets it follow the drift of the two clocks).
    :meth:`reset` forgets it (the device clock wrapped or the device restarted)."""

    def __init__(self, window: int = 300) -> None:
        self._offsets: deque[int] = deque(maxlen=max(1, window))

    def __call__(self, device_ns: int, arrival_ns: int) -> int:
        self._offsets.append(int(arrival_ns) - int(device_ns))
        return int(device_ns) + min(self._offsets)

    def reset(self) -> None:
        self._offsets.clear()


class StampFilter:
    """Per frame: the driver's stamp, converted to the sensor clock, where it is plausible,
    else the time of the grab.

    Refused (counted, logged the first time and every 100th, the frame gets the grab time): a
    driver stamp that is not after the previous one (``backwards``: the driver reset its clock
    or repeated a buffer) and one that ``jumps``: later than the grab (by more than
    ``future_tolerance_s``: a stamp from the future is a wrong clock) or older than the grab
    by more than ``max_age_s`` (a frame cannot wait that long in the driver's queue; a stamp
    that far off is in another clock). :attr:`stamp_source` is what the last frame used."""

    def __init__(self, label: str, *, max_age_s: float = 1.0,
                 future_tolerance_s: float = 0.005) -> None:
        self.label = label
        self.max_age_ns = int(max_age_s * 1e9)
        self.future_tolerance_ns = int(future_tolerance_s * 1e9)
        self.stamp_source = STAMP_GRAB
        self.backwards = 0
        self.jumps = 0
        self._last_raw: int | None = None

    @property
    def refused(self) -> int:
        return self.backwards + self.jumps

    def reset(self) -> None:
        """Forget the previous stamp (a re-opened device starts a new sequence)."""
        self._last_raw = None

    def choose(self, driver_ns: int | None, grab_ns: int, raw_ns: int | None = None) -> int:
        """The frame's stamp: ``driver_ns`` (the driver's stamp in the sensor clock; ``None``:
        the driver gave none) or ``grab_ns``. ``raw_ns``: the stamp in the driver's own clock,
        for the backwards test (default ``driver_ns``)."""
        if driver_ns is None:
            self.stamp_source = STAMP_GRAB
            return grab_ns
        raw = driver_ns if raw_ns is None else raw_ns
        why = ""
        if self._last_raw is not None and raw <= self._last_raw:
            self.backwards += 1
            why = (f"went backwards by {(self._last_raw - raw) * 1e-6:.3f} ms"
                   if raw < self._last_raw else "repeated the previous stamp")
        elif driver_ns > grab_ns + self.future_tolerance_ns:
            self.jumps += 1
            why = f"is {(driver_ns - grab_ns) * 1e-6:.1f} ms after the grab"
        elif driver_ns < grab_ns - self.max_age_ns:
            self.jumps += 1
            why = f"is {(grab_ns - driver_ns) * 1e-9:.3f} s before the grab"
        self._last_raw = raw
        if why:
            if self.refused == 1 or self.refused % 100 == 0:
                log.warning("%s: the driver's frame stamp %s; this frame is stamped at the grab "
                            "(%d refused so far: %d backwards, %d jumps)", self.label, why,
                            self.refused, self.backwards, self.jumps)
            self.stamp_source = STAMP_GRAB
            return grab_ns
        self.stamp_source = STAMP_DRIVER
        return driver_ns


def v4l2_stamp_clock(stamp_ns: int, monotonic_now_ns: int, realtime_now_ns: int,
                     within_s: float = 10.0) -> str | None:
    """Which clock a V4L2 buffer timestamp is in: ``monotonic`` (the kernel's default for
    every driver since Linux 3.10, ``V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC``), ``realtime`` (old
    drivers, uvcvideo's ``clock=realtime``), or ``None`` when it is within ``within_s`` of
    neither clock now."""
    window = within_s * 1e9
    if abs(monotonic_now_ns - stamp_ns) <= window:
        return "monotonic"
    if abs(realtime_now_ns - stamp_ns) <= window:
        return "realtime"
    return None


def realsense_stamp_ns(stamp_ms: float, domain: str, arrival_ns: int,
                       hardware_clock: DeviceClockMapper) -> int | None:
    """A RealSense frame's metadata stamp in the sensor clock (``CLOCK_REALTIME``, ns), or
    ``None`` when it cannot be used. ``domain`` (``rs.timestamp_domain`` name):
    ``global_time`` (the camera's clock mapped to the host's by the SDK) and ``system_time``
    (the host's clock when the frame reached the SDK) are host milliseconds since the epoch,
    taken as they are; ``hardware_clock`` (the camera's own counter, when the SDK cannot map
    it) goes through ``hardware_clock`` (:class:`DeviceClockMapper`) with the ``arrival_ns``."""
    if not math.isfinite(stamp_ms) or stamp_ms <= 0:  # NaN, inf or none
        return None
    stamp_ns = ms_to_ns(stamp_ms)
    if domain in ("global_time", "system_time"):
        return stamp_ns
    if domain == "hardware_clock":
        return hardware_clock(stamp_ns, arrival_ns)
    return None
