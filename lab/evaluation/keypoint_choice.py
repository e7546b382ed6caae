"""Which keypoints on the robot's base make its heading observable (Cramer-Rao).

The pose bound of :mod:`lab.evaluation.cramer_rao` is a sum over keypoint sightings:
with i.i.d. Gaussian pixel noise of std ``sigma_px``, the Fisher information of (x, y, theta)
is ``sum_k J_k^T J_k / sigma_px^2`` over every (camera, keypoint) pair that is visible, ``J_k``
(2, 3) the derivative of that keypoint's pixel with respect to the planar pose. So each keypoint
has its own information matrix at each pose, and the bound of any subset of keypoints is the
inverse of the sum of theirs. That makes two questions cheap:

* **leave one out**: how much worse the heading bound gets without each keypoint of the
  model (which keypoints carry the heading);
* **add one**: which candidate points on the *rigid* base lower it most (greedy, each step the
  candidate that lowers the median heading bound most).

Visibility includes the base's self-occlusion, which the solver's bound leaves out: the base is
modelled as an upright cylinder of the model's footprint radius; a keypoint on its side (below
the top face) is seen only by cameras on its side of the robot, a keypoint on the top rim also
by cameras above the top face. Keypoints inside the footprint (on the top face) are seen from
above. Other occluders (the torso, furniture) are not modelled.

Poses: the scenario's stop poses (Table I is measured there), each at several headings, and the
cameras that see >= ``min_keypoints`` of the robot's keypoints count (the backend's rule).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from backend_service.covariance import ErrorModel, propagate_correlated
from core.camera import CameraModel
from core.pose import PlanarPose
from core.site import RobotModel

#: derivative step of the numeric Jacobian (m, rad)
_STEP: float = 1e-6


@dataclasses.dataclass(frozen=True)
class Candidate:
    """A point on the rigid base, ``xyz_m`` in the base frame (x forward, y left, z up)."""

    name: str
    xyz_m: tuple[float, float, float]


def base_candidates(model: RobotModel, *, ring_steps: int = 16) -> list[Candidate]:
    """Points on the base's cylinder (footprint radius, model's top height) that the model does
    not have yet: the top rim, a middle ring and the bottom ring, every 360/``ring_steps`` deg.
    The top height is the highest keypoint of the model (its base plate), the bottom the lowest."""
    kp = np.asarray(model.keypoints_base_m, dtype=np.float64)
    z_top, z_bottom = float(kp[:, 2].max()), float(kp[:, 2].min())
    radius = float(model.footprint_radius_m)
    rings = {"top": z_top, "middle": 0.5 * (z_top + z_bottom), "bottom": z_bottom}
    out = []
    for ring, z in rings.items():
        for i in range(ring_steps):
            phi = 2 * math.pi * i / ring_steps
            p = np.array([radius * math.cos(phi), radius * math.sin(phi), z])
            if np.min(np.linalg.norm(kp - p, axis=1)) < 0.03:  # the model has it already
                continue
            out.append(Candidate(f"{ring}_{round(math.degrees(phi)):03d}deg",
                                 (float(p[0]), float(p[1]), float(p[2]))))
    return out


def visible_keypoints(cam: CameraModel, T_world_base: np.ndarray, points_base: np.ndarray,
             radius_m: float, z_top_m: float) -> np.ndarray:
    """(N,) bool: in front of the camera, inside its image, and not hidden by the base's own
    cylinder (see the module text)."""
    pts_w = points_base @ T_world_base[:3, :3].T + T_world_base[:3, 3]
    uv, depth = cam.project(pts_w)
    ok = (depth > 0) & cam.in_image(uv)
    cam_base = np.linalg.solve(T_world_base, np.append(cam.T_world_cam[:3, 3], 1.0))[:3]
    r_xy = np.linalg.norm(points_base[:, :2], axis=1)
    normal = np.where(r_xy[:, None] > 1e-9, points_base[:, :2] / np.maximum(r_xy, 1e-9)[:, None],
                      0.0)
    facing = np.einsum("ij,ij->i", normal, cam_base[None, :2] - points_base[:, :2]) > 0
    on_side = r_xy > 0.8 * radius_m
    on_top = points_base[:, 2] >= z_top_m - 1e-6
    seen_from_above = on_top & (cam_base[2] > z_top_m)
    return ok & (~on_side | facing | seen_from_above)


def point_information(cameras: Sequence[CameraModel], points_base: np.ndarray,
                      pose: PlanarPose, sigma_px: float, radius_m: float, z_top_m: float
                      ) -> np.ndarray:
    """(N, 3, 3): each point's Fisher information of (x, y, theta) at ``pose`` summed over the
    cameras that see it (numeric central-difference Jacobian of the real camera model)."""
    pts = np.asarray(points_base, dtype=np.float64).reshape(-1, 3)
    info = np.zeros((len(pts), 3, 3))
    base = pose.as_array()
    T = pose.T()
    for cam in cameras:
        vis = visible_keypoints(cam, T, pts, radius_m, z_top_m)
        if not vis.any():
            continue
        J = np.zeros((len(pts), 2, 3))
        for j in range(3):
            d = np.zeros(3)
            d[j] = _STEP
            uv = []
            for sign in (1.0, -1.0):
                Tj = PlanarPose(*(base + sign * d)).T()
                uv.append(cam.project(pts @ Tj[:3, :3].T + Tj[:3, 3])[0])
            J[:, :, j] = (uv[0] - uv[1]) / (2 * _STEP)
        info[vis] += np.einsum("nki,nkj->nij", J[vis], J[vis]) / sigma_px**2
    return info


@dataclasses.dataclass(frozen=True)
class KeypointChoice:
    """Heading and position bounds (medians over the poses where the model's keypoints give a
    full-rank bound) for the model's keypoints, without each of them, and with candidates
    added greedily."""

    sigma_px: float
    poses: int
    theta_deg: float
    position_m: float
    #: (keypoint name, median theta bound without it, deg), worst loss first
    leave_one_out: tuple[tuple[str, float], ...]
    #: (candidate name, xyz_m, median theta bound with it and the ones before, deg)
    greedy: tuple[tuple[str, tuple[float, float, float], float], ...]


def _median_bounds(info_sum: np.ndarray) -> tuple[float, float]:
    theta, pos = [], []
    for F in info_sum:
        if np.linalg.matrix_rank(F, tol=1e-9 * max(np.abs(F).max(), 1e-300)) < 3:
            continue
        C = np.linalg.inv(F)
        theta.append(math.sqrt(C[2, 2]))
        pos.append(math.sqrt(C[0, 0] + C[1, 1]))
    if not theta:
        return math.inf, math.inf
    return math.degrees(float(np.median(theta))), float(np.median(pos))


def mirror_groups(candidates: Sequence[Candidate]) -> list[list[int]]:
    """Candidates grouped with their left/right mirror image (``y -> -y``): pairs, and single
    points on the robot's x axis (their own mirror). A keypoint network trained on mirrored
    crops (``--mirror``, the test-time flip) needs its keypoints in such pairs."""
    xyz = np.array([c.xyz_m for c in candidates], dtype=np.float64).reshape(-1, 3)
    groups: list[list[int]] = []
    seen: set[int] = set()
    for i, p in enumerate(xyz):
        if i in seen:
            continue
        mirror = p * np.array([1.0, -1.0, 1.0])
        match = [j for j in range(len(xyz)) if j != i and j not in seen
                 and np.linalg.norm(xyz[j] - mirror) < 1e-6]
        group = [i] if np.linalg.norm(mirror - p) < 1e-6 or not match else [i, match[0]]
        seen.update(group)
        groups.append(group)
    return groups


def keypoint_choice(cameras: Sequence[CameraModel], model: RobotModel,
                    poses: Sequence[PlanarPose], *, sigma_px: float = 0.5,
                    candidates: Sequence[Candidate] | None = None, add: int = 4,
                    min_keypoints: int = 4, pairs: bool = False) -> KeypointChoice:
    """The bounds of ``model``'s keypoints over ``poses``, the loss without each keypoint, and
    ``add`` candidates chosen greedily (default: :func:`base_candidates`). ``pairs``: the
    greedy steps add a candidate together with its mirror image (:func:`mirror_groups`; ``add``
    then counts points, a step of a pair adds two), as a network trained on mirrored crops
    needs."""
    kp = np.asarray(model.keypoints_base_m, dtype=np.float64)
    cands = list(base_candidates(model) if candidates is None else candidates)
    cand_xyz = np.array([c.xyz_m for c in cands], dtype=np.float64).reshape(-1, 3)
    radius, z_top = float(model.footprint_radius_m), float(kp[:, 2].max())
    info_kp, info_cand, used = [], [], 0
    for pose in poses:
        T = pose.T()
        seeing = [c for c in cameras
                  if int(visible_keypoints(c, T, kp, radius, z_top).sum()) >= min_keypoints]
        if not seeing:
            continue
        used += 1
        info_kp.append(point_information(seeing, kp, pose, sigma_px, radius, z_top))
        info_cand.append(point_information(seeing, cand_xyz, pose, sigma_px, radius, z_top))
    if not used:
        raise ValueError("no pose is seen by a camera with >= "
                         f"{min_keypoints} visible keypoints: nothing to bound")
    I_kp = np.stack(info_kp)  # (P, M, 3, 3)
    I_c = np.stack(info_cand)  # (P, C, 3, 3)
    total = I_kp.sum(axis=1)
    theta, pos = _median_bounds(total)
    loo = []
    for m, name in enumerate(model.keypoint_names):
        loo.append((name, _median_bounds(total - I_kp[:, m])[0]))
    loo.sort(key=lambda t: -t[1])
    greedy: list[tuple[str, tuple[float, float, float], float]] = []
    current = total.copy()
    remaining = mirror_groups(cands) if pairs else [[c] for c in range(len(cands))]
    added = 0
    while remaining and added < add:
        best = min(remaining,
                   key=lambda g: _median_bounds(current + I_c[:, g].sum(axis=1))[0])
        current = current + I_c[:, best].sum(axis=1)
        remaining.remove(best)
        bound = _median_bounds(current)[0]
        for c in best:  # each point of the step with the bound after the whole step
            greedy.append((cands[c].name, cands[c].xyz_m, bound))
        added += len(best)
    return KeypointChoice(float(sigma_px), used, theta, pos, tuple(loo), tuple(greedy))


@dataclasses.dataclass(frozen=True)
class HeadingBudget:
    """Where a camera pose's heading error comes from: medians over the poses of the heading
    std (deg) per source for one frame-set, and ``averaged_deg`` the total after averaging
    ``frames`` frame-sets (what averages down: keypoint noise and the per-detection errors; what
    does not: the cameras' calibration). ``cameras`` is how many cameras the poses used
    (at most ``max_cameras``, the ones seeing most keypoints)."""

    frames: int
    keypoint_noise_deg: float
    detection_shift_deg: float
    detection_scale_deg: float
    calibration_deg: float
    averaged_deg: float
    poses: int
    #: the total when the keypoint errors repeat at a stop (a static robot is the same image
    #: in every frame: only sensor noise changes, so a network's view-dependent error does not
    #: average down)
    repeated_deg: float = math.nan


def heading_budget(cameras: Sequence[CameraModel], model: RobotModel,
                   poses: Sequence[PlanarPose], *, sigma_px: float, errors: ErrorModel,
                   frames: int = 5, max_cameras: int = 2, min_keypoints: int = 4
                   ) -> HeadingBudget:
    """The heading error budget of the least-squares camera pose with ``max_cameras`` cameras
    (Table I's ">= 2 cameras" rows use two or more): per source, propagated with
    :func:`backend_service.covariance.propagate_correlated`, the backend's own propagation."""
    kp = np.asarray(model.keypoints_base_m, dtype=np.float64)
    radius, z_top = float(model.footprint_radius_m), float(kp[:, 2].max())
    parts: dict[str, list[float]] = {k: [] for k in ("noise", "shift", "scale", "calib", "avg",
                                                      "rep")}
    for pose in poses:
        T = pose.T()
        vis = {c.camera_id: visible_keypoints(c, T, kp, radius, z_top) for c in cameras}
        seeing = sorted((c for c in cameras if vis[c.camera_id].sum() >= min_keypoints),
                        key=lambda c: -int(vis[c.camera_id].sum()))[:max_cameras]
        if len(seeing) < max_cameras:
            continue
        base = pose.as_array()
        J = np.zeros((len(seeing), len(kp), 2, 3))
        for j in range(3):
            d = np.zeros(3)
            d[j] = _STEP
            for ci, cam in enumerate(seeing):
                uv = []
                for sign in (1.0, -1.0):
                    Tj = PlanarPose(*(base + sign * d)).T()
                    uv.append(cam.project(kp @ Tj[:3, :3].T + Tj[:3, 3])[0])
                J[ci, :, :, j] = (uv[0] - uv[1]) / (2 * _STEP)
        w = np.stack([vis[c.camera_id] for c in seeing]).astype(np.float64)
        J = np.where(w[:, :, None, None] > 0, J, 0.0).reshape(-1, 3)
        JtJ = J.T @ J
        if np.linalg.matrix_rank(JtJ) < 3:
            continue
        A = np.linalg.solve(JtJ, J.T)  # (3, 2CM): unit weights, sigma cancels
        pts_w = kp @ T[:3, :3].T + T[:3, 3]
        noise = sigma_px**2 * np.linalg.inv(JtJ)
        shift, _ = propagate_correlated(A, seeing, pts_w, w, ErrorModel(
            detection_shift_sigma_px=errors.detection_shift_sigma_px))
        scale, _ = propagate_correlated(A, seeing, pts_w, w, ErrorModel(
            detection_scale_sigma=errors.detection_scale_sigma))
        _, calib = propagate_correlated(A, seeing, pts_w, w, ErrorModel(
            extrinsic_sigma_m=errors.extrinsic_sigma_m,
            extrinsic_sigma_deg=errors.extrinsic_sigma_deg))
        parts["noise"].append(noise[2, 2])
        parts["shift"].append(shift[2, 2])
        parts["scale"].append(scale[2, 2])
        parts["calib"].append(calib[2, 2])
        parts["avg"].append((noise[2, 2] + shift[2, 2] + scale[2, 2]) / frames + calib[2, 2])
        parts["rep"].append(noise[2, 2] + shift[2, 2] + scale[2, 2] + calib[2, 2])
    if not parts["avg"]:
        raise ValueError(f"no pose is seen by {max_cameras} cameras with >= {min_keypoints} "
                         "visible keypoints")

    def med(key: str) -> float:
        return math.degrees(math.sqrt(float(np.median(parts[key]))))

    return HeadingBudget(int(frames), med("noise"), med("shift"), med("scale"), med("calib"),
                         med("avg"), len(parts["avg"]), med("rep"))


def format_budget(budget: HeadingBudget, errors: ErrorModel, sigma_px: float) -> str:
    """The budget as text (the CLI prints it)."""
    rows = [
        (f"keypoint noise ({sigma_px:g} px each)", budget.keypoint_noise_deg, ""),
        (f"detection shift ({errors.detection_shift_sigma_px:g} px)",
         budget.detection_shift_deg, ""),
        (f"detection scale ({100 * errors.detection_scale_sigma:g} %)",
         budget.detection_scale_deg, ""),
        (f"camera calibration ({100 * errors.extrinsic_sigma_m:g} cm, "
         f"{errors.extrinsic_sigma_deg:g} deg)", budget.calibration_deg, "does not average"),
        (f"total after averaging {budget.frames} frame-sets", budget.averaged_deg,
         "keypoint errors new in every frame"),
        ("", budget.repeated_deg, "keypoint errors repeat at a stop"),
    ]
    lines = [f"heading error budget, two cameras, medians over {budget.poses} poses "
             "(deg, 1 sigma):"]
    for label, value, note in rows:
        lines.append(f"  {label:<38} {value:.3f}" + (f"  ({note})" if note else ""))
    return "\n".join(lines)


def stop_poses(waypoints: Sequence[tuple[float, float, float]], headings: int = 8
               ) -> list[PlanarPose]:
    """Each (x, y, theta) stop at its own heading and ``headings - 1`` more, evenly spaced."""
    out = []
    for x, y, theta in waypoints:
        for k in range(headings):
            out.append(PlanarPose(float(x), float(y), float(theta) + 2 * math.pi * k / headings))
    return out


def format_choice(choice: KeypointChoice) -> str:
    """The report as text (the CLI prints it)."""
    lines = [
        f"keypoint choice: Cramer-Rao bound over {choice.poses} poses, sigma "
        f"{choice.sigma_px:g} px per keypoint, base self-occlusion modelled",
        f"  the model's keypoints: heading {choice.theta_deg:.3f} deg, position "
        f"{100 * choice.position_m:.2f} cm (medians)",
        "  without one keypoint (heading bound, deg; + change):",
    ]
    for name, theta in choice.leave_one_out:
        lines.append(f"    {name:<18} {theta:.3f}  ({100 * (theta / choice.theta_deg - 1):+.1f} %)")
    lines.append("  candidates on the rigid base added greedily (heading bound, deg):")
    for name, xyz, theta in choice.greedy:
        lines.append(f"    + {name:<18} ({xyz[0]:+.3f}, {xyz[1]:+.3f}, {xyz[2]:.3f}) m  "
                     f"{theta:.3f}  ({100 * (theta / choice.theta_deg - 1):+.1f} %)")
    return "\n".join(lines)
