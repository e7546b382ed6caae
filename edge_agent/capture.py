"""Frame capture: the edge agent saves the frames it processes, for a lab's own dataset.

``smartedge edge-agent ... --capture DIR`` writes the processed frames to
``DIR/<camera_id>/<stamp_ns>.png`` (lossless, the default) or ``.jpg`` (``--capture-format
jpg``, quality ``--capture-jpeg-quality``), full resolution, named with the capture stamp the
frame's detections carry, so a frame and its detections (and the fused pose at that stamp) are
found by the same number. At most ``--capture-rate`` frames per second of capture time.

Bounded disk use: the files already in ``DIR/<camera_id>`` count against
``--capture-budget-mb``; when the next frame would pass it the capture stops, says so in the
agent's status (``capture stopped: ...``) and log, and the agent goes on detecting. A full disk
stops it the same way. Each file is written beside its name and renamed into place, so a frame
on disk is always whole.

Encoding and writing happen in a writer thread with a short queue, never in the worker loop; a
frame offered while the queue is full is not captured (``capture_skipped_busy``). Counters:
``frames_captured``, ``capture_bytes``, ``capture_skipped_busy``, ``capture_errors``.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import queue
import threading
from pathlib import Path
from typing import Any, Final

import numpy as np

log = logging.getLogger(__name__)

FORMATS: Final = ("png", "jpg")
#: frames waiting for the writer at most (more are not captured, counted)
QUEUE_FRAMES: Final = 4


class FrameCapture:
    """Writes frames of ``camera_id`` under ``folder`` (module docstring). ``stats``: the
    service's :class:`~core.runtime.Stats` (or anything with ``count(name, n)``)."""

    def __init__(self, folder: str | Path, camera_id: str, *, rate_hz: float = 1.0,
                 budget_mb: float = 1000.0, fmt: str = "png", jpeg_quality: int = 95,
                 stats: Any = None) -> None:
        if fmt not in FORMATS:
            raise ValueError(f"--capture-format {fmt!r}: one of {FORMATS}")
        if not rate_hz > 0:
            raise ValueError(f"--capture-rate {rate_hz}: must be > 0")
        if not budget_mb > 0:
            raise ValueError(f"--capture-budget-mb {budget_mb}: must be > 0")
        if not 1 <= jpeg_quality <= 100:
            raise ValueError(f"--capture-jpeg-quality {jpeg_quality}: 1 to 100")
        self.folder = Path(folder) / camera_id
        self.folder.mkdir(parents=True, exist_ok=True)
        self.camera_id = camera_id
        self.fmt = fmt
        self.jpeg_quality = int(jpeg_quality)
        self.period_ns = round(1e9 / rate_hz)
        self.budget_bytes = int(budget_mb * 1024 * 1024)
        #: bytes under this camera's folder, what was there before included
        self.used_bytes = sum(p.stat().st_size for p in self.folder.iterdir() if p.is_file())
        self.stats = stats
        self.captured = 0
        self.stopped = ""  # why the capture stopped ("": capturing)
        self._next_stamp_ns: int | None = None
        self._last_size = 0
        self._queue: queue.Queue[tuple[int, np.ndarray | bytes, str] | None] = queue.Queue(
            QUEUE_FRAMES)
        self._thread = threading.Thread(target=self._run, name=f"capture {camera_id}",
                                        daemon=True)
        self._thread.start()
        if self.used_bytes >= self.budget_bytes:
            self._stop(f"budget of {budget_mb:g} MB already used by the files in {self.folder}")
        log.info("%s: capturing %s frames at <= %g Hz to %s (budget %g MB, %.1f MB there)",
                 camera_id, fmt, rate_hz, self.folder, budget_mb, self.used_bytes / 2**20)

    def _count(self, name: str, n: int = 1) -> None:
        if self.stats is not None:
            self.stats.count(name, n)

    def _stop(self, why: str) -> None:
        if not self.stopped:
            self.stopped = why
            log.warning("%s: capture stopped: %s (%d frames captured); detecting goes on",
                        self.camera_id, why, self.captured)

    def offer(self, image_rgb: np.ndarray, stamp_ns: int, *, wait: bool = False) -> bool:
        """Capture this frame if one is due by its stamp and the capture runs; True if queued.
        ``wait``: wait for room in the writer's queue (offline extraction) instead of skipping."""
        return self._offer(stamp_ns, image_rgb, self.fmt, wait)

    def offer_encoded(self, data: bytes, ext: str, stamp_ns: int, *, wait: bool = False
                      ) -> bool:
        """As :meth:`offer` for an image already encoded (a ROS ``CompressedImage``'s JPEG, kept
        byte for byte as ``<stamp_ns>.<ext>``)."""
        return self._offer(stamp_ns, bytes(data), ext, wait)

    def _offer(self, stamp_ns: int, item: np.ndarray | bytes, ext: str, wait: bool) -> bool:
        if self.stopped:
            return False
        if self._next_stamp_ns is not None and stamp_ns < self._next_stamp_ns:
            return False
        # the next frame would likely pass the budget: stop before writing half of it
        if self.used_bytes + self._last_size > self.budget_bytes:
            self._stop(f"budget of {self.budget_bytes / 2**20:g} MB reached")
            return False
        try:
            self._queue.put((int(stamp_ns), item, ext), block=wait)
        except queue.Full:
            self._count("capture_skipped_busy")
            return False
        self._next_stamp_ns = int(stamp_ns) + self.period_ns
        return True

    def status(self) -> str:
        """One phrase for the agent's status detail."""
        if self.stopped:
            return f"capture stopped: {self.stopped}, {self.captured} frames"
        return f"capture {self.captured} frames, {self.used_bytes / 2**20:.1f} MB"

    def _encode(self, image_rgb: np.ndarray) -> bytes:
        import cv2

        bgr = cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2BGR)
        params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality] if self.fmt == "jpg" else []
        ok, data = cv2.imencode(f".{self.fmt}", bgr, params)
        if not ok:
            raise ValueError(f"OpenCV could not encode a {bgr.shape} frame as {self.fmt}")
        return data.tobytes()

    def _write(self, stamp_ns: int, item: np.ndarray | bytes, ext: str) -> None:
        data = item if isinstance(item, bytes) else self._encode(item)
        if self.used_bytes + len(data) > self.budget_bytes:
            self._stop(f"budget of {self.budget_bytes / 2**20:g} MB reached")
            return
        path = self.folder / f"{stamp_ns}.{ext}"
        tmp = path.with_name(f".{path.name}.tmp")
        try:
            with open(tmp, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        except OSError:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise
        self.used_bytes += len(data)
        self._last_size = len(data)
        self.captured += 1
        self._count("frames_captured")
        self._count("capture_bytes", len(data))

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self.stopped:
                continue
            try:
                self._write(*item)
            except OSError as exc:
                self._count("capture_errors")
                if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
                    self._stop(f"cannot write to {self.folder}: {exc.strerror}")
                else:
                    log.error("%s: frame %d not captured: %s", self.camera_id, item[0], exc)
            except (ValueError, TypeError) as exc:  # a frame OpenCV cannot encode
                self._count("capture_errors")
                log.error("%s: frame %d not captured: %s", self.camera_id, item[0], exc)

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is queued, then stop the writer."""
        self._queue.put(None)
        self._thread.join(timeout_s)
