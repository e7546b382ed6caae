"""The joint least-squares problem of the robot-as-target calibration
(:mod:`calibration.robot_target`): keypoint observations hung on trajectory
nodes, their projection through the cameras with closed-form Jacobians, the odometry and
localization factors, priors that hold cameras or the set's placement, the normal equations and
Levenberg-Marquardt with Huber weights. numpy only; dense normal equations (a few thousand
unknowns for a 5-minute drive).

Conventions as in :mod:`~calibration.robot_target`: world = map, z up; camera
optical frame (OpenCV); camera poses perturbed on the left, R' = Exp(w) R_world_cam,
c' = c + dc (world axes); a node is the robot's planar pose (x, y, theta).
"""

from __future__ import annotations

import dataclasses
from typing import Final, Protocol

import numpy as np

from calibration.least_squares import Damping, Problem, huber_weights, levenberg_marquardt
from core.camera import CameraModel
from core.geometry import (
    rotation_from_rotvec,
    rotvec_from_rotation,
    wrap_angle_array,
)
from core.projection import SOLVER_MIN_DEPTH_M, project_world_points

__all__ = [
    "JointProblem",
    "Observations",
    "ProblemSettings",
    "adjust",
    "project_keypoints",
    "robot_points",
    "subset_observations",
]


class ProblemSettings(Protocol):
    """What the problem reads of the calibration's settings
    (:class:`~calibration.robot_target.RobotTargetConfig`): odometry noise
    (m, m per m, rad, rad per rad of turn, rad per m) and the Huber threshold (px)."""

    @property
    def odom_sigma_m(self) -> float: ...
    @property
    def odom_sigma_per_m(self) -> float: ...
    @property
    def odom_sigma_rad(self) -> float: ...
    @property
    def odom_sigma_rad_per_rad(self) -> float: ...
    @property
    def odom_sigma_rad_per_m(self) -> float: ...
    @property
    def huber_px(self) -> float: ...


@dataclasses.dataclass
class Observations:
    """Keypoint observations, flattened: camera index (n,), node index (n,), the robot's pose
    offset from its node by odometry (n, 3: dx, dy in the node's frame, dtheta), keypoint base
    coordinates (n, 3), pixels (n, 2), weights (n,), detection index (n,)."""

    cam: np.ndarray
    node: np.ndarray
    delta: np.ndarray
    kp: np.ndarray
    uv: np.ndarray
    w: np.ndarray
    det: np.ndarray


def subset_observations(obs: Observations, sel: np.ndarray) -> Observations:
    """The observations selected by ``sel`` (a bool mask or indices)."""
    return Observations(*(getattr(obs, f.name)[sel] for f in dataclasses.fields(obs)))


def robot_points(nodes: np.ndarray, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """World points (n, 3) of the observed keypoints and (n, 2) their offset from the node's
    position (what a node heading change rotates)."""
    q = nodes[obs.node]
    c, s = np.cos(q[:, 2]), np.sin(q[:, 2])
    dx, dy, dth = obs.delta[:, 0], obs.delta[:, 1], obs.delta[:, 2]
    bx = q[:, 0] + c * dx - s * dy
    by = q[:, 1] + s * dx + c * dy
    th = q[:, 2] + dth
    ct, st = np.cos(th), np.sin(th)
    px = bx + ct * obs.kp[:, 0] - st * obs.kp[:, 1]
    py = by + st * obs.kp[:, 0] + ct * obs.kp[:, 1]
    pw = np.stack([px, py, obs.kp[:, 2]], axis=-1)
    return pw, np.stack([px - q[:, 0], py - q[:, 1]], axis=-1)


def project_keypoints(R_wc: np.ndarray, c_w: np.ndarray, K: np.ndarray, dist: np.ndarray,
             cam: np.ndarray, pw: np.ndarray, jacobians: bool
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Pixels (n, 2), depth (n,), and with ``jacobians`` d(u, v)/d(camera rotation, camera
    position) (n, 2, 6) and d(u, v)/d(world point) (n, 2, 3), observation i through camera
    ``cam[i]`` (:func:`core.projection.project_world_points`; the depth clamped to
    :data:`core.projection.SOLVER_MIN_DEPTH_M` so the solver sees finite values)."""
    proj = project_world_points(R_wc[cam], c_w[cam], K[cam], dist[cam], pw,
                                jacobians=jacobians, min_depth_m=SOLVER_MIN_DEPTH_M)
    return proj.uv, proj.depth_m, proj.d_uv_d_camera, proj.d_uv_d_point


class JointProblem:
    """The joint least-squares problem (:mod:`calibration.robot_target`'s
    docstring lists its factors): unknowns are the trajectory nodes (3 each, first) and the
    solved cameras (6 each: rotation about world axes, then position)."""

    def __init__(self, cams: list[CameraModel], solve_mask: np.ndarray, obs: Observations,
                 node_odom: np.ndarray, node_prior: np.ndarray, prior_sqrt_info: np.ndarray,
                 config: ProblemSettings) -> None:
        self.config = config
        self.C = len(cams)
        self.K_nodes = len(node_odom)
        self.K = np.stack([c.K for c in cams])
        dist = np.zeros((self.C, 8))
        for i, c in enumerate(cams):
            dist[i, : c.dist.size] = c.dist
        self.dist = dist
        self.solve_mask = solve_mask
        self.node_odom_input = node_odom
        self.obs = obs
        self.robust = np.ones(len(obs.w))
        self.keep = obs.w > 0
        self.node_prior = node_prior
        self.prior_sqrt_info = prior_sqrt_info  # (K, 3, 3), zero where no prior
        # odometry between consecutive nodes: increments in the first node's frame
        a, b = node_odom[:-1], node_odom[1:]
        ca, sa = np.cos(a[:, 2]), np.sin(a[:, 2])
        dxw, dyw = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        self.odom_delta = np.stack([ca * dxw + sa * dyw, -sa * dxw + ca * dyw,
                                    wrap_angle_array(b[:, 2] - a[:, 2])], axis=-1)
        dist_m = np.hypot(dxw, dyw)
        turn = np.abs(self.odom_delta[:, 2])
        s_xy = config.odom_sigma_m + config.odom_sigma_per_m * dist_m
        s_th = (config.odom_sigma_rad + config.odom_sigma_rad_per_rad * turn
                + config.odom_sigma_rad_per_m * dist_m)
        self.odom_inv_sigma = 1.0 / np.stack([s_xy, s_xy, s_th], axis=-1)
        cam_cols = np.flatnonzero(solve_mask)
        self.cam_col = np.full(self.C, -1)
        self.cam_col[cam_cols] = 3 * self.K_nodes + 6 * np.arange(len(cam_cols))
        self.n = 3 * self.K_nodes + 6 * len(cam_cols)
        self.pixel_sigma = 1.0
        #: camera index → (R0, c0, (6,) inverse sigmas): a prior holding a camera near a pose
        self.cam_prior: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        #: (camera indices, their initial rotations (n, 3, 3) and positions (n, 3), inverse
        #: sigmas (3,)): holds the set's mean x, y and yaw at the initial poses' (frame "site")
        self.gauge_prior: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def _gauge(self, R_wc: np.ndarray, c_w: np.ndarray) -> np.ndarray:
        idx, R0, c0, inv_sigma = self.gauge_prior  # type: ignore[misc]
        yaw = np.mean([rotvec_from_rotation(R_wc[i] @ R0[j].T)[2] for j, i in enumerate(idx)])
        dxy = (c_w[idx, :2] - c0[:, :2]).mean(axis=0)
        return inv_sigma * np.array([dxy[0], dxy[1], yaw])

    def _camera_prior(self, R_wc: np.ndarray, c_w: np.ndarray, ci: int) -> np.ndarray:
        R0, c0, inv_sigma = self.cam_prior[ci]
        return inv_sigma * np.concatenate([rotvec_from_rotation(R_wc[ci] @ R0.T), c_w[ci] - c0])

    # residual parts ---------------------------------------------------------------------------

    def reprojection(self, R_wc: np.ndarray, c_w: np.ndarray, nodes: np.ndarray,
                     jacobians: bool = False):
        pw, off = robot_points(nodes, self.obs)
        uv, z, G, d_uv_a = project_keypoints(R_wc, c_w, self.K, self.dist, self.obs.cam, pw,
                                             jacobians)
        err = uv - self.obs.uv
        return err, z, G, d_uv_a, off

    def cost(self, R_wc: np.ndarray, c_w: np.ndarray, nodes: np.ndarray) -> float:
        err, z, *_ = self.reprojection(R_wc, c_w, nodes)
        return self._total_cost(err, z, R_wc, c_w, nodes)

    def _reproj_weights(self, err: np.ndarray, z: np.ndarray) -> np.ndarray:
        w = np.where(self.keep & (z > 0.05), self.obs.w, 0.0)
        return w * self.robust / self.pixel_sigma ** 2

    def _total_cost(self, err: np.ndarray, z: np.ndarray, R_wc: np.ndarray, c_w: np.ndarray,
                    nodes: np.ndarray) -> float:
        w = self._reproj_weights(err, z)
        c = float(np.sum(w * np.sum(err * err, axis=1)))
        r_o, _, _ = self._odometry(nodes)
        r_p = self._prior(nodes)
        r_c = sum(float(np.sum(self._camera_prior(R_wc, c_w, ci) ** 2))
                  for ci in self.cam_prior)
        if self.gauge_prior is not None:
            r_c += float(np.sum(self._gauge(R_wc, c_w) ** 2))
        return c + float(np.sum(r_o ** 2)) + float(np.sum(r_p ** 2)) + r_c

    def _odometry(self, nodes: np.ndarray):
        a, b = nodes[:-1], nodes[1:]
        ca, sa = np.cos(a[:, 2]), np.sin(a[:, 2])
        dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        e = np.stack([ca * dx + sa * dy - self.odom_delta[:, 0],
                      -sa * dx + ca * dy - self.odom_delta[:, 1],
                      wrap_angle_array(b[:, 2] - a[:, 2] - self.odom_delta[:, 2])], axis=-1)
        # Jacobians (E, 3, 3) wrt a and b
        Ja = np.zeros((len(a), 3, 3))
        Ja[:, 0, 0], Ja[:, 0, 1] = -ca, -sa
        Ja[:, 1, 0], Ja[:, 1, 1] = sa, -ca
        Ja[:, 0, 2] = -sa * dx + ca * dy
        Ja[:, 1, 2] = -ca * dx - sa * dy
        Ja[:, 2, 2] = -1.0
        Jb = np.zeros((len(a), 3, 3))
        Jb[:, 0, 0], Jb[:, 0, 1] = ca, sa
        Jb[:, 1, 0], Jb[:, 1, 1] = -sa, ca
        Jb[:, 2, 2] = 1.0
        s = self.odom_inv_sigma
        return e * s, Ja * s[:, :, None], Jb * s[:, :, None]

    def _prior(self, nodes: np.ndarray) -> np.ndarray:
        d = nodes - self.node_prior
        d[:, 2] = wrap_angle_array(d[:, 2])
        return np.einsum("kij,kj->ki", self.prior_sqrt_info, d)

    # normal equations -------------------------------------------------------------------------

    def normal_equations(self, R_wc: np.ndarray, c_w: np.ndarray, nodes: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(H, g, per-camera own information (C, 6, 6), kept reprojection weights)."""
        err, z, G, d_uv_a, off = self.reprojection(R_wc, c_w, nodes, jacobians=True)
        w = self._reproj_weights(err, z)
        Kn, n = self.K_nodes, self.n
        H = np.zeros((n, n))
        g = np.zeros(n)
        # reprojection: node part (x, y, theta of the node) and camera part
        Jn = np.empty((len(w), 2, 3))
        Jn[:, :, 0] = d_uv_a[:, :, 0]
        Jn[:, :, 1] = d_uv_a[:, :, 1]
        Jn[:, :, 2] = -d_uv_a[:, :, 0] * off[:, 1, None] + d_uv_a[:, :, 1] * off[:, 0, None]
        sw = w[:, None, None]
        Hnn = np.einsum("nki,nkj->nij", Jn * sw, Jn)
        gn = np.einsum("nki,nk->ni", Jn * sw, err)
        Hcc = np.einsum("nki,nkj->nij", G * sw, G)
        gc = np.einsum("nki,nk->ni", G * sw, err)
        Hnc = np.einsum("nki,nkj->nij", Jn * sw, G)
        node_idx = self.obs.node
        cam_idx = self.obs.cam
        own = np.zeros((self.C, 6, 6))
        for ci in range(self.C):
            sel = cam_idx == ci
            own[ci] = Hcc[sel].sum(axis=0)
        blocks_nn = _sum_by(node_idx, Hnn.reshape(-1, 9), Kn).reshape(Kn, 3, 3)
        g_n = _sum_by(node_idx, gn, Kn)
        for k3 in range(3):
            rows = 3 * np.arange(Kn) + k3
            for j3 in range(3):
                H[rows, 3 * np.arange(Kn) + j3] += blocks_nn[:, k3, j3]
        g[: 3 * Kn] += g_n.reshape(-1)
        for ci in np.flatnonzero(self.solve_mask):
            col = self.cam_col[ci]
            sel = cam_idx == ci
            H[col:col + 6, col:col + 6] += own[ci]
            g[col:col + 6] += gc[sel].sum(axis=0)
            Hnc_k = _sum_by(node_idx[sel], Hnc[sel].reshape(-1, 18), Kn).reshape(Kn, 3, 6)
            H[: 3 * Kn, col:col + 6] += Hnc_k.reshape(3 * Kn, 6)
            H[col:col + 6, : 3 * Kn] += Hnc_k.reshape(3 * Kn, 6).T
        self._add_trajectory_factors(H, g, nodes)
        self._add_camera_priors(H, g, R_wc, c_w, 3 * Kn)
        return H, g, own, w

    def _add_trajectory_factors(self, H: np.ndarray, g: np.ndarray, nodes: np.ndarray) -> None:
        """Odometry between consecutive nodes and the localization prior of every node."""
        Kn = self.K_nodes
        r_o, Ja, Jb = self._odometry(nodes)
        E = len(r_o)
        ia, ib = 3 * np.arange(E), 3 * np.arange(1, E + 1)
        Haa = np.einsum("eki,ekj->eij", Ja, Ja)
        Hbb = np.einsum("eki,ekj->eij", Jb, Jb)
        Hab = np.einsum("eki,ekj->eij", Ja, Jb)
        for r in range(3):
            for c in range(3):
                np.add.at(H, (ia + r, ia + c), Haa[:, r, c])
                np.add.at(H, (ib + r, ib + c), Hbb[:, r, c])
                np.add.at(H, (ia + r, ib + c), Hab[:, r, c])
                np.add.at(H, (ib + c, ia + r), Hab[:, r, c])
        ga = np.einsum("eki,ek->ei", Ja, r_o)
        gb = np.einsum("eki,ek->ei", Jb, r_o)
        np.add.at(g, (ia[:, None] + np.arange(3)), ga)
        np.add.at(g, (ib[:, None] + np.arange(3)), gb)
        r_p = self._prior(nodes)
        P = self.prior_sqrt_info
        Hp = np.einsum("kri,krj->kij", P, P)
        gp = np.einsum("kri,kr->ki", P, r_p)
        ik = 3 * np.arange(Kn)
        for r in range(3):
            for c in range(3):
                H[ik + r, ik + c] += Hp[:, r, c]
        g[: 3 * Kn] += gp.reshape(-1)

    def _add_camera_priors(self, H: np.ndarray, g: np.ndarray, R_wc: np.ndarray,
                           c_w: np.ndarray, offset: int) -> None:
        """The held cameras' priors (Jacobian ~ diag(inverse sigma) near the prior pose)."""
        for ci, (_, _, inv_sigma) in self.cam_prior.items():
            col = self.cam_col[ci] - 3 * self.K_nodes + offset
            r = self._camera_prior(R_wc, c_w, ci)
            H[col:col + 6, col:col + 6] += np.diag(inv_sigma ** 2)
            g[col:col + 6] += inv_sigma * r
        if self.gauge_prior is not None:
            idx, _, _, inv_sigma = self.gauge_prior
            J = np.zeros((3, H.shape[0]))
            for i in idx:
                col = self.cam_col[i] - 3 * self.K_nodes + offset
                J[0, col + 3] = J[1, col + 4] = 1.0 / len(idx)  # mean x, y
                J[2, col + 2] = 1.0 / len(idx)  # mean yaw (rotation about world z)
            J *= inv_sigma[:, None]
            H += J.T @ J
            g += J.T @ self._gauge(R_wc, c_w)

    def camera_normal_equations(self, R_wc: np.ndarray, c_w: np.ndarray, nodes: np.ndarray
                                ) -> tuple[np.ndarray, np.ndarray]:
        """(H, g) of the solved cameras' parameters alone, the trajectory held fixed."""
        err, z, G, _, _ = self.reprojection(R_wc, c_w, nodes, jacobians=True)
        w = self._reproj_weights(err, z)
        cols = np.flatnonzero(self.solve_mask)
        H = np.zeros((6 * len(cols), 6 * len(cols)))
        g = np.zeros(6 * len(cols))
        for j, ci in enumerate(cols):
            sel = (self.obs.cam == ci) & (w > 0)
            Gw = G[sel] * w[sel, None, None]
            H[6 * j:6 * j + 6, 6 * j:6 * j + 6] = np.einsum("nki,nkj->ij", Gw, G[sel])
            g[6 * j:6 * j + 6] = np.einsum("nki,nk->i", Gw, err[sel])
        self._add_camera_priors(H, g, R_wc, c_w, 0)
        return H, g

    def apply(self, R_wc: np.ndarray, c_w: np.ndarray, nodes: np.ndarray, dx: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nodes2 = nodes + dx[: 3 * self.K_nodes].reshape(-1, 3)
        nodes2[:, 2] = wrap_angle_array(nodes2[:, 2])
        R2, c2 = R_wc.copy(), c_w.copy()
        for ci in np.flatnonzero(self.solve_mask):
            col = self.cam_col[ci]
            R2[ci] = rotation_from_rotvec(dx[col:col + 3]) @ R_wc[ci]
            c2[ci] = c_w[ci] + dx[col + 3:col + 6]
        return R2, c2, nodes2


def _sum_by(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Rows of ``values`` (m, k) summed by ``index`` (m,) into (n, k) (bincount per column)."""
    out = np.empty((n, values.shape[1]))
    for j in range(values.shape[1]):
        out[:, j] = np.bincount(index, weights=values[:, j], minlength=n)
    return out


#: the robot-target adjustment's damping: relaxed fivefold after a kept step, down to 1e-7
ROBOT_DAMPING: Final = Damping(initial=1e-3, down=5.0, floor=1e-7, step_tol=1e-8,
                               rel_tol=1e-7)


def adjust(problem: JointProblem, R_wc: np.ndarray, c_w: np.ndarray, nodes: np.ndarray,
           iterations: int, fix_nodes: bool = False, robust: bool = True
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Minimise the problem's cost from the given state
    (:func:`calibration.least_squares.levenberg_marquardt`); Huber weights refreshed at each
    linearization; ``fix_nodes``: only the cameras move."""
    State = tuple[np.ndarray, np.ndarray, np.ndarray]
    idx = (np.arange(3 * problem.K_nodes, problem.n) if fix_nodes else np.arange(problem.n))

    def linearize(x: State) -> tuple[np.ndarray, np.ndarray]:
        if robust:
            err, _, *_ = problem.reprojection(*x)
            problem.robust = huber_weights(np.sqrt(np.sum(err * err, axis=1)),
                                           problem.config.huber_px)
        if fix_nodes:
            return problem.camera_normal_equations(*x)
        H, g, _, _ = problem.normal_equations(*x)
        return H, g

    def step(x: State, A: np.ndarray, g: np.ndarray) -> tuple[State, np.ndarray]:
        delta = -np.linalg.solve(A, g)
        dx = np.zeros(problem.n)
        dx[idx] = delta
        return problem.apply(*x, dx), delta

    (R_wc, c_w, nodes), it = levenberg_marquardt(
        Problem(linearize, lambda x: problem.cost(*x), step), (R_wc, c_w, nodes), iterations,
        ROBOT_DAMPING)
    return R_wc, c_w, nodes, it
