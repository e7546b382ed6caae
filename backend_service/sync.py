"""Frame-set synchronizer: group per-camera :class:`protocol.RobotDetections` into frame-sets.

Per robot, detections whose stamps (corrected by each camera's ``clock_offset_ns``) lie within
``sync_window_ms`` of a window's anchor stamp (the first stamp that opened it) form one
frame-set. A frame-set is whatever cameras saw the robot: no camera is required. A window is
emitted when

- every *live* camera (one that sent anything within ``camera_timeout_s``) has reported for it,
  either with a message in the window (a detection or "robot not seen") or with a later stamp
  (it moved on, so it will not contribute); with :attr:`FrameSetSynchronizer.relevant_cameras`
  set (a site with several robots), only the live cameras that can contribute to this robot's
  window count: the others' messages are not waited for (counted ``closed_early`` when a window
  goes out before them, and their messages after it are no ``late`` ones), or
- it has waited ``sync_max_wait_ms`` since its first message arrived (``now_ns`` clock).

Windows are emitted in stamp order; a message for a window that is already emitted (or older) is
``late`` and dropped, so output stamps never go backwards. Other counters: ``duplicate`` (same
camera, same stamp), ``future`` (stamp more than the site's ``clock.max_future_ms`` ahead of
``now_ns``), ``unknown_camera``, ``bad_keypoints`` (keypoint count differs from the robot model),
``image_size`` (the message's image size is not the camera's calibrated size nor an exact
scale of it; an exact scale, e.g. a 424x240 stream of an 848x480 calibration, is converted to
calibrated pixels, see :func:`~backend_service.frame_set.image_scale`),
``rate_limited`` (a camera sending faster than ``max_camera_rate_hz``: its excess frames),
``not_seen`` (message without this robot), ``after_close`` (a message for a window that went
out before it, from a camera that could not contribute to it), ``replaced`` (a camera sent two
frames within one window; the one closer to the anchor is kept), ``overflow`` (too many open
windows: the oldest is emitted early), ``empty`` (a window closed with no detection),
``emitted``. Memory is bounded by ``max_open_windows`` per robot and the site's camera count.

Every counter that concerns one camera is also kept per camera (:attr:`camera_counters`), so a
camera whose frames all come late or ahead is named. Each camera's clock is tracked too
(:meth:`camera_clocks`: the median of arrival minus stamp over its recent frames); one that
runs ahead is rejected as ``future`` rather than allowed to advance the shared window anchor
past the others (which would make all their frames ``late``). :meth:`problems` turns this into
status reasons: a camera gone silent, a rogue rate, stamps ahead or behind the others.

Time: ``now_ns`` is supplied by the caller (the backend's clock on the common time base); the
synchronizer never reads the wall clock.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from collections.abc import Callable, Collection
from typing import Final

from backend_service.frame_set import (
    CameraObservation,
    FrameSet,
    image_scale,
    observation_for_robot,
)
from core.site import Site
from protocol.messages import RobotDetections

log = logging.getLogger(__name__)

#: ``(robot_id, stamp_ns) -> cameras`` that can see that robot at that stamp (``None``: any);
#: see :class:`FrameSetSynchronizer`'s ``relevant_cameras``
RelevantCameras = Callable[[str, int], "frozenset[str] | None"]

COUNTER_NAMES: Final = (
    "received", "emitted", "late", "duplicate", "future", "unknown_camera", "bad_keypoints",
    "image_size", "not_seen", "replaced", "overflow", "empty", "rate_limited", "closed_early",
    "after_close",
)
#: the counters also kept per camera
CAMERA_COUNTER_NAMES: Final = (
    "received", "late", "duplicate", "future", "bad_keypoints", "image_size", "replaced",
    "rate_limited",
)
#: a problem (late, future, rate-limited frames) is reported for this long after it happened
PROBLEM_HOLD_NS: Final = 5_000_000_000
#: a camera with more of its recent frames late than this fraction is reported
LATE_PROBLEM_FRACTION: Final = 0.2
#: frames whose latency (arrival - stamp) is kept per camera for its clock estimate
CLOCK_SAMPLES: Final = 32


@dataclasses.dataclass
class _Window:
    anchor_ns: int
    opened_at_ns: int
    observations: dict[str, CameraObservation] = dataclasses.field(default_factory=dict)
    reported: set[str] = dataclasses.field(default_factory=set)
    #: the cameras that can contribute (``None``: any camera)
    relevant: frozenset[str] | None = None


class FrameSetSynchronizer:
    """Software synchronization of detections into :class:`FrameSet` s (paper Sec. III-B).

    ``robot_id``: synchronize only this robot; ``None``: every robot of the site (unidentified
    detections, ``robot_id == ""``, are only attributed when the site has one robot; on a site
    with several, :class:`~backend_service.pipeline.BackendPipeline` names them first by where
    each robot is expected to be, :mod:`backend_service.association`).
    Thresholds come from ``site.thresholds`` and the clock policy from ``site.clock``. Not
    thread-safe: call from one worker loop.
    """

    def __init__(self, site: Site, robot_id: str | None = None, max_open_windows: int = 32,
                 relevant_cameras: RelevantCameras | None = None) -> None:
        th = site.thresholds
        self.site = site
        self.window_ns = int(th.sync_window_ms * 1e6)
        self.max_wait_ns = int(th.sync_max_wait_ms * 1e6)
        self.camera_timeout_ns = int(th.camera_timeout_s * 1e9)
        self.max_future_ns = site.clock.max_future_ns
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
        self._newest_stamp: dict[str, int] = {}  # camera -> newest accepted stamp
        # live_cameras' answer, exact for now_ns in [_live_from_ns, _live_until_ns]: a camera
        # leaves the set only by time passing, joins it only by a push (which clears this)
        self._live: frozenset[str] | None = None
        self._live_from_ns = 0
        self._live_until_ns = 0
        self._size_warned: set[str] = set()
        self.camera_counters: dict[str, dict[str, int]] = {}
        self.max_rate_hz = float(th.max_camera_rate_hz)
        # token bucket per camera: (tokens, last refill ns); one second of frames deep
        self._bucket: dict[str, tuple[float, int]] = {}
        self._latency: dict[str, collections.deque[int]] = {}  # camera -> arrival - stamp
        self._last_problem_ns: dict[tuple[str, str], int] = {}  # (camera, counter) -> now_ns
        self._ever_seen: set[str] = set()
        self._last_rx_ns: dict[str, int] = {}  # camera -> arrival of its last frame, any
        self._future_ms: dict[str, float] = {}  # camera -> how far ahead its last refused was
        # camera -> arrival times of its recent frames / of those that came late
        self._recent_rx: dict[str, collections.deque[int]] = {}
        self._recent_late: dict[str, collections.deque[int]] = {}
        #: the robots whose windows are kept (:meth:`synchronize_only`)
        self._synced: tuple[str, ...] = self.robot_ids
        #: the cameras presumed live at a cold start (:meth:`expect_cameras`)
        self._expected: tuple[str, ...] = tuple(site.cameras)
        #: ``(robot_id, stamp_ns) -> cameras`` that can hold a detection of that robot at that
        #: (clock-corrected) stamp, ``None`` for any camera; asked once per window, when it
        #: opens. ``None`` (the default): every live camera is waited for.
        self.relevant_cameras = relevant_cameras
        #: per robot, the recently emitted windows closed before some live camera reported:
        #: (anchor, the cameras that could contribute)
        self._closed_early: dict[str, collections.deque[tuple[int, frozenset[str]]]] = {
            r: collections.deque(maxlen=8) for r in self.robot_ids}

    def synchronize_only(self, robot_ids: Collection[str] | None) -> list[FrameSet]:
        """Keep windows only for ``robot_ids`` (``None``: every robot, the default): a backend
        sharing a site's robots synchronizes the robots it runs, and a message's detections of
        the others cost nothing here. Returns the open windows of the robots left out, emitted
        now (the caller decides what they are worth); a robot taken back starts with the next
        message."""
        keep = set(self.robot_ids if robot_ids is None else robot_ids)
        out: list[FrameSet] = []
        for robot_id in self._synced:
            if robot_id not in keep:
                for win in self._windows[robot_id]:
                    self._emit(robot_id, win, out)
                self._windows[robot_id].clear()
        self._synced = tuple(r for r in self.robot_ids if r in keep)
        return out

    def expect_cameras(self, camera_ids: Collection[str] | None) -> None:
        """The cameras whose messages reach this synchronizer (``None``: every camera of the
        site, the default): at a cold start these are presumed live, so the first frame-sets
        wait for them and not for cameras that are never received here."""
        ids = tuple(self.site.cameras) if camera_ids is None else tuple(camera_ids)
        unknown = sorted(set(ids) - set(self.site.cameras))
        if unknown:
            raise ValueError(f"cameras {unknown} are not in site {self.site.name!r}")
        self._expected = ids

    # -- input -------------------------------------------------------------------------------

    def live_cameras(self, now_ns: int) -> frozenset[str]:
        """Cameras that sent anything within ``camera_timeout_s`` of ``now_ns``. Computed again
        only when a camera may have joined (a push) or left (time passed its timeout): every
        message polls, and a site may have many cameras."""
        if (self._live is not None
                and self._live_from_ns <= now_ns <= self._live_until_ns):
            return self._live
        live = frozenset(c for c, t in self._last_seen_ns.items()
                         if now_ns - t <= self.camera_timeout_ns)
        self._live = live
        self._live_from_ns = now_ns
        self._live_until_ns = (min(self._last_seen_ns[c] for c in live) + self.camera_timeout_ns
                               if live else now_ns)
        return live

    def push(self, msg: RobotDetections, now_ns: int) -> list[FrameSet]:
        """Add one camera message (arrived at ``now_ns``); returns frame-sets that closed."""
        self.counters["received"] += 1
        if not self._last_seen_ns:
            # Cold start: every site camera is presumed live until it has been silent for
            # camera_timeout_s, so the first frame-sets wait for all of them.
            self._last_seen_ns = dict.fromkeys(self._expected, now_ns)
            self._live = None
        cam = self.site.cameras.get(msg.camera_id)
        if cam is None:
            self.counters["unknown_camera"] += 1
            return self.poll(now_ns)
        self._count_camera(msg.camera_id, "received", now_ns)
        if not self._take_token(msg.camera_id, now_ns):
            self._count(msg.camera_id, "rate_limited", now_ns)
            return self.poll(now_ns)
        scale = image_scale(msg.image_width, msg.image_height, cam.width, cam.height)
        if scale is None:
            self._count(msg.camera_id, "image_size", now_ns)
            if msg.camera_id not in self._size_warned:
                self._size_warned.add(msg.camera_id)
                log.warning("camera %s: detections for %dx%d images, calibrated %dx%d (not an "
                            "exact scale): dropped (counter image_size; warned once)",
                            msg.camera_id, msg.image_width, msg.image_height, cam.width,
                            cam.height)
            return self.poll(now_ns)
        stamp = int(msg.stamp_ns) + int(cam.clock_offset_ns)
        latency = self._latency.setdefault(msg.camera_id, collections.deque(maxlen=CLOCK_SAMPLES))
        latency.append(now_ns - stamp)
        self._last_rx_ns[msg.camera_id] = now_ns
        if stamp - now_ns > self.max_future_ns:
            self._count(msg.camera_id, "future", now_ns)
            self._future_ms[msg.camera_id] = (stamp - now_ns) * 1e-6
            return self.poll(now_ns)
        recent = self._last_stamp.setdefault(msg.camera_id, collections.deque(maxlen=16))
        if stamp in recent:
            self._count(msg.camera_id, "duplicate", now_ns)
            return self.poll(now_ns)
        recent.append(stamp)
        self._newest_stamp[msg.camera_id] = max(recent)
        self._ever_seen.add(msg.camera_id)
        self._last_seen_ns[msg.camera_id] = max(now_ns, self._last_seen_ns.get(msg.camera_id,
                                                                              now_ns))
        if self._live is not None and msg.camera_id not in self._live:
            self._live = None  # a camera joined
        for robot_id in self._synced:
            self._add(robot_id, msg, stamp, now_ns, scale)
        return self.poll(now_ns)

    def _count_camera(self, camera_id: str, counter: str, now_ns: int) -> None:
        per = self.camera_counters.setdefault(camera_id, dict.fromkeys(CAMERA_COUNTER_NAMES, 0))
        per[counter] = per.get(counter, 0) + 1
        if counter in ("received", "late"):
            recent = self._recent_rx if counter == "received" else self._recent_late
            recent.setdefault(camera_id, collections.deque(maxlen=256)).append(now_ns)
        elif counter != "replaced":
            self._last_problem_ns[(camera_id, counter)] = now_ns

    def _count(self, camera_id: str, counter: str, now_ns: int) -> None:
        self.counters[counter] += 1
        self._count_camera(camera_id, counter, now_ns)

    def _take_token(self, camera_id: str, now_ns: int) -> bool:
        """Token bucket of ``max_camera_rate_hz``, one second deep: a burst of a second's worth
        of frames passes, a sustained higher rate is cut to the limit."""
        if self.max_rate_hz <= 0:
            return True
        tokens, last = self._bucket.get(camera_id, (self.max_rate_hz, now_ns))
        tokens = min(self.max_rate_hz, tokens + max(0, now_ns - last) * 1e-9 * self.max_rate_hz)
        if tokens < 1.0:
            self._bucket[camera_id] = (tokens, now_ns)
            return False
        self._bucket[camera_id] = (tokens - 1.0, now_ns)
        return True

    # -- health ------------------------------------------------------------------------------

    def camera_clocks(self) -> dict[str, float]:
        """Per camera: the median latency (arrival minus corrected stamp, ms) over its recent
        frames. Negative: its clock runs ahead of the backend's."""
        out = {}
        for cam, lat in self._latency.items():
            if lat:
                values = sorted(lat)
                out[cam] = values[len(values) // 2] * 1e-6
        return out

    def problems(self, now_ns: int) -> list[str]:
        """Status reasons, one per unhealthy camera (empty when all is well): a camera that
        was seen and has gone silent, one whose frames were rejected as ahead of the clock,
        late, or over the rate limit within the last few seconds, one whose clock differs from
        the others' by more than the sync window."""
        out = []
        # lost: nothing at all arrives (a camera whose frames arrive but are refused is named
        # for why they are refused instead)
        silent = sorted(c for c in self._ever_seen
                        if now_ns - self._last_rx_ns.get(c, now_ns) > self.camera_timeout_ns)
        for cam in silent:
            out.append(f"camera {cam} lost")
        clocks = self.camera_clocks()
        consensus = sorted(clocks.values())[len(clocks) // 2] if len(clocks) >= 3 else None
        for (cam, counter), at in sorted(self._last_problem_ns.items()):
            if now_ns - at > PROBLEM_HOLD_NS or cam in silent:
                continue
            if counter == "future":
                ahead = self._future_ms.get(cam, float("nan"))
                out.append(f"camera {cam} stamps {ahead:.0f} ms ahead of the clock (dropped)")
            elif counter == "rate_limited":
                out.append(f"camera {cam} above {self.max_rate_hz:g} Hz (rogue source?)")
            else:
                out.append(f"camera {cam}: {counter}")
        for cam, late in sorted(self._recent_late.items()):
            n_late = sum(1 for t in late if now_ns - t <= PROBLEM_HOLD_NS)
            n_rx = sum(1 for t in self._recent_rx.get(cam, ()) if now_ns - t <= PROBLEM_HOLD_NS)
            if cam not in silent and n_late >= 5 and n_late > LATE_PROBLEM_FRACTION * n_rx:
                out.append(f"camera {cam}: {n_late} of {n_rx} frames late in "
                           f"{PROBLEM_HOLD_NS * 1e-9:.0f} s")
        if consensus is not None:
            for cam, lat in sorted(clocks.items()):
                if abs(lat - consensus) * 1e6 > max(self.window_ns, 1) and cam not in silent:
                    out.append(f"camera {cam} clock {lat - consensus:+.0f} ms off the others")
        return out

    def _add(self, robot_id: str, msg: RobotDetections, stamp: int, now_ns: int,
             scale: float = 1.0) -> None:
        emitted = self._emitted_anchor[robot_id]
        if emitted is not None and stamp <= emitted + self.window_ns:
            for anchor, relevant in self._closed_early[robot_id]:
                if abs(stamp - anchor) <= self.window_ns and msg.camera_id not in relevant:
                    # its window did not wait for this camera: it could not contribute
                    self.counters["after_close"] += 1
                    return
            self._count(msg.camera_id, "late", now_ns)
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
            if self.relevant_cameras is not None:
                win.relevant = self.relevant_cameras(robot_id, stamp)
            windows.append(win)
            windows.sort(key=lambda w: w.anchor_ns)
        win.reported.add(msg.camera_id)
        obs = observation_for_robot(msg, robot_id, self._num_keypoints.get(robot_id, -1),
                                    self._attribute_unnamed, stamp, scale)
        if isinstance(obs, str):
            if obs in CAMERA_COUNTER_NAMES:
                self._count(msg.camera_id, obs, now_ns)
            else:
                self.counters[obs] += 1
            return
        old = win.observations.get(msg.camera_id)
        if old is not None:
            self._count(msg.camera_id, "replaced", now_ns)
            if abs(old.stamp_ns - win.anchor_ns) <= abs(stamp - win.anchor_ns):
                return
        win.observations[msg.camera_id] = obs

    # -- output ------------------------------------------------------------------------------

    def _moved_on(self, camera_id: str, win: _Window) -> bool:
        newest = self._newest_stamp.get(camera_id)
        return newest is not None and newest > win.anchor_ns + self.window_ns

    def _ready(self, win: _Window, live: frozenset[str], now_ns: int) -> bool:
        if now_ns - win.opened_at_ns >= self.max_wait_ns:
            return True
        pending = live - win.reported
        if win.relevant is not None:
            pending &= win.relevant
        return all(self._moved_on(c, win) for c in pending)

    def poll(self, now_ns: int) -> list[FrameSet]:
        """Emit every window that is complete or has waited long enough, oldest first."""
        out: list[FrameSet] = []
        live = self.live_cameras(now_ns)
        for robot_id in self._synced:
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
                if win.relevant is not None and not live <= win.reported | win.relevant:
                    # live cameras that could not contribute had not reported yet
                    self.counters["closed_early"] += 1
                    self._closed_early[robot_id].append((win.anchor_ns, win.relevant))
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
