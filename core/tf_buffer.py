"""A small TF buffer: the robot's frame tree from ``/tf`` and ``/tf_static``, looked up at a stamp.

A ROS robot describes where its parts are as a tree of frames: every transform message says
where a ``child`` frame is in its ``parent`` frame (``T_parent_child``, metres and a unit
quaternion) at a stamp. Static transforms (``/tf_static``: a camera bolted to the head) hold
at any time; dynamic ones (``/tf``: the head's pan and tilt, the base in ``odom``) hold at their
stamp. :class:`TfBuffer` keeps that tree and answers :meth:`TfBuffer.lookup`:
``T_target_source`` at ``stamp_ns``, the pose of ``source`` in ``target``, found by walking
from both frames up to their common ancestor (so ``base_link`` <- ``head_pan_link`` <-
``head_tilt_link`` <- ``camera`` and the reverse both work).

Time:

- a dynamic edge keeps a bounded history (:attr:`TfBufferConfig.history_s` seconds behind its
  newest stamp, at most :attr:`TfBufferConfig.max_items_per_edge` transforms); a stamp between
  two of its transforms gets their SE(3) interpolation (translation linear, rotation along the
  shorter great arc: slerp);
- a stamp after an edge's newest transform is answered with that newest transform while it is
  at most :attr:`TfBufferConfig.max_age_s` older than the stamp (counted ``held``: a joint
  published at 50 Hz is up to 20 ms behind a camera frame); older, the lookup fails with
  :class:`TfStaleError` saying how old against the limit;
- a stamp before an edge's oldest transform fails with :class:`TfExtrapolationError` naming the
  span the history holds (no motion is invented);
- ``stamp_ns=None`` asks for the latest time every dynamic edge of the chain covers (tf2's
  ``Time(0)``).

What is refused on input (``add`` returns ``False``, counts it, logs the first of each kind per
edge): a non-finite translation or rotation, a quaternion whose squared norm is more than 1 %
off one (tf2's check), a matrix that is not a rotation, an empty frame, a frame that is its own
parent (``invalid``); a frame that already has another parent (``two_parents``: one frame, one
parent); an edge that would close a loop (``loops``); a static edge sent as dynamic or the
reverse (``kind_conflict``); a dynamic transform older than the history's window
(``too_old``) or at a stamp already held (``duplicate``, the first one wins); a new frame past
:attr:`TfBufferConfig.max_frames` (``too_many_frames``). A static edge
sent again replaces its value (a restarted robot may republish ``/tf_static``).

Lookups that fail raise a :class:`TfError` (``missing``, ``stale``, ``extrapolation`` in
:attr:`TfBuffer.counters`; :attr:`TfBuffer.last_error` keeps the latest message for a
service's status). :func:`transforms_from_ros` / :meth:`TfBuffer.add_tf_message` take a
decoded ``tf2_msgs/msg/TFMessage`` (ROS 2 or ROS 1, as
:func:`robot_bridge.adapters.ros2.deserialize_tf_message` returns it). Frame ids lose a leading
``/`` as tf2 does. Transport-free and not thread-safe: one worker loop owns a buffer.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterable
from typing import Any, Final

import numpy as np

from core.geometry import quaternion_to_rotation, rotation_to_quaternion
from core.history import StampedHistory
from protocol.errors import SmartedgeError
from protocol.messages import NS_PER_S

log = logging.getLogger(__name__)

#: tf2 refuses a quaternion whose squared norm is further than this from 1
_QUATERNION_NORM2_TOLERANCE: Final = 0.01
#: how far a (4, 4) matrix's rotation block may be from orthonormal
_ROTATION_TOLERANCE: Final = 1e-4
#: below this angle between two rotations slerp is replaced by a normalised lerp
_SLERP_LINEAR_DOT: Final = 0.9995
#: how many known frames an unknown-frame error lists
_FRAMES_LISTED: Final = 20
#: refusals logged at most once per (kind, frame), for this many (kind, frame) pairs
_WARNINGS_KEPT: Final = 256

#: the counters a buffer keeps (all start at 0; see the module docstring)
COUNTER_NAMES: Final = (
    "transforms", "static_transforms", "invalid", "two_parents", "loops", "kind_conflict",
    "too_old", "duplicate", "too_many_frames", "lookups", "lookups_ok", "missing", "stale",
    "extrapolation", "held",
)


# --------------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------------


class TfError(SmartedgeError, LookupError):
    """A lookup could not be answered; the message names the frames and why.

    ``target_frame``, ``source_frame``: the lookup's frames; ``stamp_ns``: its stamp
    (``None``: latest)."""

    def __init__(self, message: str, *, target_frame: str, source_frame: str,
                 stamp_ns: int | None) -> None:
        super().__init__(message)
        self.target_frame = target_frame
        self.source_frame = source_frame
        self.stamp_ns = stamp_ns


class TfMissingError(TfError):
    """A frame is unknown, or the two frames are in trees that no transform joins.

    ``missing_frame``: the unknown frame (``None`` when both are known but not connected);
    ``roots``: the root each frame reaches (``(target_root, source_root)``) when not connected.
    """

    def __init__(self, message: str, *, missing_frame: str | None = None,
                 roots: tuple[str, str] | None = None, **kw: Any) -> None:
        super().__init__(message, **kw)
        self.missing_frame = missing_frame
        self.roots = roots


class TfStaleError(TfError):
    """The newest transform of an edge is older than the lookup stamp by more than the limit.

    ``parent``, ``child``: the edge; ``age_ns``: stamp - newest; ``limit_ns``: the
    configured ``max_age_s`` in ns."""

    def __init__(self, message: str, *, parent: str, child: str, age_ns: int, limit_ns: int,
                 **kw: Any) -> None:
        super().__init__(message, **kw)
        self.parent = parent
        self.child = child
        self.age_ns = age_ns
        self.limit_ns = limit_ns


class TfExtrapolationError(TfError):
    """The lookup stamp is before the oldest transform an edge's history holds.

    ``parent``, ``child``: the edge; ``oldest_ns``, ``newest_ns``: the span held."""

    def __init__(self, message: str, *, parent: str, child: str, oldest_ns: int,
                 newest_ns: int, **kw: Any) -> None:
        super().__init__(message, **kw)
        self.parent = parent
        self.child = child
        self.oldest_ns = oldest_ns
        self.newest_ns = newest_ns


# --------------------------------------------------------------------------------------------
# configuration and data
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TfBufferConfig:
    """How much a :class:`TfBuffer` keeps and how old a transform may be.

    ``history_s``: seconds of history per dynamic edge, behind its newest stamp (tf2 keeps 10).
    ``max_age_s``: how far a lookup stamp may be past an edge's newest transform and still get
    it (0: only stamps the history brackets). ``max_items_per_edge``: a hard cap on one edge's
    history (a flood of distinct stamps cannot grow memory); ``max_frames``: on the number of
    child frames (a flood of invented frame names cannot either)."""

    history_s: float = 10.0
    max_age_s: float = 0.1
    max_items_per_edge: int = 10_000
    max_frames: int = 1_000

    def __post_init__(self) -> None:
        if not (math.isfinite(self.history_s) and self.history_s > 0.0):
            raise ValueError(f"TfBufferConfig.history_s must be > 0 s, got {self.history_s}")
        if not (math.isfinite(self.max_age_s) and self.max_age_s >= 0.0):
            raise ValueError(f"TfBufferConfig.max_age_s must be >= 0 s, got {self.max_age_s}")
        if int(self.max_items_per_edge) < 2:
            raise ValueError(f"TfBufferConfig.max_items_per_edge must be >= 2, got "
                             f"{self.max_items_per_edge}")
        if int(self.max_frames) < 1:
            raise ValueError(f"TfBufferConfig.max_frames must be >= 1, got {self.max_frames}")


@dataclasses.dataclass(frozen=True, eq=False)
class Rigid:
    """A rigid transform ``T_parent_child``: ``translation_m`` (3,) and the unit quaternion
    ``q_xyzw`` (4,) of the child's axes in the parent's."""

    translation_m: np.ndarray
    q_xyzw: np.ndarray

    def matrix(self) -> np.ndarray:
        """The (4, 4) homogeneous matrix."""
        T = np.eye(4)
        T[:3, :3] = quaternion_to_rotation(self.q_xyzw)
        T[:3, 3] = self.translation_m
        return T


@dataclasses.dataclass(frozen=True)
class TransformReading:
    """One transform as a ROS message carries it: ``child`` in ``parent`` at ``stamp_ns``."""

    parent: str
    child: str
    stamp_ns: int
    translation_m: tuple[float, float, float]
    q_xyzw: tuple[float, float, float, float]


@dataclasses.dataclass
class _Edge:
    parent: str
    static: bool
    value: Rigid | None = None  # static edges
    history: StampedHistory[Rigid] | None = None  # dynamic edges


def _slerp(q0: np.ndarray, q1: np.ndarray, fraction: float) -> np.ndarray:
    """Unit quaternion a ``fraction`` of the way from ``q0`` to ``q1`` along the shorter arc."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > _SLERP_LINEAR_DOT:
        q = q0 + fraction * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(min(dot, 1.0))
    s = math.sin(theta)
    return (math.sin((1.0 - fraction) * theta) * q0 + math.sin(fraction * theta) * q1) / s


def interpolate_rigid(a: Rigid, b: Rigid, fraction: float) -> Rigid:
    """SE(3) blend a ``fraction`` (in [0, 1]) of the way from ``a`` to ``b`` (both
    ``T_parent_child`` of one edge): translation linear, rotation slerp."""
    t = a.translation_m + fraction * (b.translation_m - a.translation_m)
    return Rigid(t, _slerp(a.q_xyzw, b.q_xyzw, fraction))


def _clean_frame(frame: Any) -> str:
    return str(frame).strip().lstrip("/")


def _fmt_s(ns: int) -> str:
    return f"{ns / NS_PER_S:.3f} s"


# --------------------------------------------------------------------------------------------
# the buffer
# --------------------------------------------------------------------------------------------


class TfBuffer:
    """The frame tree, one edge per child frame (module docstring).

    ``config``: :class:`TfBufferConfig`. :attr:`counters` holds :data:`COUNTER_NAMES`;
    :attr:`last_error` the latest refusal or failed lookup, for a status line."""

    def __init__(self, config: TfBufferConfig | None = None) -> None:
        self.config = config or TfBufferConfig()
        self._history_ns = round(self.config.history_s * NS_PER_S)
        self._max_age_ns = round(self.config.max_age_s * NS_PER_S)
        self._edges: dict[str, _Edge] = {}  # by child frame
        self.counters: dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)
        self.last_error: str = ""
        self._warned: set[tuple[str, str]] = set()

    # -- input -----------------------------------------------------------------------------------

    def add(self, parent: str, child: str, stamp_ns: int, T_parent_child: np.ndarray, *,
            static: bool = False) -> bool:
        """Add the (4, 4) transform ``T_parent_child`` (pose of ``child`` in ``parent``, m) at
        ``stamp_ns``; ``static``: valid at any time (``/tf_static``). ``True`` when held; a
        refusal is counted and ``False`` (module docstring)."""
        T = np.asarray(T_parent_child, dtype=np.float64)
        reason = ""
        if T.shape != (4, 4):
            reason = f"transform has shape {T.shape}, not (4, 4)"
        elif not np.all(np.isfinite(T)):
            reason = "transform is not finite"
        else:
            R = T[:3, :3]
            if (float(np.max(np.abs(R.T @ R - np.eye(3)))) > _ROTATION_TOLERANCE
                    or float(np.linalg.det(R)) <= 0.0
                    or float(np.max(np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)))) > _ROTATION_TOLERANCE):
                reason = "transform's rotation block is not a rotation"
        if reason:
            return self._refuse("invalid", _clean_frame(parent), _clean_frame(child), reason)
        return self.add_quaternion(parent, child, stamp_ns, T[:3, 3],
                                   rotation_to_quaternion(T[:3, :3]), static=static)

    def add_quaternion(self, parent: str, child: str, stamp_ns: int,
                       translation_m: Iterable[float], q_xyzw: Iterable[float], *,
                       static: bool = False) -> bool:
        """:meth:`add` with the transform as a ROS message holds it: ``translation_m`` (3,)
        and the quaternion ``q_xyzw`` (4,), which must be unit within tf2's tolerance (it is
        normalised)."""
        parent, child = _clean_frame(parent), _clean_frame(child)
        try:
            t = np.asarray(list(translation_m), dtype=np.float64).reshape(3)
            q = np.asarray(list(q_xyzw), dtype=np.float64).reshape(4)
            stamp = int(stamp_ns)
        except (TypeError, ValueError) as exc:
            return self._refuse("invalid", parent, child, f"unreadable transform: {exc}")
        if not parent or not child:
            return self._refuse("invalid", parent, child, "empty frame id")
        if parent == child:
            return self._refuse("invalid", parent, child, "a frame cannot be its own parent")
        if not np.all(np.isfinite(t)):
            return self._refuse("invalid", parent, child, f"translation {t.tolist()} is not "
                                "finite")
        norm2 = float(np.dot(q, q))
        if not math.isfinite(norm2) or abs(norm2 - 1.0) > _QUATERNION_NORM2_TOLERANCE:
            return self._refuse("invalid", parent, child,
                                f"quaternion {q.tolist()} is not a unit quaternion")
        if stamp < 0 and not static:
            return self._refuse("invalid", parent, child, f"negative stamp {stamp}")
        q = q / math.sqrt(norm2)

        edge = self._edges.get(child)
        if edge is not None and edge.parent != parent:
            return self._refuse("two_parents", parent, child,
                                f"'{child}' already has parent '{edge.parent}'")
        if edge is None and child in self._path_to_root(parent):
            return self._refuse("loops", parent, child,
                                f"'{parent}' is below '{child}': the edge would close a loop")
        if edge is not None and edge.static != static:
            was = "static" if edge.static else "dynamic"
            return self._refuse("kind_conflict", parent, child,
                                f"the edge is {was}, this transform is not")
        if edge is None and len(self._edges) >= int(self.config.max_frames):
            return self._refuse("too_many_frames", parent, child,
                                f"the buffer holds {len(self._edges)} frames already")
        rigid = Rigid(t, q)
        if static:
            if edge is None:
                self._edges[child] = _Edge(parent, True, value=rigid)
            else:
                edge.value = rigid
            self.counters["static_transforms"] += 1
            return True
        if edge is None:
            edge = _Edge(parent, False, history=StampedHistory(
                int(self.config.max_items_per_edge), out_of_order="insert"))
            self._edges[child] = edge
        history = edge.history
        assert history is not None
        newest = history.latest()
        if newest is not None and stamp < newest.stamp_ns - self._history_ns:
            return self._refuse("too_old", parent, child,
                                f"stamp {_fmt_s(newest.stamp_ns - stamp)} older than the newest, "
                                f"history {self.config.history_s:g} s")
        if not history.insert(stamp, rigid):
            return self._refuse("duplicate", parent, child, f"stamp {stamp} already held")
        history.trim_to_age(self._history_ns)
        self.counters["transforms"] += 1
        return True

    def add_readings(self, readings: Iterable[TransformReading], *, static: bool) -> int:
        """:meth:`add_quaternion` every reading; returns how many were held."""
        return sum(self.add_quaternion(r.parent, r.child, r.stamp_ns, r.translation_m,
                                       r.q_xyzw, static=static) for r in readings)

    def add_tf_message(self, msg: Any, *, static: bool) -> int:
        """Every transform of a decoded ``tf2_msgs/msg/TFMessage`` (``/tf``; ``static`` for
        ``/tf_static``); returns how many were held. A transform whose fields cannot be read
        is counted ``invalid``."""
        readings: list[TransformReading] = []
        for index, item in enumerate(getattr(msg, "transforms", None) or ()):
            try:
                readings.append(transform_from_ros(item))
            except (AttributeError, TypeError, ValueError) as exc:
                self._refuse("invalid", "?", "?", f"transforms[{index}]: {exc}")
        return self.add_readings(readings, static=static)

    def _refuse(self, counter: str, parent: str, child: str, reason: str) -> bool:
        self.counters[counter] += 1
        self.last_error = f"transform {parent or '?'} -> {child or '?'} refused: {reason}"
        if (counter, child) not in self._warned and len(self._warned) < _WARNINGS_KEPT:
            self._warned.add((counter, child))
            log.warning("%s (%s; further ones counted, not logged)", self.last_error, counter)
        return False

    # -- the tree --------------------------------------------------------------------------------

    def frames(self) -> set[str]:
        """Every frame some transform names (as child or parent)."""
        return set(self._edges) | {e.parent for e in self._edges.values()}

    def parent_of(self, frame: str) -> str | None:
        """The parent of ``frame``; ``None`` for a root or an unknown frame."""
        edge = self._edges.get(_clean_frame(frame))
        return edge.parent if edge is not None else None

    def is_static(self, frame: str) -> bool | None:
        """Whether the edge to ``frame``'s parent is static; ``None`` when it has none."""
        edge = self._edges.get(_clean_frame(frame))
        return edge.static if edge is not None else None

    def _path_to_root(self, frame: str) -> list[str]:
        path = [frame]
        while (edge := self._edges.get(path[-1])) is not None:
            path.append(edge.parent)
        return path

    # -- lookup ----------------------------------------------------------------------------------

    def lookup(self, target_frame: str, source_frame: str,
               stamp_ns: int | None = None) -> np.ndarray:
        """``T_target_source`` (4, 4): the pose of ``source_frame`` in ``target_frame`` at
        ``stamp_ns`` (``None``: the latest time the chain covers). Raises
        :class:`TfMissingError`, :class:`TfStaleError` or :class:`TfExtrapolationError`."""
        target, source = _clean_frame(target_frame), _clean_frame(source_frame)
        self.counters["lookups"] += 1
        try:
            T = self._lookup(target, source, stamp_ns)
        except TfError as exc:
            self.last_error = str(exc)
            raise
        self.counters["lookups_ok"] += 1
        return T

    def can_transform(self, target_frame: str, source_frame: str,
                      stamp_ns: int | None = None) -> bool:
        """Whether :meth:`lookup` would succeed (counted as a lookup)."""
        try:
            self.lookup(target_frame, source_frame, stamp_ns)
        except TfError:
            return False
        return True

    def _chain(self, target: str, source: str, stamp_ns: int | None) -> tuple[list[str],
                                                                              list[str]]:
        """The children whose edges lead from ``target`` and from ``source`` up to their
        common ancestor."""
        known = self.frames()
        for frame in (target, source):
            if frame not in known:
                self.counters["missing"] += 1
                names = sorted(known)
                listed = ", ".join(names[:_FRAMES_LISTED]) or "none"
                if len(names) > _FRAMES_LISTED:
                    listed += f" and {len(names) - _FRAMES_LISTED} more"
                raise TfMissingError(
                    f"frame '{frame}' is unknown: no transform names it (looking up "
                    f"'{source}' in '{target}'; known frames: {listed})",
                    missing_frame=frame, target_frame=target, source_frame=source,
                    stamp_ns=stamp_ns)
        up_target, up_source = self._path_to_root(target), self._path_to_root(source)
        on_target = set(up_target)
        common = next((f for f in up_source if f in on_target), None)
        if common is None:
            self.counters["missing"] += 1
            raise TfMissingError(
                f"'{target}' and '{source}' are not connected: '{target}' reaches root "
                f"'{up_target[-1]}', '{source}' reaches root '{up_source[-1]}'; no transform "
                f"joins the two trees", roots=(up_target[-1], up_source[-1]),
                target_frame=target, source_frame=source, stamp_ns=stamp_ns)
        return (up_target[:up_target.index(common)], up_source[:up_source.index(common)])

    def _lookup(self, target: str, source: str, stamp_ns: int | None) -> np.ndarray:
        if target == source:
            return np.eye(4)
        from_target, from_source = self._chain(target, source, stamp_ns)
        if stamp_ns is None:
            newest = [e.history.latest().stamp_ns  # type: ignore[union-attr]
                      for e in (self._edges[c] for c in from_target + from_source)
                      if not e.static]
            stamp = min(newest) if newest else 0
        else:
            stamp = int(stamp_ns)
        ctx = {"target_frame": target, "source_frame": source, "stamp_ns": stamp_ns}
        T_common_target = self._compose_up(from_target, stamp, ctx)
        T_common_source = self._compose_up(from_source, stamp, ctx)
        R, t = T_common_target[:3, :3], T_common_target[:3, 3]
        T_target_common = np.eye(4)
        T_target_common[:3, :3] = R.T
        T_target_common[:3, 3] = -R.T @ t
        return T_target_common @ T_common_source

    def _compose_up(self, children: list[str], stamp: int, ctx: dict[str, Any]) -> np.ndarray:
        """``T_ancestor_first`` for the edges of ``children`` (first child lowest)."""
        T = np.eye(4)
        for child in children:
            T = self._edge_at(child, stamp, ctx).matrix() @ T
        return T

    def _edge_at(self, child: str, stamp: int, ctx: dict[str, Any]) -> Rigid:
        edge = self._edges[child]
        if edge.static:
            assert edge.value is not None
            return edge.value
        history = edge.history
        assert history is not None
        oldest, newest = history.oldest(), history.latest()
        assert oldest is not None and newest is not None
        if stamp > newest.stamp_ns:
            age = stamp - newest.stamp_ns
            if age > self._max_age_ns:
                self.counters["stale"] += 1
                raise TfStaleError(
                    f"transform {edge.parent} -> {child} is stale: its newest is "
                    f"{_fmt_s(age)} older than the lookup stamp (limit "
                    f"{self.config.max_age_s:g} s)", parent=edge.parent, child=child,
                    age_ns=age, limit_ns=self._max_age_ns, **ctx)
            self.counters["held"] += 1
            return newest.item
        bracket = history.bracket(stamp)
        if bracket is None:
            self.counters["extrapolation"] += 1
            raise TfExtrapolationError(
                f"transform {edge.parent} -> {child}: the lookup stamp is "
                f"{_fmt_s(oldest.stamp_ns - stamp)} before the oldest held (history spans "
                f"{_fmt_s(newest.stamp_ns - oldest.stamp_ns)}, {len(history)} transforms)",
                parent=edge.parent, child=child, oldest_ns=oldest.stamp_ns,
                newest_ns=newest.stamp_ns, **ctx)
        if bracket.fraction == 0.0:
            return bracket.before.item
        return interpolate_rigid(bracket.before.item, bracket.after.item, bracket.fraction)

    # -- status ----------------------------------------------------------------------------------

    def detail(self) -> str:
        """One status line: frames, edges, what failed last."""
        static = sum(e.static for e in self._edges.values())
        line = (f"tf: {len(self.frames())} frames, {static} static and "
                f"{len(self._edges) - static} dynamic transforms")
        return f"{line}; last error: {self.last_error}" if self.last_error else line


# --------------------------------------------------------------------------------------------
# ROS messages
# --------------------------------------------------------------------------------------------


def transform_from_ros(msg: Any) -> TransformReading:
    """A decoded ``geometry_msgs/msg/TransformStamped`` (rosbags object, ROS 2 or ROS 1) →
    :class:`TransformReading` (``header.frame_id`` the parent, ``child_frame_id`` the child,
    the header stamp in ns). Values are checked by :meth:`TfBuffer.add_quaternion`."""
    stamp = msg.header.stamp
    tr, rot = msg.transform.translation, msg.transform.rotation
    return TransformReading(
        parent=str(msg.header.frame_id), child=str(msg.child_frame_id),
        stamp_ns=int(stamp.sec) * NS_PER_S + int(stamp.nanosec),
        translation_m=(float(tr.x), float(tr.y), float(tr.z)),
        q_xyzw=(float(rot.x), float(rot.y), float(rot.z), float(rot.w)))


def transforms_from_ros(msg: Any) -> list[TransformReading]:
    """Every transform of a decoded ``tf2_msgs/msg/TFMessage``, in message order."""
    return [transform_from_ros(item) for item in msg.transforms]
