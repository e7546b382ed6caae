"""TUM trajectory files: one pose per line, ``stamp_s tx ty tz qx qy qz qw``.

Blank lines and lines starting with ``#`` are ignored. Errors name the file and the line.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from protocol.errors import SmartedgeError
from smartedge.evaluation.metrics import Trajectory

log = logging.getLogger(__name__)


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
