"""The simulated room: obstacles as boxes and line-of-sight tests by ray/box intersection.

Frames: world (= map), z up, metres.
"""

from __future__ import annotations

import numpy as np

from core.geometry import rotation_z
from simulation.scenario import Box, Scenario


class World:
    """Obstacles of a scenario prepared for fast, vectorized segment/box tests."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        boxes = scenario.obstacles
        self.num_boxes = len(boxes)
        # Per box: rotation world→box (about z), centre (3,), half extents (3,)
        self._R_box_world = np.array(
            [rotation_z(-b.yaw_rad) for b in boxes]).reshape(-1, 3, 3)
        self._center = np.array(
            [[*b.center_xy_m, b.z_min_m + b.size_m[2] / 2] for b in boxes]).reshape(-1, 3)
        self._half = np.array([b.size_m / 2 for b in boxes]).reshape(-1, 3)

    @property
    def obstacles(self) -> tuple[Box, ...]:
        return self.scenario.obstacles

    def segments_blocked(self, origin_world: np.ndarray, points_world: np.ndarray) -> np.ndarray:
        """(N,) bool: whether the segment from ``origin_world`` (3,) to each of ``points_world``
        (N, 3) passes through any obstacle box (slab test; end points inside a box count)."""
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        if self.num_boxes == 0 or len(pts) == 0:
            return np.zeros(len(pts), dtype=bool)
        o = np.asarray(origin_world, dtype=np.float64)
        # (B, N, 3) origin and direction in each box frame, relative to the box centre
        o_loc = np.einsum("bij,bj->bi", self._R_box_world, o - self._center)[:, None, :]
        d_loc = np.einsum("bij,nj->bni", self._R_box_world, pts - o)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d_loc
            t1 = (-self._half[:, None, :] - o_loc) * inv
            t2 = (self._half[:, None, :] - o_loc) * inv
        tmin = np.minimum(t1, t2)
        tmax = np.maximum(t1, t2)
        # Axis-parallel rays: inside the slab → unbounded, outside → never hits.
        parallel = d_loc == 0.0
        inside = np.abs(o_loc) <= self._half[:, None, :]
        tmin = np.where(parallel, np.where(inside, -np.inf, np.inf), tmin)
        tmax = np.where(parallel, np.where(inside, np.inf, -np.inf), tmax)
        t_enter = tmin.max(axis=2)
        t_exit = tmax.min(axis=2)
        hit = (t_enter <= t_exit) & (t_exit >= 0.0) & (t_enter <= 1.0)
        return hit.any(axis=0)

    def footprint_collides(self, xy: np.ndarray, radius_m: float) -> bool:
        """Whether a disc of ``radius_m`` at ``xy`` overlaps an obstacle or the walls."""
        xy = np.asarray(xy, float)
        sc = self.scenario
        if np.any(xy - radius_m < sc.room_min_xy_m) or np.any(xy + radius_m > sc.room_max_xy_m):
            return True
        for b in sc.obstacles:
            local = (xy - b.center_xy_m) @ rotation_z(b.yaw_rad)[:2, :2]  # R^T d: box frame
            nearest = np.clip(local, -b.size_m[:2] / 2, b.size_m[:2] / 2)
            if np.linalg.norm(local - nearest) < radius_m:
                return True
        return False


def box_corners_xy(box: Box) -> np.ndarray:
    """(4, 2) footprint corners of a box in the world frame (for plotting)."""
    hx, hy = box.size_m[0] / 2, box.size_m[1] / 2
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    R = rotation_z(box.yaw_rad)[:2, :2]
    return local @ R.T + box.center_xy_m
