"""Plain-numpy geometry shared by every floor: angles, SE(2), SE(3), quaternions, the OpenCV
lens distortion model (and its inverse) and the static-robot detector.

Only numpy, math and dataclasses are imported, so an edge board can use it.

Conventions:

- Angles are radians. :func:`wrap_angle` maps into **[-pi, pi)**, everywhere (``pi`` itself
  becomes ``-pi``); the remainder is computed exactly (``fmod``), so wrapping is idempotent.
- A planar pose is ``(x, y, theta)`` in metres and radians, REP-103 axes; as a transform it
  maps the body frame into the frame it is expressed in (``T_world_robot``).
- ``se2_*`` take and return planar poses as (3,) arrays; :func:`se2_matrix` builds the (3, 3)
  homogeneous matrix, :func:`se3_from_planar` the (4, 4) one at z = 0.
- Quaternions are ``(x, y, z, w)`` (ROS, scipy, TUM order).
- Rotations from roll, pitch, yaw are ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (ROS ``RPY``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Final

import numpy as np

from protocol.messages import NS_PER_S

_TAU: Final = 2.0 * math.pi

# --------------------------------------------------------------------------------------------
# angles
# --------------------------------------------------------------------------------------------


def wrap_angle(angle_rad: float) -> float:
    """``angle_rad`` wrapped into [-pi, pi). NaN and infinities give NaN."""
    if not math.isfinite(angle_rad):
        return math.nan
    r = math.fmod(angle_rad, _TAU)  # exact; then Sterbenz makes the shifts below exact too
    if r >= math.pi:
        return r - _TAU
    if r < -math.pi:
        return r + _TAU
    return float(r)


def wrap_angle_array(angles_rad: np.ndarray | float) -> np.ndarray:
    """Vectorized :func:`wrap_angle`: any shape, float64 out, values in [-pi, pi), bit-for-bit
    the scalar result. NaN and infinities give NaN."""
    a = np.asarray(angles_rad, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        r = np.fmod(a, _TAU)
        return np.where(r >= math.pi, r - _TAU, np.where(r < -math.pi, r + _TAU, r))


def angle_diff(a_rad: float, b_rad: float) -> float:
    """Signed smallest rotation from ``b_rad`` to ``a_rad``: ``wrap_angle(a - b)`` in [-pi, pi)."""
    return wrap_angle(a_rad - b_rad)


# --------------------------------------------------------------------------------------------
# rotations and quaternions
# --------------------------------------------------------------------------------------------


def rotation_z(yaw_rad: float) -> np.ndarray:
    """(3, 3) rotation by ``yaw_rad`` about +z."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_from_rpy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """(3, 3) ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rotation_z(yaw_rad) @ Ry @ Rx


def rotation_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """(3,) rotation vector (axis * angle, rad) → (3, 3) rotation (Rodrigues' formula)."""
    v = np.asarray(rotvec, dtype=np.float64).reshape(3)
    th = float(np.linalg.norm(v))
    if th < 1e-15:
        return np.eye(3)
    k = v / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * K @ K


def rotvec_from_rotation(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation → (3,) rotation vector (axis * angle, rad), the inverse of
    :func:`rotation_from_rotvec` for angles below ~179 deg (the axis of a half turn is not
    recovered)."""
    R = np.asarray(R, dtype=np.float64)
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = float(np.linalg.norm(axis)) / 2.0  # sin(angle)
    angle = math.atan2(s, (float(np.trace(R[:3, :3])) - 1.0) / 2.0)
    if s < 1e-12:
        return axis / 2.0
    return axis * (angle / (2.0 * s))


def rpy_from_rotation(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of a (3, 3) rotation, inverse of :func:`rotation_from_rpy` for
    ``|pitch| < pi / 2``; yaw in [-pi, pi)."""
    pitch = math.asin(max(-1.0, min(1.0, -float(R[2, 0]))))
    roll = math.atan2(float(R[2, 1]), float(R[2, 2]))
    return roll, pitch, yaw_from_rotation(R)


def yaw_from_rotation(R: np.ndarray) -> float:
    """Heading in [-pi, pi) of the body x axis projected onto the xy plane, from a (2, 2),
    (3, 3) or (4, 4) rotation / homogeneous transform."""
    return wrap_angle(math.atan2(float(R[1, 0]), float(R[0, 0])))


def quaternion_to_rotation(q_xyzw: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (x, y, z, w) → (..., 3, 3) rotation matrices. Normalised first;
    a zero quaternion gives NaN."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rotation_to_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w), ``w >= 0``, of a (3, 3) rotation (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)[:3, :3]
    tr = float(np.trace(m))
    diag = np.diag(m)
    i = int(np.argmax(diag))
    if tr >= diag[i]:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = [m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], 0.25 * s * s]
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + m[i, i] - m[j, j] - m[k, k], 0.0))
        q = [0.0, 0.0, 0.0, m[k, j] - m[j, k]]
        q[i] = 0.25 * s * s
        q[j] = m[j, i] + m[i, j]
        q[k] = m[k, i] + m[i, k]
    v = np.asarray(q) / s
    v /= np.linalg.norm(v)
    if v[3] < 0.0:
        v = -v
    return float(v[0]), float(v[1]), float(v[2]), float(v[3])


def yaw_to_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    """Planar heading (about +z) → unit quaternion (x, y, z, w)."""
    half = 0.5 * float(yaw_rad)
    return 0.0, 0.0, math.sin(half), math.cos(half)


def yaw_to_quaternion_array(yaw_rad: np.ndarray) -> np.ndarray:
    """(N,) headings → (N, 4) unit quaternions (x, y, z, w)."""
    half = 0.5 * np.asarray(yaw_rad, dtype=np.float64).reshape(-1)
    zero = np.zeros_like(half)
    return np.stack([zero, zero, np.sin(half), np.cos(half)], axis=1)


def quaternion_to_yaw(x: float, y: float, z: float, w: float) -> float:
    """Yaw in [-pi, pi) of a quaternion (x, y, z, w); it need not be normalised.

    Raises ``ValueError`` when it is zero or not finite.
    """
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"invalid quaternion {[x, y, z, w]}")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return wrap_angle(math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


# --------------------------------------------------------------------------------------------
# SE(2): planar poses (x, y, theta)
# --------------------------------------------------------------------------------------------


def se2_matrix(x: float, y: float, theta_rad: float) -> np.ndarray:
    """(3, 3) homogeneous matrix of the planar pose (x, y, theta)."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[c, -s, float(x)], [s, c, float(y)], [0.0, 0.0, 1.0]])


def se2_from_matrix(T: np.ndarray) -> np.ndarray:
    """(3,) planar pose (x, y, theta in [-pi, pi)) of a (3, 3) SE(2) matrix, or of a (4, 4)
    transform projected onto the floor (translation x, y; heading of the body x axis)."""
    m = np.asarray(T, dtype=np.float64)
    return np.array([m[0, -1], m[1, -1], yaw_from_rotation(m)])


def se3_from_planar(x: float, y: float, theta_rad: float) -> np.ndarray:
    """(4, 4) homogeneous transform of the planar pose (x, y, theta) at z = 0."""
    T = np.eye(4)
    T[:3, :3] = rotation_z(theta_rad)
    T[0, 3], T[1, 3] = float(x), float(y)
    return T


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a ⊕ b``: the pose ``b`` (given in the frame of ``a``) in the frame ``a`` is given in;
    (3,) poses, theta wrapped."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1],
                     wrap_angle(float(a[2] + b[2]))])


def se2_inverse(a: np.ndarray) -> np.ndarray:
    """``a⁻¹`` of a (3,) planar pose, theta wrapped."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], wrap_angle(-float(a[2]))])


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ ⊕ b``: the (3,) pose ``b`` expressed in the frame of ``a`` (both in one frame)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, angle_diff(float(b[2]), float(a[2]))])


# --------------------------------------------------------------------------------------------
# SE(3)
# --------------------------------------------------------------------------------------------


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform (``T_a_b`` → ``T_b_a``)."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


# --------------------------------------------------------------------------------------------
# lens distortion
# --------------------------------------------------------------------------------------------


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(position difference m, rotation angle deg) between two (4, 4) poses of the same frame,
    e.g. an estimated and a true ``T_world_cam``."""
    A, B = np.asarray(T_a, np.float64), np.asarray(T_b, np.float64)
    dp = float(np.linalg.norm(A[:3, 3] - B[:3, 3]))
    dR = A[:3, :3].T @ B[:3, :3]
    s = float(np.linalg.norm([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]))
    return dp, math.degrees(math.atan2(s / 2.0, (float(np.trace(dR)) - 1.0) / 2.0))


def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply the OpenCV radial-tangential (and rational) distortion to normalized image
    coordinates.

    ``xy``: (..., 2) normalized coordinates (x/z, y/z). ``dist``: OpenCV coefficients
    (k1, k2, p1, p2[, k3[, k4, k5, k6]]) along the last axis, 0, 4, 5 or 8 of them; leading
    axes broadcast against ``xy``'s (one row per camera, say). Returns (..., 2) distorted
    normalized coordinates, what ``cv2.projectPoints`` computes before applying K.
    """
    xy = np.asarray(xy, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64)
    n = dist.shape[-1] if dist.ndim else 0
    if n == 0:
        return xy
    if n > 8:
        raise ValueError(f"{n} distortion coefficients; OpenCV's model has at most 8 here")
    d = np.zeros((*dist.shape[:-1], 8))
    d[..., :n] = dist
    k1, k2, p1, p2, k3, k4, k5, k6 = (d[..., i] for i in range(8))
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    r4, r6 = r2 * r2, r2 * r2 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def distort_normalized_jacobian(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(..., 2, 2) derivative of :func:`distort_normalized` with respect to its input, in closed
    form: row i is d(distorted coordinate i)/d(x, y).

    ``xy`` and ``dist`` as in :func:`distort_normalized` (leading axes broadcast). Without
    distortion coefficients the result is the identity.
    """
    xy = np.asarray(xy, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64)
    n = dist.shape[-1] if dist.ndim else 0
    if n > 8:
        raise ValueError(f"{n} distortion coefficients; OpenCV's model has at most 8 here")
    d = np.zeros((*dist.shape[:-1], 8)) if dist.ndim else np.zeros(8)
    d[..., :n] = dist
    k1, k2, p1, p2, k3, k4, k5, k6 = (d[..., i] for i in range(8))
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    dradial_dr2 = (dnum * den - num * dden) / (den * den)
    out = np.empty((*np.broadcast_shapes(x.shape, k1.shape), 2, 2))
    out[..., 0, 0] = radial + 2 * x * x * dradial_dr2 + 2 * p1 * y + 6 * p2 * x
    out[..., 0, 1] = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
    out[..., 1, 0] = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
    out[..., 1, 1] = radial + 2 * y * y * dradial_dr2 + 6 * p1 * y + 2 * p2 * x
    return out


def undistort_normalized(xy_distorted: np.ndarray, dist: np.ndarray, *,
                         iterations: int = 20, tol: float = 1e-12) -> np.ndarray:
    """Invert :func:`distort_normalized`: (..., 2) distorted normalized coordinates (what
    ``K^-1 [u, v, 1]`` gives for an image pixel) → (..., 2) undistorted normalized coordinates
    (x/z, y/z of the ray in the camera optical frame).

    Newton iterations on the exact model with a finite-difference 2x2 Jacobian, starting from the
    distorted coordinates; unlike ``cv2.undistortPoints``' fixed-point loop it converges to
    1e-12 for strong distortion too. Points without a preimage inside the lens's fold radius
    (:func:`lens_fold_radius`), or that do not converge, are NaN. ``dist`` as in
    :func:`distort_normalized` (one coefficient vector).
    """
    target = np.asarray(xy_distorted, dtype=np.float64)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    if dist.size == 0 or not np.any(dist):
        return target.copy()
    shape = target.shape
    t = target.reshape(-1, 2)
    x = t.copy()
    eps = 1e-7
    ex, ey = np.array([eps, 0.0]), np.array([0.0, eps])
    with np.errstate(all="ignore"):
        for _ in range(iterations):
            f = distort_normalized(x, dist) - t
            if np.all(np.abs(f[np.isfinite(f)]) < tol):
                break
            jx = (distort_normalized(x + ex, dist) - distort_normalized(x - ex, dist)) / (2 * eps)
            jy = (distort_normalized(x + ey, dist) - distort_normalized(x - ey, dist)) / (2 * eps)
            det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
            dx = (jy[:, 1] * f[:, 0] - jy[:, 0] * f[:, 1]) / det
            dy = (-jx[:, 1] * f[:, 0] + jx[:, 0] * f[:, 1]) / det
            x = x - np.stack([dx, dy], axis=-1)
        residual = np.max(np.abs(distort_normalized(x, dist) - t), axis=-1)
        bad = ~(residual < 1e-9) | ~(np.hypot(x[:, 0], x[:, 1]) < lens_fold_radius(dist))
    x[bad] = np.nan
    return x.reshape(shape)


#: the fold search covers normalized radii up to this (about 87 degrees off-axis), in these steps
_FOLD_SEARCH_MAX_RADIUS: Final = 20.0
_FOLD_SEARCH_STEP: Final = 1e-3


def lens_fold_radius(dist: np.ndarray) -> float:
    """Normalized undistorted radius (of x/z, y/z) where the lens model's radial distortion stops
    growing with the radius; ``inf`` when it keeps growing (every physical lens).

    Beyond it the polynomial folds back: ``cv2.projectPoints`` puts points from outside the
    field of view into the image, where no real lens images them. The renderer leaves image
    pixels without a preimage inside this radius empty; keypoints beyond it are not in the
    image. Tangential terms (tiny for real lenses) are ignored. Cached per coefficient vector.
    """
    return _fold_radius(np.asarray(dist, np.float64).ravel()[:8].tobytes())


@functools.lru_cache(maxsize=64)
def _fold_radius(dist_bytes: bytes) -> float:
    coeffs = np.frombuffer(dist_bytes, np.float64)
    d = np.zeros(8)
    d[: len(coeffs)] = coeffs
    d[2:4] = 0.0  # radial part only
    if not np.any(d):
        return math.inf
    r = np.arange(1, int(_FOLD_SEARCH_MAX_RADIUS / _FOLD_SEARCH_STEP) + 1) * _FOLD_SEARCH_STEP
    with np.errstate(all="ignore"):
        r_d = distort_normalized(np.column_stack([r, np.zeros_like(r)]), d)[:, 0]
        growing = np.isfinite(r_d[1:]) & (np.diff(r_d) > 0)
    stop = np.flatnonzero(~growing)
    return float(r[stop[0]]) if len(stop) else math.inf


# --------------------------------------------------------------------------------------------
# static detection
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class MotionState:
    """Result of static detection after the latest odometry sample.

    ``still_since_ns``: stamp of the first sample of the current run of below-threshold
    samples (``None`` while moving). ``is_static``: that run lasted the dwell time.
    ``stop_id``: number of stops so far; the current stop's id while static.
    """

    stamp_ns: int | None = None
    still_since_ns: int | None = None
    is_static: bool = False
    stop_id: int = 0


class StaticDetector:
    """The one static-robot detector: odometry body velocities below thresholds for a dwell.

    The robot is *static* when its speed stayed ``<= max_speed_mps`` and its yaw rate
    ``<= max_yaw_rate_radps`` for at least ``dwell_s``; every such still period is one *stop*
    (numbered by ``stop_id``); any sample above the thresholds ends it. Velocities are the
    ones the robot reports (its wheel odometry twist), which do not suffer from the
    quantisation of differentiating poses at high rate. Time is the samples' stamps only.
    """

    def __init__(self, max_speed_mps: float, max_yaw_rate_radps: float, dwell_s: float) -> None:
        self.max_speed_mps = float(max_speed_mps)
        self.max_yaw_rate_radps = float(max_yaw_rate_radps)
        self.dwell_s = float(dwell_s)
        self._dwell_ns = round(self.dwell_s * NS_PER_S)
        self._state = MotionState()

    @classmethod
    def from_thresholds(cls, thresholds: object) -> StaticDetector:
        """Build from an object with ``static_max_speed_mps``, ``static_max_yaw_rate_radps``
        and ``static_dwell_s`` (a :class:`core.site.Thresholds`)."""
        return cls(
            thresholds.static_max_speed_mps,  # type: ignore[attr-defined]
            thresholds.static_max_yaw_rate_radps,  # type: ignore[attr-defined]
            thresholds.static_dwell_s,  # type: ignore[attr-defined]
        )

    @property
    def state(self) -> MotionState:
        return self._state

    def update(self, stamp_ns: int, vx_mps: float, vy_mps: float, wz_radps: float) -> MotionState:
        """Feed one odometry sample (stamps increasing); returns the new state."""
        prev = self._state
        still = (
            math.hypot(vx_mps, vy_mps) <= self.max_speed_mps
            and abs(wz_radps) <= self.max_yaw_rate_radps
        )
        if not still:
            self._state = MotionState(stamp_ns, None, False, prev.stop_id)
            return self._state
        since = prev.still_since_ns if prev.still_since_ns is not None else stamp_ns
        is_static = stamp_ns - since >= self._dwell_ns
        stop_id = prev.stop_id + 1 if is_static and not prev.is_static else prev.stop_id
        self._state = MotionState(stamp_ns, since, is_static, stop_id)
        return self._state
