"""Frame-set synchronizer: group per-camera :class:`protocol.RobotDetections` into frame-sets.

Per robot, detections whose stamps (corrected by each camera's ``clock_offset_ns``) lie within
``sync_window_ms`` of a window's anchor stamp (the first stamp that opened it) form one
frame-set. A frame-set is whatever cameras saw the robot: no camera is required. A window is
emitted when

- every *live* camera (one that sent anything within ``camera_timeout_s``) has reported for it,
  either with a message in the window (a detection or "robot not seen") or with a later stamp
  (it moved on, so it will not contribute), or
- it has waited ``sync_max_wait_ms`` since its first message arrived (``now_ns`` clock).

Windows are emitted in stamp order; a message for a window that is already emitted (or older) is
``late`` and dropped, so output stamps never go backwards. Other counters: ``duplicate`` (same
camera, same stamp), ``future`` (stamp more than ``max_future_ms`` ahead of ``now_ns``),
``unknown_camera``, ``bad_keypoints`` (keypoint count differs from the robot model),
``image_size`` (the message's image size is not the camera's calibrated size nor an exact
scale of it; an exact scale, e.g. a 424x240 stream of an 848x480 calibration, is converted to
calibrated pixels, see :func:`~backend_service.frame_set.image_scale`),
``not_seen`` (message without this robot), ``replaced`` (a camera sent two frames within one
window; the one closer to the anchor is kept), ``overflow`` (too many open windows: the oldest is
emitted early), ``empty`` (a window closed with no detection), ``emitted``. Memory is bounded by
``max_open_windows`` per robot and the site's camera count.

Time: ``now_ns`` is supplied by the caller (the backend's clock on the common time base); the
synchronizer never reads the wall clock.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from typing import Final

from backend_service.frame_set import (
    CameraObservation,
    FrameSet,
    image_scale,
    observation_for_robot,
)
from protocol.messages import RobotDetections
from protocol.site import Site

log = logging.getLogger(__name__)

COUNTER_NAMES: Final = (
    "received", "emitted", "late", "duplicate", "future", "unknown_camera", "bad_keypoints",
    "image_size", "not_seen", "replaced", "overflow", "empty",
)


@dataclasses.dataclass
class _Window:
    anchor_ns: int
    opened_at_ns: int
    observations: dict[str, CameraObservation] = dataclasses.field(default_factory=dict)
    reported: set[str] = dataclasses.field(default_factory=set)


class FrameSetSynchronizer:
    """Software synchronization of detections into :class:`FrameSet` s (paper Sec. III-B).

    ``robot_id``: synchronize only this robot; ``None``: every robot of the site (unidentified
    detections, ``robot_id == ""``, are only attributed when the site has one robot).
    Thresholds come from ``site.thresholds``. Not thread-safe: call from one worker loop.
    """

    def __init__(self, site: Site, robot_id: str | None = None, max_open_windows: int = 32,
                 ) -> None:
        th = site.thresholds
        self.site = site
        self.window_ns = int(th.sync_window_ms * 1e6)
        self.max_wait_ns = int(th.sync_max_wait_ms * 1e6)
        self.camera_timeout_ns = int(th.camera_timeout_s * 1e9)
        self.max_future_ns = int(th.max_future_ms * 1e6)
        self.max_open_windows = int(max_open_windows)
        if robot_id is not None:
            self.robot_ids: tuple[str, ...] = (robot_id,)
        else:
            self.robot_ids = tuple(site.robots)
        self._attribute_unnamed = robot_id is not None or len(site.robots) == 1
        self._num_keypoints = {r: site.robot_model(r).num_keypoints
                               for r in self.robot_ids if r in site.robots}
        self.counters: dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)
        self._windows: dict[str, list[_Window]] = {r: [] for r in self.robot_ids}
        self._emitted_anchor: dict[str, int | None] = dict.fromkeys(self.robot_ids)
        self._last_seen_ns: dict[str, int] = {}  # camera -> arrival time (now_ns)
        self._last_stamp: dict[str, collections.deque[int]] = {}  # camera -> recent stamps
        self._size_warned: set[str] = set()

    # -- input -------------------------------------------------------------------------------

    def live_cameras(self, now_ns: int) -> set[str]:
        """Cameras that sent anything within ``camera_timeout_s`` of ``now_ns``."""
        return {c for c, t in self._last_seen_ns.items() if now_ns - t <= self.camera_timeout_ns}

    def push(self, msg: RobotDetections, now_ns: int) -> list[FrameSet]:
        """Add one camera message (arrived at ``now_ns``); returns frame-sets that closed."""
        self.counters["received"] += 1
        if not self._last_seen_ns:
            # Cold start: every site camera is presumed live until it has been silent for
            # camera_timeout_s, so the first frame-sets wait for all of them.
            self._last_seen_ns = dict.fromkeys(self.site.cameras, now_ns)
        cam = self.site.cameras.get(msg.camera_id)
        if cam is None:
            self.counters["unknown_camera"] += 1
            return self.poll(now_ns)
        scale = image_scale(msg.image_width, msg.image_height, cam.width, cam.height)
        if scale is None:
            self.counters["image_size"] += 1
            if msg.camera_id not in self._size_warned:
                self._size_warned.add(msg.camera_id)
                log.warning("camera %s: detections for %dx%d images, calibrated %dx%d (not an "
                            "exact scale): dropped (counter image_size; warned once)",
                            msg.camera_id, msg.image_width, msg.image_height, cam.width,
                            cam.height)
            return self.poll(now_ns)
        stamp = int(msg.stamp_ns) + int(cam.clock_offset_ns)
        if stamp - now_ns > self.max_future_ns:
            self.counters["future"] += 1
            return self.poll(now_ns)
        recent = self._last_stamp.setdefault(msg.camera_id, collections.deque(maxlen=16))
        if stamp in recent:
            self.counters["duplicate"] += 1
            return self.poll(now_ns)
        recent.append(stamp)
        self._last_seen_ns[msg.camera_id] = max(now_ns, self._last_seen_ns.get(msg.camera_id,
                                                                              now_ns))
        for robot_id in self.robot_ids:
            self._add(robot_id, msg, stamp, now_ns, scale)
        return self.poll(now_ns)

    def _add(self, robot_id: str, msg: RobotDetections, stamp: int, now_ns: int,
             scale: float = 1.0) -> None:
        emitted = self._emitted_anchor[robot_id]
        if emitted is not None and stamp <= emitted + self.window_ns:
            self.counters["late"] += 1
            return
        windows = self._windows[robot_id]
        win = None
        best_gap = None
        for w in windows:
            gap = abs(stamp - w.anchor_ns)
            if gap <= self.window_ns and (best_gap is None or gap < best_gap):
                win, best_gap = w, gap
        if win is None:
            win = _Window(stamp, now_ns)
            windows.append(win)
            windows.sort(key=lambda w: w.anchor_ns)
        win.reported.add(msg.camera_id)
        obs = observation_for_robot(msg, robot_id, self._num_keypoints.get(robot_id, -1),
                                    self._attribute_unnamed, stamp, scale)
        if isinstance(obs, str):
            self.counters[obs] += 1
            return
        old = win.observations.get(msg.camera_id)
        if old is not None:
            self.counters["replaced"] += 1
            if abs(old.stamp_ns - win.anchor_ns) <= abs(stamp - win.anchor_ns):
                return
        win.observations[msg.camera_id] = obs

    # -- output ------------------------------------------------------------------------------

    def _moved_on(self, camera_id: str, win: _Window) -> bool:
        recent = self._last_stamp.get(camera_id)
        return bool(recent) and max(recent) > win.anchor_ns + self.window_ns  # type: ignore[type-var]

    def _ready(self, win: _Window, live: set[str], now_ns: int) -> bool:
        if now_ns - win.opened_at_ns >= self.max_wait_ns:
            return True
        return all(c in win.reported or self._moved_on(c, win) for c in live)

    def poll(self, now_ns: int) -> list[FrameSet]:
        """Emit every window that is complete or has waited long enough, oldest first."""
        out: list[FrameSet] = []
        live = self.live_cameras(now_ns)
        for robot_id in self.robot_ids:
            windows = self._windows[robot_id]
            while len(windows) > self.max_open_windows:
                self.counters["overflow"] += 1
                self._emit(robot_id, windows.pop(0), out)
            ready_idx = -1
            for i, win in enumerate(windows):
                if self._ready(win, live, now_ns):
                    ready_idx = i
            # Older windows go out with a newer ready one, so stamps stay monotonic.
            for win in windows[: ready_idx + 1]:
                self._emit(robot_id, win, out)
            del windows[: ready_idx + 1]
        return out

    def _emit(self, robot_id: str, win: _Window, out: list[FrameSet]) -> None:
        prev = self._emitted_anchor[robot_id]
        self._emitted_anchor[robot_id] = win.anchor_ns if prev is None else max(prev,
                                                                                win.anchor_ns)
        if not win.observations:
            self.counters["empty"] += 1
            return
        obs = tuple(win.observations[c] for c in sorted(win.observations))
        self.counters["emitted"] += 1
        out.append(FrameSet.from_observations(robot_id, obs))

    def flush(self) -> list[FrameSet]:
        """Emit every open window now (shutdown, end of a recording)."""
        out: list[FrameSet] = []
        for robot_id in self.robot_ids:
            for win in self._windows[robot_id]:
                self._emit(robot_id, win, out)
            self._windows[robot_id].clear()
        return out

    @property
    def open_windows(self) -> int:
        """Number of windows waiting (all robots)."""
        return sum(len(w) for w in self._windows.values())
