"""The one trajectory type and its files: stamped 3D poses (:class:`Trajectory`), made from
planar poses (x, y, theta) or read from and written to TUM files (one pose per line,
``stamp_s tx ty tz qx qy qz qw``; blank lines and ``#`` comments ignored; errors name the file
and the line); planar poses interpolated at any stamps with a gap limit
(:meth:`Trajectory.planar_at`).

Pure numpy; the metrics over trajectories (alignment, APE) live in :mod:`lab.evaluation.metrics`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from core.geometry import quaternion_to_rotation, wrap_angle_array, yaw_to_quaternion_array
from protocol.errors import SmartedgeError

log = logging.getLogger(__name__)


class TrajectoryError(SmartedgeError, ValueError):
    """Arrays that do not make a trajectory (lengths or shapes disagree)."""


@dataclasses.dataclass(frozen=True, eq=False)
class Trajectory:
    """Stamped 3D poses: ``stamps_s`` (N,) seconds, ``positions_m`` (N, 3) metres,
    ``quat_xyzw`` (N, 4) unit quaternions (x, y, z, w) of the body → world rotation."""

    stamps_s: np.ndarray
    positions_m: np.ndarray
    quat_xyzw: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.stamps_s)
        if self.positions_m.shape != (n, 3) or self.quat_xyzw.shape != (n, 4):
            raise TrajectoryError(
                f"trajectory arrays disagree: {n} stamps, positions {self.positions_m.shape}, "
                f"quaternions {self.quat_xyzw.shape}"
            )

    def __len__(self) -> int:
        return len(self.stamps_s)

    @classmethod
    def from_planar(cls, stamps_s: np.ndarray, xytheta: np.ndarray) -> Trajectory:
        """Planar poses (N, 3) (x, y, theta) at z = 0 → a 3D trajectory."""
        p = np.asarray(xytheta, dtype=np.float64).reshape(-1, 3)
        pos = np.column_stack([p[:, :2], np.zeros(len(p))])
        return cls(np.asarray(stamps_s, dtype=np.float64).reshape(-1), pos,
                   yaw_to_quaternion_array(p[:, 2]))

    def rotations(self) -> np.ndarray:
        """(N, 3, 3) body → world rotation matrices."""
        return quaternion_to_rotation(self.quat_xyzw)

    def planar(self) -> np.ndarray:
        """(N, 3) (x, y, yaw) of the poses (yaw of the rotation's x axis in the xy plane)."""
        R = self.rotations()
        yaw = wrap_angle_array(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
        return np.column_stack([self.positions_m[:, :2], yaw])

    def planar_at(self, stamps_s: np.ndarray | Sequence[float], max_gap_s: float
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Planar poses interpolated at ``stamps_s`` (M,): ((M, 3) x, y, yaw, (M,) bool ``ok``).
        A stamp is interpolated linearly (yaw along the shorter way) between the poses just
        before and just after it, or taken as is where a pose has that stamp. ``ok`` is False
        (poses NaN) outside the trajectory, or where those two poses are more than
        ``max_gap_s`` apart (the pose between them is not known well enough). The stamps must
        be increasing (a :class:`TrajectoryError` says where not)."""
        t = np.asarray(self.stamps_s, dtype=np.float64)
        q = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
        if len(t) > 1 and not np.all(np.diff(t) > 0):
            i = int(np.flatnonzero(np.diff(t) <= 0)[0])
            raise TrajectoryError(f"stamps not increasing at pose {i + 1} ({t[i + 1]!r} after "
                                  f"{t[i]!r})")
        out = np.full((len(q), 3), np.nan)
        ok = np.zeros(len(q), bool)
        if len(t) == 0:
            return out, ok
        p = self.planar()
        hi = np.searchsorted(t, q, side="left")  # first pose at or after each stamp
        exact = (hi < len(t)) & (t[np.minimum(hi, len(t) - 1)] == q)
        out[exact] = p[hi[exact]]
        ok[exact] = True
        between = ~exact & (hi > 0) & (hi < len(t))
        a, b = hi[between] - 1, hi[between]
        gap = t[b] - t[a]
        good = gap <= max_gap_s
        a, b = a[good], b[good]
        idx = np.flatnonzero(between)[good]
        alpha = ((q[idx] - t[a]) / (t[b] - t[a]))[:, None]
        d = p[b] - p[a]
        d[:, 2] = wrap_angle_array(d[:, 2])
        out[idx] = p[a] + alpha * d
        out[idx, 2] = wrap_angle_array(out[idx, 2])
        ok[idx] = True
        return out, ok

    def subset(self, idx: np.ndarray | Sequence[int]) -> Trajectory:
        i = np.asarray(idx, dtype=np.int64)
        return Trajectory(self.stamps_s[i], self.positions_m[i], self.quat_xyzw[i])


class TrajectoryFileError(SmartedgeError, ValueError):
    """A trajectory file is missing, unreadable or malformed; the message names file and line."""

    def __init__(self, path: str, line: int | None, reason: str) -> None:
        where = f"{path}:{line}" if line is not None else path
        super().__init__(f"{where}: {reason}")
        self.path = path
        self.line = line
        self.reason = reason


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM file into a :class:`Trajectory` (stamps in s, positions in m, quaternions
    x, y, z, w). Raises :class:`TrajectoryFileError` naming the file and line on bad input."""
    p = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryFileError(p, None, f"cannot read: {exc}") from None
    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise TrajectoryFileError(
                p, lineno, f"expected 8 numbers (stamp tx ty tz qx qy qz qw), got {len(parts)}"
            )
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            raise TrajectoryFileError(p, lineno, f"not a number in {line[:80]!r}") from None
        if not all(math.isfinite(v) for v in vals):
            raise TrajectoryFileError(p, lineno, "contains NaN or infinity")
        if math.sqrt(sum(v * v for v in vals[4:])) < 1e-9:
            raise TrajectoryFileError(p, lineno, "quaternion is zero")
        rows.append(vals)
    if not rows:
        raise TrajectoryFileError(p, None, "no poses in file")
    mat = np.array(rows, dtype=np.float64)
    q = mat[:, 4:8] / np.linalg.norm(mat[:, 4:8], axis=1, keepdims=True)
    return Trajectory(mat[:, 0].copy(), mat[:, 1:4].copy(), q)


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write a :class:`Trajectory` as a TUM file (stamps with nanosecond precision)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, pos, q in zip(traj.stamps_s, traj.positions_m, traj.quat_xyzw, strict=False):
        lines.append(
            f"{t:.9f} {pos[0]:.9f} {pos[1]:.9f} {pos[2]:.9f} "
            f"{q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}"
        )
    out.write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_tum_planar(path: str | Path, stamps_s: np.ndarray, xytheta: np.ndarray) -> None:
    """Write planar poses (N, 3) (x, y, theta) at z = 0 as a TUM file."""
    write_tum(path, Trajectory.from_planar(stamps_s, xytheta))


def write_estimates_tum(path: str | Path, estimates: Sequence[Any]) -> int:
    """Write pose messages (anything with ``stamp_ns``, ``x``, ``y``, ``theta``, e.g.
    :class:`protocol.messages.PoseEstimate`) as a planar TUM file, sorted by stamp, one line per
    stamp (the last message of a stamp wins). Returns the number of poses written."""
    by_stamp = {int(e.stamp_ns): (float(e.x), float(e.y), float(e.theta)) for e in estimates}
    stamps = np.array(sorted(by_stamp), dtype=np.int64)
    poses = np.array([by_stamp[int(s)] for s in stamps], dtype=np.float64).reshape(-1, 3)
    write_tum_planar(path, stamps * 1e-9, poses)
    return len(stamps)
