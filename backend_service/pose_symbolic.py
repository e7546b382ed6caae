"""Paper Eq. 2 as CasADi expressions: the robot's rotation and translation from ``q``, the
OpenCV projection with its Jacobian written out by the chain rule, the robust losses, the
Gauss-Newton normal equations, and the per-camera kernels (one per keypoint count, DoF and loss,
the camera and the robot model as inputs) that :mod:`backend_service.compiled_functions`
compiles once per machine. :class:`~backend_service.pose_solver.PoseProblem` assembles a camera
set's problem from these.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final

import casadi as ca
import numpy as np

from backend_service.compiled_functions import compiled
from core.camera import CameraModel
from core.projection import SOLVER_MIN_DEPTH_M


def rotation_sym(q: ca.SX, dof: int) -> tuple[ca.SX, ca.SX]:
    """(R (3x3), t (3x1)) of T_world_robot(q)."""
    if dof == 3:
        c, s = ca.cos(q[2]), ca.sin(q[2])
        R = ca.vertcat(ca.horzcat(c, -s, 0), ca.horzcat(s, c, 0), ca.horzcat(0, 0, 1))
        t = ca.vertcat(q[0], q[1], 0)
        return R, t
    roll, pitch, yaw = q[3], q[4], q[5]
    cr, sr, cp, sp, cy, sy = (ca.cos(roll), ca.sin(roll), ca.cos(pitch), ca.sin(pitch),
                              ca.cos(yaw), ca.sin(yaw))
    Rz = ca.vertcat(ca.horzcat(cy, -sy, 0), ca.horzcat(sy, cy, 0), ca.horzcat(0, 0, 1))
    Ry = ca.vertcat(ca.horzcat(cp, 0, sp), ca.horzcat(0, 1, 0), ca.horzcat(-sp, 0, cp))
    Rx = ca.vertcat(ca.horzcat(1, 0, 0), ca.horzcat(0, cr, -sr), ca.horzcat(0, sr, cr))
    return Rz @ Ry @ Rx, ca.vertcat(q[0], q[1], q[2])


def project_cam_sym(camera: CameraModel, pc: ca.SX) -> tuple[ca.SX, ca.SX]:
    """Distorted pixels (M x 2) and depths (M x 1) of camera-frame points (M x 3), OpenCV
    model (the same maths as :meth:`core.camera.CameraModel.project_cam`)."""
    z = pc[:, 2]
    zs = ca.fmax(z, SOLVER_MIN_DEPTH_M)
    x = pc[:, 0] / zs
    y = pc[:, 1] / zs
    d = np.zeros(8)
    d[: camera.dist.size] = camera.dist
    if np.any(d != 0.0):
        k1, k2, p1, p2, k3, k4, k5, k6 = (float(v) for v in d)
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        radial = (1 + k1 * r2 + k2 * r4 + k3 * r6)
        if k4 != 0.0 or k5 != 0.0 or k6 != 0.0:
            radial = radial / (1 + k4 * r2 + k5 * r4 + k6 * r6)
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    else:
        xd, yd = x, y
    K = camera.K
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    return ca.horzcat(u, v), z


def project_with_jacobian_sym(camera: CameraModel, pc: ca.SX,
                               dpc_dq: tuple[ca.SX, ca.SX, ca.SX]) -> tuple[ca.SX, ...]:
    """Distorted pixels of camera-frame points ``pc`` (M x 3) and their Jacobians w.r.t. the
    pose, given ``dpc_dq`` = (dX, dY, dZ), each (M x dof), by the chain rule: pixel <-
    distorted normalized <- normalized <- camera point <- pose. Returns u, v (M x 1) and
    du, dv (M x dof). The same model as :func:`project_cam_sym` (tested against CasADi's AD);
    written out because the shared 2x2 distortion Jacobian needs about 30 % fewer
    instructions than forward AD through the distortion once per pose direction. The
    camera's coefficients are constants here: terms of zero coefficients are left out."""
    d = np.zeros(8)
    d[: camera.dist.size] = camera.dist
    K = camera.K
    return _projection_with_jacobian(
        (float(K[0, 0]), float(K[0, 1]), float(K[0, 2]), float(K[1, 1]), float(K[1, 2])),
        tuple(float(v) for v in d), pc, dpc_dq,
        distorted=bool(np.any(d != 0.0)), rational=bool(np.any(d[5:] != 0.0)))


def _projection_with_jacobian(k: Sequence, dist: Sequence, pc: ca.SX,
                              dpc_dq: tuple[ca.SX, ca.SX, ca.SX], *, distorted: bool = True,
                              rational: bool = True) -> tuple[ca.SX, ...]:
    """:func:`project_with_jacobian_sym` for intrinsics ``k`` = (fx, skew, cx, fy, cy) and
    the 8 OpenCV coefficients ``dist`` = (k1, k2, p1, p2, k3, k4, k5, k6), numbers or
    symbols. ``distorted`` / ``rational``: False leaves out the distortion / its denominator
    (only right when those coefficients are zero)."""
    dof = dpc_dq[0].shape[1]

    def cols(e: ca.SX) -> ca.SX:  # (M x 1) -> (M x dof) for elementwise products
        return ca.repmat(e, 1, dof)

    X, Y, Z = pc[:, 0], pc[:, 1], pc[:, 2]
    iz = 1.0 / ca.fmax(Z, SOLVER_MIN_DEPTH_M)
    x = X * iz
    y = Y * iz
    dZ = dpc_dq[2] * cols(Z > SOLVER_MIN_DEPTH_M)  # the clamp's derivative
    dx = cols(iz) * (dpc_dq[0] - cols(x) * dZ)
    dy = cols(iz) * (dpc_dq[1] - cols(y) * dZ)
    if distorted:
        k1, k2, p1, p2, k3, k4, k5, k6 = dist
        r2 = x * x + y * y
        num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dnum = k1 + r2 * (2 * k2 + r2 * (3 * k3))
        if rational:
            den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
            radial = num / den
            dradial = (dnum - radial * (k4 + r2 * (2 * k5 + r2 * (3 * k6)))) / den
        else:
            radial, dradial = num, dnum
        xy = x * y
        xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
        d00 = cols(radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x)
        d01 = cols(2 * xy * dradial + 2 * p1 * x + 2 * p2 * y)
        d11 = cols(radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x)
        dxd = d00 * dx + d01 * dy
        dyd = d01 * dx + d11 * dy
    else:
        xd, yd, dxd, dyd = x, y, dx, dy
    fx, skew, cx, fy, cy = k
    u = fx * xd + skew * yd + cx
    v = fy * yd + cy
    du = fx * dxd + skew * dyd
    dv = fy * dyd
    return u, v, du, dv


def rho_sym(s: ca.SX, c: ca.SX, loss: str) -> ca.SX:
    if loss == "huber":
        c2 = c * c
        return ca.if_else(s <= c2, s, 2 * c * ca.sqrt(ca.fmax(s, 1e-300)) - c2)
    if loss == "cauchy":
        c2 = c * c
        return c2 * ca.log1p(s / c2)
    return s


def _rho_derivatives_sym(s: ca.SX, c: ca.SX, loss: str) -> tuple[ca.SX, ca.SX, ca.SX]:
    """(rho(s), rho'(s), rho''(s)) elementwise."""
    if loss == "huber":
        c2 = c * c
        root = ca.sqrt(ca.fmax(s, 1e-300))
        inside = s <= c2
        return (ca.if_else(inside, s, 2 * c * root - c2),
                ca.if_else(inside, 1.0, c / root),
                ca.if_else(inside, 0.0, -0.5 * c / (root * s)))
    if loss == "cauchy":
        c2 = c * c
        d = 1.0 / (1.0 + s / c2)
        return c2 * ca.log1p(s / c2), d, -d * d / c2
    return s, ca.DM.ones(s.shape), ca.DM.zeros(s.shape)


def normal_equations_sym(ru: ca.SX, rv: ca.SX, Ju: ca.SX, Jv: ca.SX, c: ca.SX, loss: str,
                          dof: int) -> tuple[ca.SX, ca.SX, ca.SX]:
    """Cost, gradient and Gauss-Newton normal matrix of ``1/2 sum_k rho(|r_k|^2)``.

    ``ru``, ``rv`` (K,) weighted residuals r_k = (ru_k, rv_k) of the K keypoints, ``Ju``,
    ``Jv`` (K, dof) their Jacobians w.r.t. the pose (J_k has rows Ju_k, Jv_k).
    Per keypoint k with s = |r_k|^2 and a = J_k^T r_k: gradient ``rho' a``; normal matrix
    ``rho' J_k^T J_k + gamma a a^T`` with ``gamma = 2 rho''`` (the exact second-order term of
    the loss, second derivatives of r dropped as in Gauss-Newton) as long as the keypoint's
    2x2 curvature ``rho' I + 2 rho'' r r^T`` stays positive semi-definite, else its eigenvalue
    along r is clamped to 0 (``gamma = -rho'/s``; Huber's linear branch is exactly that).
    Without a loss this is plain J^T J, J^T r. Returns (cost (1,), gradient (dof,), upper
    triangle of the normal matrix row-major (dof*(dof+1)/2,)).
    """
    s = ru * ru + rv * rv
    a = Ju * ca.repmat(ru, 1, dof) + Jv * ca.repmat(rv, 1, dof)  # (K, dof) rows J_k^T r_k
    if loss == "none":
        cost = 0.5 * ca.sum1(s)
        grad = ca.sum1(a).T
        H = Ju.T @ Ju + Jv.T @ Jv
    else:
        rho, rho1, rho2 = _rho_derivatives_sym(s, c, loss)
        gamma = ca.if_else(rho1 + 2 * s * rho2 >= 0, 2 * rho2, -rho1 / ca.fmax(s, 1e-300))
        cost = 0.5 * ca.sum1(rho)
        grad = (rho1.T @ a).T
        R1 = ca.repmat(rho1, 1, dof)
        H = Ju.T @ (R1 * Ju) + Jv.T @ (R1 * Jv) + a.T @ (ca.repmat(gamma, 1, dof) * a)
    upper = [H[i, j] for i in range(dof) for j in range(i, dof)]
    return cost, grad, ca.vertcat(*upper)


#: camera parameters of the kernel: fx, skew, cx, fy, cy, 8 OpenCV coefficients,
#: R_cam_world (row-major), t_cam_world
_CAMERA_PARAMS: Final = 5 + 8 + 9 + 3


def camera_parameters(camera: CameraModel) -> np.ndarray:
    """The (25,) parameter vector of one camera for the compiled kernel."""
    d = np.zeros(8)
    d[: camera.dist.size] = camera.dist
    K, T = camera.K, camera.T_cam_world
    return np.concatenate([[K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]], d,
                           T[:3, :3].reshape(-1), T[:3, 3]])


def _one_camera_sym(num_keypoints: int, dof: int) -> tuple[list[ca.SX], tuple[ca.SX, ...]]:
    """The symbolic inputs ``[q, camera (25), observed pixels (2M), weights (M), keypoints
    (3M)]`` of one camera's kernel and, from them, (ru, rv (M), Ju, Jv (M x dof), depths (M)):
    the weighted pixel residuals of :meth:`PoseProblem.normal_equations_vm`, per camera, with
    the camera and the robot model as inputs instead of constants."""
    M = num_keypoints
    q = ca.SX.sym("q", dof)
    cam = ca.SX.sym("camera", _CAMERA_PARAMS)
    obs = ca.SX.sym("uv", 2 * M)
    w = ca.SX.sym("w", M)
    kps = ca.SX.sym("keypoints", 3 * M)
    R_wr, t_wr = rotation_sym(q, dof)
    R_cw = ca.reshape(cam[13:22], 3, 3).T
    kp = ca.reshape(kps, 3, M).T
    pts_cam = kp @ (R_cw @ R_wr).T + ca.repmat((R_cw @ t_wr + cam[22:25]).T, M, 1)
    dpc_dq = tuple(ca.jacobian(pts_cam[:, a], q) for a in range(3))  # AD: rigid motion
    u, v, du, dv = _projection_with_jacobian(
        tuple(cam[i] for i in range(5)), tuple(cam[5 + i] for i in range(8)), pts_cam, dpc_dq)
    o = ca.reshape(obs, 2, M).T
    sw = ca.sqrt(w)
    residuals = (sw * (u - o[:, 0]), sw * (v - o[:, 1]), ca.repmat(sw, 1, dof) * du,
                 ca.repmat(sw, 1, dof) * dv, pts_cam[:, 2])
    return [q, cam, obs, w, kps], residuals


def _camera_kernel_sym(num_keypoints: int, dof: int, loss: str) -> ca.Function:
    """``(q, camera (25), observed pixels (2M), weights (M), scale, keypoints (3M)) ->
    [cost, gradient, normal-matrix upper triangle]`` of ONE camera: what
    :meth:`PoseProblem.normal_equations_vm` sums over the cameras, so one compiled function
    serves every camera set."""
    (q, cam, obs, w, kps), (ru, rv, Ju, Jv, _) = _one_camera_sym(num_keypoints, dof)
    c = ca.SX.sym("c", 1)
    cost, grad, h_upper = normal_equations_sym(ru, rv, Ju, Jv, c, loss, dof)
    return ca.Function(f"pose_camera_kernel_m{num_keypoints}_dof{dof}_{loss}",
                       [q, cam, obs, w, c, kps], [ca.densify(ca.vertcat(cost, grad, h_upper))],
                       ["q", "camera", "uv", "w", "c", "keypoints"], ["normal_equations"])


def _residual_kernel_sym(num_keypoints: int, dof: int) -> ca.Function:
    """``(q, camera (25), observed pixels (2M), weights (M), keypoints (3M)) -> [weighted
    residuals (2M, u/v interleaved), their Jacobian (2M x dof), depths (M)]`` of ONE camera:
    what :meth:`PoseProblem.evaluate` returns, per camera (the Jacobian by the chain rule of
    :func:`_projection_with_jacobian`)."""
    M = num_keypoints
    (q, cam, obs, w, kps), (ru, rv, Ju, Jv, depth) = _one_camera_sym(M, dof)
    r = ca.reshape(ca.horzcat(ru, rv).T, 2 * M, 1)
    J = ca.vertcat(*[ca.vertcat(Ju[j, :], Jv[j, :]) for j in range(M)])
    return ca.Function(f"pose_residual_kernel_m{M}_dof{dof}", [q, cam, obs, w, kps],
                       [ca.densify(r), ca.densify(J), ca.densify(depth)],
                       ["q", "camera", "uv", "w", "keypoints"], ["residuals", "jacobian", "depth"])


def normal_equations_kernel(num_keypoints: int, dof: int, loss: str, wait: bool = False
                             ) -> tuple[ca.Function | None, bool]:
    return compiled(("normal_equations", num_keypoints, dof, loss),
                   lambda: _camera_kernel_sym(num_keypoints, dof, loss), wait)


def residuals_kernel(num_keypoints: int, dof: int, wait: bool = False
                      ) -> tuple[ca.Function | None, bool]:
    return compiled(("residuals", num_keypoints, dof),
                   lambda: _residual_kernel_sym(num_keypoints, dof), wait)


def compiled_camera_kernel(num_keypoints: int, dof: int, loss: str, *,
                           wait: bool = False) -> ca.Function | None:
    """The compiled per-camera Gauss-Newton kernel (:func:`_camera_kernel_sym`) for this
    keypoint count, DoF and loss, or ``None``: not built yet (the first call starts the build
    in the background; ``wait=True`` waits for it), switched off (:data:`JIT_ENV` = ``"0"``),
    no compiler, a failed build, or a library whose numbers differ from the virtual
    machine's (never used then). The library is built once per machine, loaded once per
    process."""
    return normal_equations_kernel(num_keypoints, dof, loss, wait)[0]


def compiled_residual_kernel(num_keypoints: int, dof: int, *,
                             wait: bool = False) -> ca.Function | None:
    """The compiled per-camera residual kernel (:func:`_residual_kernel_sym`), as
    :func:`compiled_camera_kernel`."""
    return residuals_kernel(num_keypoints, dof, wait)[0]
