"""ICP gate of the semantic map: align a robot's cloud to the map before fusing it.

The robot's pose (and so its cloud in the world frame) is less reliable than the calibrated
static sensors' (drift since the last correction, forward-kinematics tolerances), so the paper
aligns each robot cloud to the allocentric map before integration. :func:`align_to_map` runs
coarse-to-fine point-to-plane ICP (Open3D's legacy ``registration_icp``), the robot cloud
downsampled per level with ``voxel_down_sample``, against the map's voxel means and normals, and
gates the result: enough overlap (fitness), small residuals, a correction no larger than the
expected pose error, and a well-constrained geometry (surface normals in all three directions).

Open3D, the mapper's heavy dependency, is imported here and nowhere else in the project's
packages.

Error policy: a malformed call (arrays of the wrong shape or type, a bad configuration) raises
:class:`mapper.semantic_map.MapError`; a cloud that cannot be aligned (non-finite points, too
few points, too little map nearby) or an alignment that fails a gate returns an
:class:`AlignmentResult` with ``accepted=False`` and the ``reason``, so the caller counts it per
reason and goes on.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import open3d as o3d

from mapper.semantic_map import MapError

logger = logging.getLogger(__name__)

_reg = o3d.pipelines.registration


@dataclasses.dataclass(frozen=True)
class AlignmentConfig:
    """Parameters of :func:`align_to_map`.

    Per level (coarse to fine, equal lengths): ``voxel_sizes_m`` (robot cloud downsampling, m),
    ``max_correspondence_m`` (ICP correspondence distance, m), ``max_iterations``. ICP stops a
    level early when fitness and RMSE change by less than ``relative_fitness`` /
    ``relative_rmse``. ``min_points``: least robot points after the finest downsampling and
    least map points near the cloud; ``max_points``: at most this many robot points per level
    (every k-th of the downsampled cloud; bounds the latency, the accuracy barely changes).
    Gates on the finest level's result: ``min_fitness`` (share
    of the downsampled robot points with a map point within the correspondence distance),
    ``max_inlier_rmse_m`` (RMS distance of those pairs), ``max_offset_m`` (displacement of the
    pivot, by default the cloud's centroid), ``max_offset_deg`` (full rotation angle),
    ``min_normal_spread`` (smallest eigenvalue of the mean ``n nᵀ`` of the matched map normals:
    0 when a direction is unconstrained, e.g. a floor and one wall; 1/3 at best).
    ``crop_margin_m``: map points farther than this outside the cloud's bounding box are not
    used (``None``: ``max_offset_m`` + the coarsest correspondence distance).
    ``robust_scale``: Tukey's biweight on the finest level's point-to-plane residuals with its
    cut-off at this share of that level's correspondence distance (0: plain least squares);
    robot points on things the map does not hold yet (furniture missing from the prior model)
    then pull less; ``robust_levels``: ``"finest"`` or ``"all"``. ``planar``: keep only the
    planar part (x, y, yaw) of each level's correction (a ground robot's pose error; roll,
    pitch and height would let points of furniture the map lacks tilt the cloud).
    """

    voxel_sizes_m: tuple[float, ...] = (0.2, 0.1, 0.05)
    max_correspondence_m: tuple[float, ...] = (0.5, 0.25, 0.1)
    max_iterations: tuple[int, ...] = (30, 20, 15)
    relative_fitness: float = 1e-6
    relative_rmse: float = 1e-6
    min_points: int = 50
    max_points: int = 5000
    min_fitness: float = 0.5
    max_inlier_rmse_m: float = 0.05
    max_offset_m: float = 0.5
    max_offset_deg: float = 10.0
    min_normal_spread: float = 0.01
    crop_margin_m: float | None = None
    robust_scale: float = 0.0
    robust_levels: str = "finest"
    planar: bool = True

    def __post_init__(self) -> None:
        def bad(field: str, reason: str) -> MapError:
            return MapError(f"alignment config: {field}: {reason}")

        levels = len(self.voxel_sizes_m)
        if levels == 0:
            raise bad("voxel_sizes_m", "needs at least one level")
        for name in ("max_correspondence_m", "max_iterations"):
            if len(getattr(self, name)) != levels:
                raise bad(name, f"needs one value per level ({levels}), got "
                                f"{len(getattr(self, name))}")
        for name in ("voxel_sizes_m", "max_correspondence_m"):
            if not all(math.isfinite(x) and x > 0 for x in getattr(self, name)):
                raise bad(name, f"values must be finite and > 0, got {getattr(self, name)}")
        if not all(isinstance(x, int) and x >= 1 for x in self.max_iterations):
            raise bad("max_iterations", f"values must be integers >= 1, got "
                                        f"{self.max_iterations}")
        if not 0.0 <= self.min_fitness <= 1.0:
            raise bad("min_fitness", f"must be in [0, 1], got {self.min_fitness}")
        for name in ("relative_fitness", "relative_rmse", "max_inlier_rmse_m", "max_offset_m",
                     "max_offset_deg", "min_normal_spread", "robust_scale"):
            if not getattr(self, name) >= 0.0:
                raise bad(name, f"must be >= 0, got {getattr(self, name)}")
        if not (isinstance(self.min_points, int) and self.min_points >= 3):
            raise bad("min_points", f"must be an integer >= 3, got {self.min_points}")
        if not (isinstance(self.max_points, int) and self.max_points >= self.min_points):
            raise bad("max_points", f"must be an integer >= min_points, got {self.max_points}")
        if self.crop_margin_m is not None and not self.crop_margin_m >= 0.0:
            raise bad("crop_margin_m", f"must be >= 0 or None, got {self.crop_margin_m}")


@dataclasses.dataclass(frozen=True)
class AlignmentResult:
    """Outcome of :func:`align_to_map`.

    ``T_correction`` (4, 4) float64 maps the given cloud onto the map (world → world; apply it
    to the cloud, or compose it onto ``T_world_sensor``, only when ``accepted``); identity
    when the input was rejected before ICP. ``fitness`` in [0, 1], ``inlier_rmse_m`` metres,
    ``offset_m`` displacement of the pivot (metres), ``offset_deg`` full rotation angle and
    ``yaw_deg`` its yaw part (degrees), ``normal_spread`` (see :class:`AlignmentConfig`),
    ``num_points`` robot points used at the finest level, ``num_map_points`` map points near
    the cloud. ``reason`` is empty when accepted, else starts with a stable token
    (``non_finite_points``, ``too_few_points``, ``too_few_map_points``, ``low_fitness``,
    ``high_rmse``, ``large_offset``, ``degenerate``) followed by the figures.
    """

    T_correction: np.ndarray
    fitness: float
    inlier_rmse_m: float
    offset_m: float
    offset_deg: float
    yaw_deg: float
    normal_spread: float
    num_points: int
    num_map_points: int
    accepted: bool
    reason: str


def _check_array(value: object, field: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.dtype.kind not in "fiu":
        raise MapError(f"{field}: expected a float array of shape (N, 3), got {arr.dtype} "
                       f"{arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.float64)


def _column_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis (3,) minimum and maximum of (N, 3) points (column by column: numpy reduces an
    (N, 3) array over axis 0 an order of magnitude slower)."""
    return (np.array([points[:, a].min() for a in range(3)]),
            np.array([points[:, a].max() for a in range(3)]))


def _row_sums(points: np.ndarray) -> np.ndarray:
    """(N,) x + y + z of (N, 3) points: non-finite exactly where a coordinate is."""
    return points[:, 0] + points[:, 1] + points[:, 2]


def _in_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) bool: the (N, 3) points lie in the axis-aligned box [lo, hi] (False for NaN)."""
    inside = (points[:, 0] >= lo[0]) & (points[:, 0] <= hi[0])
    for a in (1, 2):
        inside &= (points[:, a] >= lo[a]) & (points[:, a] <= hi[a])
    return inside


def planar_part(T: np.ndarray) -> np.ndarray:
    """The planar part (x, y translation, rotation about z) of a (4, 4) transform: what can
    differ between a ground robot's pose and the truth; roll, pitch and height are dropped."""
    yaw = math.atan2(T[1, 0], T[0, 0])
    out = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:2, 3] = T[:2, 3]
    return out


def _rejected(reason: str, num_points: int = 0, num_map_points: int = 0) -> AlignmentResult:
    return AlignmentResult(np.eye(4), 0.0, math.inf, 0.0, 0.0, 0.0, 0.0, num_points,
                           num_map_points, False, reason)


def _normal_spread(normals: np.ndarray) -> float:
    """Smallest eigenvalue of the mean n nᵀ of (K, 3) unit normals (see
    :class:`AlignmentConfig`'s ``min_normal_spread``)."""
    return float(np.linalg.eigvalsh(normals.T @ normals / len(normals))[0])


def align_to_map(
    cloud_world: np.ndarray,
    map_points: np.ndarray,
    map_normals: np.ndarray,
    config: AlignmentConfig | None = None,
    *,
    pivot_world: np.ndarray | None = None,
) -> AlignmentResult:
    """Align a robot cloud to the map with coarse-to-fine point-to-plane ICP and gate it.

    ``cloud_world`` (N, 3): the robot's points in the world frame as its pose puts them,
    metres. ``map_points`` / ``map_normals`` (M, 3): the map's voxel means (or centres) and
    unit normals, world frame (e.g. ``SemanticVoxelMap.means()`` / ``.normals()``); rows with
    a non-finite point or normal are not used. ``pivot_world`` (3,): where the offset is
    measured (e.g. the sensor or robot position); default the cloud's centroid.

    Raises :class:`MapError` for arrays of the wrong shape or type; everything else is a result
    (see the module docstring).
    """
    cfg = config if config is not None else AlignmentConfig()
    cloud = _check_array(cloud_world, "cloud_world")
    mp = _check_array(map_points, "map_points")
    mn = _check_array(map_normals, "map_normals")
    if mp.shape != mn.shape:
        raise MapError(f"map_normals: expected shape {mp.shape} like map_points, got {mn.shape}")
    pivot = None
    if pivot_world is not None:
        pivot = np.asarray(pivot_world, dtype=np.float64)
        if pivot.shape != (3,) or not np.isfinite(pivot).all():
            raise MapError(f"pivot_world: expected a finite (3,) array, got {pivot!r}")

    finite = np.isfinite(_row_sums(cloud))  # a NaN or inf anywhere in a row makes it so
    if not finite.all():
        return _rejected(f"non_finite_points: {int((~finite).sum())} of {len(cloud)} points "
                         "are NaN or inf", len(cloud))
    if len(cloud) < cfg.min_points:
        return _rejected(f"too_few_points: {len(cloud)} < {cfg.min_points}", len(cloud))
    if pivot is None:
        pivot = np.array([cloud[:, a].mean() for a in range(3)])

    margin = (cfg.crop_margin_m if cfg.crop_margin_m is not None
              else cfg.max_offset_m + max(cfg.max_correspondence_m))
    lo, hi = _column_bounds(cloud)
    use = np.isfinite(_row_sums(mn)) & _in_box(mp, lo - margin, hi + margin)  # NaN fails
    n_map = int(use.sum())
    if n_map < cfg.min_points:
        return _rejected(f"too_few_map_points: {n_map} map points with normals near the cloud "
                         f"< {cfg.min_points}", len(cloud), n_map)
    map_xyz, map_nrm = mp[use], mn[use]
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
    # finest level from the cloud, each coarser one from the next finer (cheaper, same cells)
    downsampled: list[o3d.geometry.PointCloud] = []
    for voxel in sorted(set(cfg.voxel_sizes_m)):
        source = source.voxel_down_sample(voxel)
        downsampled.append(source)
    by_size = dict(zip(sorted(set(cfg.voxel_sizes_m)), downsampled, strict=True))
    finest = min(cfg.voxel_sizes_m)

    T = np.eye(4)
    result = None
    target_nrm = map_nrm
    n_used = 0
    estimation = None
    last = len(cfg.voxel_sizes_m) - 1
    for level, (voxel, dist, iters) in enumerate(
        zip(cfg.voxel_sizes_m, cfg.max_correspondence_m, cfg.max_iterations, strict=True)
    ):
        down = by_size[voxel]
        if len(down.points) > cfg.max_points:
            down = down.uniform_down_sample(-(-len(down.points) // cfg.max_points))
        n_used = len(down.points)
        if n_used < cfg.min_points:
            if level == last:
                return _rejected(f"too_few_points: {n_used} after downsampling to {voxel} m "
                                 f"< {cfg.min_points}", n_used, n_map)
            continue  # a coarse level with too few points is skipped
        # Open3D builds a k-d tree of the target on every call: give it only the map near the
        # cloud as currently placed, and at coarse levels every k-th map point (the map's
        # points are voxel means, about one per map voxel)
        moved = np.asarray(down.points) @ T[:3, :3].T + T[:3, 3]
        moved_lo, moved_hi = _column_bounds(moved)
        near = np.flatnonzero(_in_box(map_xyz, moved_lo - dist, moved_hi + dist))
        if voxel > finest:
            near = near[:: max(1, int((voxel / finest) ** 2 / 2))]
        if len(near) < cfg.min_points:  # the cloud moved away from the map at a coarse level
            return _rejected(f"too_few_map_points: {len(near)} map points near the cloud at "
                             f"level {level} < {cfg.min_points}", n_used, n_map)
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(map_xyz[near]))
        target.normals = o3d.utility.Vector3dVector(map_nrm[near])
        # the robust kernel only on the finest level: coarse levels keep least squares and
        # their wide basin (a robust kernel there settles for partial, wrong overlaps)
        if result is None:
            # ICP on geometry that cannot hold the cloud in some direction (a floor only) has
            # a singular system and moves the cloud anywhere: judge that before any step
            start = _reg.evaluate_registration(down, target, dist, T)
            start_pairs = np.asarray(start.correspondence_set, dtype=np.int64).reshape(-1, 2)
            if len(start_pairs) >= cfg.min_points:
                start_spread = _normal_spread(map_nrm[near][start_pairs[:, 1]])
                if start_spread < cfg.min_normal_spread:
                    return _rejected(f"degenerate: normal spread {start_spread:.4f} < "
                                     f"{cfg.min_normal_spread} where the cloud lies (before "
                                     "ICP)", n_used, n_map)
        robust = cfg.robust_scale > 0 and (level == last or cfg.robust_levels == "all")
        estimation = _reg.TransformationEstimationPointToPlane(
            _reg.TukeyLoss(k=dist * cfg.robust_scale) if robust else _reg.L2Loss())
        criteria = _reg.ICPConvergenceCriteria(relative_fitness=cfg.relative_fitness,
                                               relative_rmse=cfg.relative_rmse,
                                               max_iteration=iters)
        result = _reg.registration_icp(down, target, dist, T, estimation, criteria)
        T = np.asarray(result.transformation, dtype=np.float64).copy()
        if cfg.planar:
            T = planar_part(T)
        target_nrm = np.asarray(target.normals)
    assert result is not None

    pairs = np.asarray(result.correspondence_set, dtype=np.int64).reshape(-1, 2)
    spread = _normal_spread(target_nrm[pairs[:, 1]]) if len(pairs) else 0.0
    R = T[:3, :3]
    offset_m = float(np.linalg.norm(R @ pivot + T[:3, 3] - pivot))
    offset_deg = math.degrees(math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    yaw_deg = math.degrees(math.atan2(R[1, 0], R[0, 0]))
    fitness = float(result.fitness)
    rmse = float(result.inlier_rmse) if len(pairs) else math.inf

    failed = []
    if fitness < cfg.min_fitness:
        failed.append(f"low_fitness: {fitness:.3f} < {cfg.min_fitness}")
    if rmse > cfg.max_inlier_rmse_m:
        failed.append(f"high_rmse: {rmse:.4f} m > {cfg.max_inlier_rmse_m} m")
    if offset_m > cfg.max_offset_m or offset_deg > cfg.max_offset_deg:
        failed.append(f"large_offset: {offset_m:.3f} m / {offset_deg:.2f} deg > "
                      f"{cfg.max_offset_m} m / {cfg.max_offset_deg} deg")
    if spread < cfg.min_normal_spread:
        failed.append(f"degenerate: normal spread {spread:.4f} < {cfg.min_normal_spread}")
    out = AlignmentResult(T, fitness, rmse, offset_m, offset_deg, yaw_deg, spread, n_used, n_map,
                          not failed, "; ".join(failed))
    logger.debug("ICP: accepted %s, fitness %.3f, rmse %.4f m, offset %.3f m / %.2f deg %s",
                 out.accepted, fitness, rmse, offset_m, offset_deg, out.reason)
    return out


def consistency(cloud_world: np.ndarray, map_points: np.ndarray,
                max_distance_m: float = 0.1) -> tuple[float, float]:
    """How well a cloud, as placed, agrees with the map without moving it: (fitness, inlier
    RMSE in metres), fitness the share of the cloud's points with a map point within
    ``max_distance_m`` and the RMSE over those (NaN when none). The paper's consistency measure
    of robot observations against the map (Fig. 7)."""
    cloud = _check_array(cloud_world, "cloud_world")
    mp = _check_array(map_points, "map_points")
    if len(cloud) == 0 or len(mp) == 0:
        return 0.0, math.nan
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(mp))
    res = _reg.evaluate_registration(source, target, max_distance_m, np.eye(4))
    inliers = len(np.asarray(res.correspondence_set))
    return float(res.fitness), float(res.inlier_rmse) if inliers else math.nan
