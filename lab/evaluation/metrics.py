"""Trajectory metrics: Umeyama/Procrustes alignment and absolute pose errors (pure numpy).

Conventions: positions are (N, d) arrays in metres (d = 2 for planar, 3 for spatial), planar
headings (N,) in radians, rotations (N, 3, 3). An alignment maps the *estimate* onto the
*reference* (ground truth): ``p_ref ≈ scale * R @ p_est + t``, as in Umeyama (1991) and evo.

The statistics printed by ``smartedge evaluate ate`` are those of ``evo_ape`` (max, mean, median,
min, rmse, sse, std) computed the same way, so the two can be compared number for number.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping, Sequence

import numpy as np

from core.geometry import (
    wrap_angle_array,
    yaw_from_rotation,
)
from core.trajectory import Trajectory
from protocol.errors import SmartedgeError

log = logging.getLogger(__name__)


class MetricsError(SmartedgeError, ValueError):
    """Inputs that cannot be evaluated (too few poses, degenerate geometry, no matches)."""


# --------------------------------------------------------------------------------------------
# alignment
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Alignment:
    """A similarity transform ``p_ref = scale * R @ p_est + t``.

    ``R``: (d, d) rotation, ``t``: (d,) metres, ``scale``: dimensionless (1 for SE(d)).
    """

    R: np.ndarray
    t: np.ndarray
    scale: float = 1.0

    @property
    def dim(self) -> int:
        return int(self.R.shape[0])

    def apply_points(self, points: np.ndarray) -> np.ndarray:
        """(N, d) estimate positions → (N, d) positions in the reference frame."""
        pts = np.asarray(points, dtype=np.float64)
        return self.scale * pts @ self.R.T + self.t

    def apply_rotations(self, rotations: np.ndarray) -> np.ndarray:
        """(N, d, d) estimate orientations → (N, d, d) orientations in the reference frame."""
        return np.einsum("ij,njk->nik", self.R, np.asarray(rotations, dtype=np.float64))

    @property
    def yaw_rad(self) -> float:
        """Rotation about z of the alignment (planar part), radians."""
        return yaw_from_rotation(self.R)

    def matrix(self) -> np.ndarray:
        """(d+1, d+1) homogeneous similarity matrix."""
        d = self.dim
        out = np.eye(d + 1)
        out[:d, :d] = self.scale * self.R
        out[:d, d] = self.t
        return out


def umeyama_alignment(
    est_points: np.ndarray, ref_points: np.ndarray, with_scale: bool = False
) -> Alignment:
    """Least-squares similarity (or rigid, ``with_scale=False``) transform taking
    ``est_points`` (N, d) onto ``ref_points`` (N, d) (Umeyama 1991, Procrustes analysis).

    Works for any d >= 2: d = 2 gives SE(2)/Sim(2), d = 3 gives SE(3)/Sim(3).
    Raises :class:`MetricsError` for fewer than 2 points or degenerate (all equal) points.
    """
    x = np.asarray(est_points, dtype=np.float64)
    y = np.asarray(ref_points, dtype=np.float64)
    if x.ndim != 2 or x.shape != y.shape:
        raise MetricsError(f"point sets must be (N, d) of equal shape, got {x.shape}, {y.shape}")
    n, d = x.shape
    if n < 2 or d < 2:
        raise MetricsError(f"need at least 2 points of dimension >= 2, got {x.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise MetricsError("point sets contain NaN or infinity")
    mean_x, mean_y = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mean_x, y - mean_y
    sigma_x = float(np.mean(np.sum(xc * xc, axis=1)))
    if sigma_x < 1e-18:
        raise MetricsError("estimate points are all identical: alignment is undefined")
    cov = yc.T @ xc / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(d)
    # Reflection guard: force det(R) = +1 (proper rotation).
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[d - 1, d - 1] = -1.0
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(D) @ S) / sigma_x) if with_scale else 1.0
    t = mean_y - scale * R @ mean_x
    return Alignment(R=R, t=t, scale=scale)


def align_planar(
    est_xytheta: np.ndarray, ref_xytheta: np.ndarray, with_scale: bool = False
) -> tuple[np.ndarray, Alignment]:
    """SE(2) (or Sim(2)) alignment of planar poses (N, 3) = (x, y, theta).

    Returns the aligned estimate poses (N, 3) in the reference frame and the alignment.
    """
    est = np.asarray(est_xytheta, dtype=np.float64).reshape(-1, 3)
    ref = np.asarray(ref_xytheta, dtype=np.float64).reshape(-1, 3)
    al = umeyama_alignment(est[:, :2], ref[:, :2], with_scale=with_scale)
    out = np.empty_like(est)
    out[:, :2] = al.apply_points(est[:, :2])
    out[:, 2] = wrap_angle_array(est[:, 2] + al.yaw_rad)
    return out, al


# --------------------------------------------------------------------------------------------
# errors and statistics
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ErrorStats:
    """Statistics of an error vector (the set evo prints), in the error's unit."""

    max: float
    mean: float
    median: float
    min: float
    rmse: float
    sse: float
    std: float
    count: int

    def as_dict(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in ("max", "mean", "median", "min", "rmse", "sse",
                                              "std")}


def error_stats(errors: np.ndarray) -> ErrorStats:
    """Statistics of a 1-D error array; NaN entries are ignored. An empty input gives NaNs."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    e = e[np.isfinite(e)]
    if e.size == 0:
        nan = math.nan
        return ErrorStats(nan, nan, nan, nan, nan, nan, nan, 0)
    sse = float(np.dot(e, e))
    return ErrorStats(
        max=float(e.max()), mean=float(e.mean()), median=float(np.median(e)), min=float(e.min()),
        rmse=math.sqrt(sse / e.size), sse=sse, std=float(e.std()), count=int(e.size),
    )


def rms(errors: np.ndarray) -> float:
    """Root mean square of the finite entries of ``errors`` (NaN if none)."""
    return error_stats(errors).rmse


def translation_errors(ref_points: np.ndarray, est_points: np.ndarray) -> np.ndarray:
    """(N,) Euclidean distances between (N, d) reference and estimate positions, metres."""
    return np.linalg.norm(np.asarray(ref_points, float) - np.asarray(est_points, float), axis=1)


def heading_errors(ref_theta_rad: np.ndarray, est_theta_rad: np.ndarray) -> np.ndarray:
    """(N,) absolute planar heading differences in radians, in [0, pi]."""
    diff = np.asarray(est_theta_rad, float) - np.asarray(ref_theta_rad, float)
    return np.abs(wrap_angle_array(diff))


def rotation_angle_errors(ref_R: np.ndarray, est_R: np.ndarray) -> np.ndarray:
    """(N,) angles (radians) of ``ref_R[i]^T est_R[i]`` for (N, 3, 3) rotation stacks."""
    rel = np.einsum("nji,njk->nik", np.asarray(ref_R, float), np.asarray(est_R, float))
    cos = (np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def travelled_distance(points: np.ndarray) -> np.ndarray:
    """(N,) cumulative path length (metres) along (N, d) positions, starting at 0."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros(0)
    steps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


# --------------------------------------------------------------------------------------------
# trajectories and APE
# --------------------------------------------------------------------------------------------


def match_stamps(
    stamps_a: np.ndarray, stamps_b: np.ndarray, max_diff_s: float = 0.01
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (ia, ib) of nearest stamps within ``max_diff_s``.

    Like ``evo``'s association: every pose of the trajectory with fewer poses (the second on a
    tie) looks up its nearest stamp in the other one (ties go to the earlier stamp); pairs
    further apart than ``max_diff_s`` are dropped. Returns index arrays into ``stamps_a`` and
    ``stamps_b``.
    """
    a = np.asarray(stamps_a, dtype=np.float64)
    b = np.asarray(stamps_b, dtype=np.float64)
    # evo iterates over the second trajectory unless the first one has fewer poses.
    swap = not len(b) > len(a)
    short, long_ = (b, a) if swap else (a, b)
    i_short: list[int] = []
    i_long: list[int] = []
    if len(long_) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    if np.all(np.diff(long_) >= 0):
        pos = np.searchsorted(long_, short, side="right")
        for i, (s, j) in enumerate(zip(short, pos, strict=False)):
            if s < long_[0] - max_diff_s or s > long_[-1] + max_diff_s:
                continue
            j = min(int(j), len(long_) - 1)
            d_up = long_[j] - s
            d_lo = s - long_[j - 1] if j > 0 else math.inf
            if d_up <= max_diff_s and d_up < d_lo:
                best = j
            elif d_lo <= max_diff_s and d_lo <= d_up:
                best = j - 1
            else:
                continue
            i_short.append(i)
            i_long.append(best)
    else:
        for i, s in enumerate(short):
            d = np.abs(long_ - s)
            j = int(np.argmin(d))
            if d[j] <= max_diff_s:
                i_short.append(i)
                i_long.append(j)
    ia, ib = (np.array(i_long), np.array(i_short)) if swap else (np.array(i_short),
                                                                  np.array(i_long))
    return ia.astype(np.int64), ib.astype(np.int64)


@dataclasses.dataclass(frozen=True, eq=False)
class ApeResult:
    """Absolute pose error of an estimate against a reference.

    ``translation_m``: (N,) per-pose position errors after alignment; ``rotation_rad``: (N,)
    per-pose rotation angle errors; ``alignment``: what was applied to the estimate (identity
    when not aligned); ``ref_index``/``est_index``: the matched pose indices.
    """

    translation_m: np.ndarray
    rotation_rad: np.ndarray
    alignment: Alignment
    ref_index: np.ndarray
    est_index: np.ndarray

    @property
    def translation_stats(self) -> ErrorStats:
        return error_stats(self.translation_m)

    @property
    def rotation_stats_deg(self) -> ErrorStats:
        return error_stats(np.rad2deg(self.rotation_rad))


def ape(
    ref: Trajectory,
    est: Trajectory,
    align: bool = False,
    correct_scale: bool = False,
    max_diff_s: float = 0.01,
) -> ApeResult:
    """APE of ``est`` against ``ref`` as ``evo_ape tum REF EST [--align] [--correct_scale]``:
    poses associated by nearest stamp (``max_diff_s``), then optionally aligned with Umeyama on
    the 3D positions (SE(3), or Sim(3) with ``correct_scale``), then per-pose errors.

    Raises :class:`MetricsError` when no stamps match or the alignment is degenerate.
    """
    ia, ib = match_stamps(ref.stamps_s, est.stamps_s, max_diff_s)
    if len(ia) == 0:
        raise MetricsError(f"no matching stamps within {max_diff_s} s between the trajectories")
    r, e = ref.subset(ia), est.subset(ib)
    if align or correct_scale:
        al = umeyama_alignment(e.positions_m, r.positions_m, with_scale=correct_scale)
        if not align:  # scale only, as evo does for --correct_scale alone
            al = Alignment(np.eye(3), np.zeros(3), al.scale)
    else:
        al = Alignment(np.eye(3), np.zeros(3), 1.0)
    est_pos = al.apply_points(e.positions_m)
    est_R = al.apply_rotations(e.rotations())
    return ApeResult(
        translation_m=translation_errors(r.positions_m, est_pos),
        rotation_rad=rotation_angle_errors(r.rotations(), est_R),
        alignment=al,
        ref_index=ia,
        est_index=ib,
    )


# --------------------------------------------------------------------------------------------
# grouping for the paper's tables
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MeanStd:
    """Mean and (population) standard deviation of a sample, with its size."""

    mean: float
    std: float
    count: int


def mean_std(values: np.ndarray | Sequence[float]) -> MeanStd:
    """Mean ± std of the finite entries (NaN, NaN, 0 when there are none)."""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return MeanStd(math.nan, math.nan, 0)
    return MeanStd(float(v.mean()), float(v.std()), int(v.size))


def group_by_camera_count(
    errors: np.ndarray, camera_counts: np.ndarray, groups: Sequence[int] = (1, 2, 4)
) -> dict[int | str, MeanStd]:
    """Per-waypoint errors (N,) grouped by how many cameras saw the robot there (N,) ints.

    Returns ``{count: MeanStd}`` for each requested group plus ``"average"`` over all entries
    whose count is in ``groups`` (waypoints seen by no camera are excluded everywhere).
    """
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    c = np.asarray(camera_counts, dtype=np.int64).reshape(-1)
    if e.shape != c.shape:
        raise MetricsError(f"errors {e.shape} and camera counts {c.shape} differ in length")
    out: dict[int | str, MeanStd] = {g: mean_std(e[c == g]) for g in groups}
    out["average"] = mean_std(e[np.isin(c, list(groups))])
    return out


def error_over_distance(
    ref_xy: np.ndarray, est_xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(distance travelled along the reference (N,), translation error (N,)), metres."""
    return travelled_distance(ref_xy), translation_errors(ref_xy, est_xy)


def format_stats(stats: ErrorStats | Mapping[str, float]) -> str:
    """evo-like multi-line listing of statistics."""
    d = stats.as_dict() if isinstance(stats, ErrorStats) else dict(stats)
    return "\n".join(f"{k:>10}\t{v:.6f}" for k, v in d.items())
