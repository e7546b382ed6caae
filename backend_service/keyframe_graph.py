"""The sliding-window keyframe graph that :class:`~backend_service.fusion.PoseGraphFusion` fills.

Planar keyframes (GTSAM ``Pose2`` of the robot base in the map frame, each with the odometry
``T_odom_robot`` at its stamp) kept in stamp order; the factors on them (odometry
``BetweenFactorPose2`` between consecutive keyframes, camera / initial / marginal
``PriorFactorPose2``), each remembered as a :class:`GraphFactor` record so the graph can be
rebuilt; one incremental ISAM2; and the marginalization that bounds it: the dropped keyframes'
factors folded into one Gaussian prior on the oldest kept keyframe, ISAM2 rebuilt over the kept
ones.

What enters the graph and when (the keyframe policy, the input checks, anchoring, the odometry
noise model) is the fusion's; this module holds and solves the graph. Covariances of records
are in the body frame of their measurement, as GTSAM keeps them.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
from collections.abc import Callable

import gtsam
import numpy as np

logger = logging.getLogger(__name__)


@dataclasses.dataclass
class Keyframe:
    """A variable of the graph: ``key`` (a GTSAM symbol) at ``stamp_ns`` where the odometry read
    ``T_odom_robot`` (with its covariance along odom axes, ``None`` unless the fusion uses the
    odometry's own covariances)."""

    key: int
    stamp_ns: int
    T_odom_robot: gtsam.Pose2
    cov_odom: np.ndarray | None


@dataclasses.dataclass
class GraphFactor:
    """What a factor in the graph is, so the graph can be rebuilt after marginalization.

    ``kind``: ``between`` (key_from → key_to), ``camera`` / ``initial`` / ``marginal`` (unary on
    key_to). ``cov_body``: (3, 3) in the body frame of ``measured``. ``robust``: wrapped in the
    graph's robust kernel. ``index``: slot in ISAM2.
    """

    kind: str
    key_from: int
    key_to: int
    measured: gtsam.Pose2
    cov_body: np.ndarray
    robust: bool
    index: int = -1
    #: the GTSAM factor, built once (a marginalization re-adds the kept factors to a new ISAM2)
    built: gtsam.NonlinearFactor | None = dataclasses.field(default=None, repr=False,
                                                            compare=False)


@dataclasses.dataclass
class FactorBatch:
    """New factors and values for one ISAM2 update; records get their slot after it."""

    graph: gtsam.NonlinearFactorGraph = dataclasses.field(
        default_factory=gtsam.NonlinearFactorGraph
    )
    values: gtsam.Values = dataclasses.field(default_factory=gtsam.Values)
    remove: list[int] = dataclasses.field(default_factory=list)
    records: list[GraphFactor] = dataclasses.field(default_factory=list)


class KeyframeGraph:
    """Keyframes, factor records and the ISAM2 over them, for one robot.

    ``robust_kernel`` (``huber`` or ``cauchy``; ``none`` for no robust record) with
    ``robust_threshold`` (sigmas) wraps the records marked ``robust``; ``relinearize_threshold``
    is ISAM2's. Not thread-safe (one fusion, one worker).
    """

    def __init__(self, robot_id: str, *, robust_kernel: str, robust_threshold: float,
                 relinearize_threshold: float) -> None:
        self.robot_id = robot_id
        self.robust_kernel = robust_kernel
        self.robust_threshold = robust_threshold
        self.relinearize_threshold = relinearize_threshold
        self._next_key = 0  # keys stay unique across resets
        self.reset()

    # ----------------------------------------------------------------------------------------
    # what the graph holds
    # ----------------------------------------------------------------------------------------

    def reset(self) -> None:
        """An empty graph (keys keep counting)."""
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.relinearize_threshold)
        params.relinearizeSkip = 1
        # reuse slots of factors removed when splitting between factors (bounded graph)
        params.findUnusedFactorSlots = True
        self._isam = gtsam.ISAM2(params)
        #: keyframes in stamp order, and their stamps (for bisection)
        self.keyframes: list[Keyframe] = []
        self.stamps: list[int] = []
        self._between: dict[int, GraphFactor] = {}  # by key_from
        self._priors: dict[int, list[GraphFactor]] = {}  # by key_to
        self._latest_cache: tuple[int, gtsam.Pose2, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self.keyframes)

    def new_key(self) -> int:
        key = gtsam.symbol("x", self._next_key)
        self._next_key += 1
        return key

    def index_at(self, stamp_ns: int) -> int:
        """Index of the last keyframe at or before ``stamp_ns`` (-1: before the first)."""
        return bisect.bisect_right(self.stamps, stamp_ns) - 1

    def factor_records(self) -> int:
        return len(self._between) + sum(len(v) for v in self._priors.values())

    def graph_size(self) -> tuple[int, int]:
        """(variables, factors) currently held by ISAM2 (removed factor slots not counted)."""
        factors = self._isam.getFactorsUnsafe()
        live = sum(1 for i in range(factors.size()) if factors.exists(i))
        return int(self._isam.size()), live

    # ----------------------------------------------------------------------------------------
    # building
    # ----------------------------------------------------------------------------------------

    def add(self, batch: FactorBatch, record: GraphFactor) -> None:
        """Add ``record`` (its GTSAM factor built once) to ``batch``."""
        if record.built is None:
            record.built = self._build(record)
        batch.graph.add(record.built)
        batch.records.append(record)

    def _build(self, record: GraphFactor) -> gtsam.NonlinearFactor:
        noise = gtsam.noiseModel.Gaussian.Covariance(record.cov_body)
        if record.robust:
            if self.robust_kernel == "cauchy":
                kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(self.robust_threshold)
            else:
                kernel = gtsam.noiseModel.mEstimator.Huber.Create(self.robust_threshold)
            noise = gtsam.noiseModel.Robust.Create(kernel, noise)
        if record.kind == "between":
            return gtsam.BetweenFactorPose2(record.key_from, record.key_to, record.measured,
                                            noise)
        return gtsam.PriorFactorPose2(record.key_to, record.measured, noise)

    def start(self, kf: Keyframe, T_world_robot: gtsam.Pose2, batch: FactorBatch) -> None:
        """Empty the graph and root it at ``kf`` (initial value ``T_world_robot``); the caller
        adds the prior that anchors it to ``batch`` and runs :meth:`update`."""
        self.reset()
        self.keyframes.append(kf)
        self.stamps.append(kf.stamp_ns)
        batch.values.insert(kf.key, T_world_robot)

    def insert(self, kf: Keyframe, between: Callable[[Keyframe, Keyframe], GraphFactor],
               batch: FactorBatch) -> bool:
        """Add ``kf`` (after the first keyframe) to ``batch``: appended to the chain or, for a
        stamp between two keyframes, splitting their between factor in two (``between(a, b)``
        makes the odometry record a → b). True when it split one."""
        i = self.index_at(kf.stamp_ns)
        prev = self.keyframes[i]
        before = between(prev, kf)
        T_world_prev = self._isam.calculateEstimatePose2(prev.key)
        batch.values.insert(kf.key, T_world_prev.compose(before.measured))
        self.add(batch, before)
        split = i + 1 < len(self.keyframes)
        if split:
            old = self._between.pop(prev.key)
            batch.remove.append(old.index)
            self.add(batch, between(kf, self.keyframes[i + 1]))
        self.keyframes.insert(i + 1, kf)
        self.stamps.insert(i + 1, kf.stamp_ns)
        return split

    def update(self, batch: FactorBatch, iterations: int = 1) -> bool:
        """One ISAM2 update with ``batch`` (+ ``iterations - 1`` relinearization steps). False
        when GTSAM refused the system (indeterminant): the graph is then empty, logged."""
        try:
            result = self._isam.update(batch.graph, batch.values, batch.remove)
            for _ in range(iterations - 1):
                self._isam.update()
        except RuntimeError as exc:
            # GTSAM raises on indeterminant systems; start over rather than stop the service
            logger.warning("robot %s: ISAM2 update failed (%s); graph reset", self.robot_id, exc)
            self.reset()
            return False
        for record, index in zip(batch.records, result.getNewFactorsIndices(), strict=True):
            record.index = int(index)
            if record.kind == "between":
                self._between[record.key_from] = record
            else:
                self._priors.setdefault(record.key_to, []).append(record)
        self._latest_cache = None
        return True

    # ----------------------------------------------------------------------------------------
    # estimates
    # ----------------------------------------------------------------------------------------

    def estimate(self, key: int) -> gtsam.Pose2:
        """Optimized ``T_world_robot`` of ``key``."""
        return self._isam.calculateEstimatePose2(key)

    def estimate_and_cov(self, key: int) -> tuple[gtsam.Pose2, np.ndarray]:
        """Optimized pose of ``key`` and its (3, 3) marginal covariance in its body frame (the
        latest keyframe's cached until the next update)."""
        cache = self._latest_cache
        if cache is not None and cache[0] == key:
            return cache[1], cache[2]
        pose = self._isam.calculateEstimatePose2(key)
        cov = np.asarray(self._isam.marginalCovariance(key), dtype=np.float64)
        if key == self.keyframes[-1].key:
            self._latest_cache = (key, pose, cov)
        return pose, cov

    def poses(self) -> np.ndarray:
        """(K, 3) optimized x, y, theta of every keyframe."""
        poses = np.zeros((len(self.keyframes), 3))
        if self.keyframes:
            values = self._isam.calculateEstimate()
            for i, kf in enumerate(self.keyframes):
                p = values.atPose2(kf.key)
                poses[i] = (p.x(), p.y(), p.theta())
        return poses

    # ----------------------------------------------------------------------------------------
    # bounded memory
    # ----------------------------------------------------------------------------------------

    def droppable(self, window_ns: int, max_keyframes: int) -> int:
        """Keyframes older than ``window_ns`` before the latest or beyond ``max_keyframes``,
        keeping at least the latest."""
        if not self.keyframes:
            return 0
        n = len(self.keyframes)
        too_old = bisect.bisect_left(self.stamps, self.stamps[-1] - window_ns)
        return min(max(too_old, n - max_keyframes), n - 1)

    def marginalize(self, drop: int) -> bool:
        """Fold keyframes ``[:drop]`` into a Gaussian prior on keyframe ``drop`` (the new root)
        and rebuild ISAM2 over the kept keyframes, linearized at the current estimate. False
        when the rebuilt graph failed its update (then empty, as :meth:`update`).

        The prior is what the dropped factors alone say about the root: mean = the root in the
        optimum of the dropped sub-graph, covariance = the root's marginal there. (Using the
        full-graph estimate or marginal would count the kept factors twice.)"""
        values = self._isam.calculateEstimate()
        dropped, kept = self.keyframes[:drop], self.keyframes[drop:]
        root = kept[0]
        old_graph = gtsam.NonlinearFactorGraph()
        old_values = gtsam.Values()
        for kf in dropped:
            for record in self._priors.pop(kf.key, []):
                old_graph.add(record.built)
            old_graph.add(self._between.pop(kf.key).built)
            old_values.insert(kf.key, values.atPose2(kf.key))
        old_values.insert(root.key, values.atPose2(root.key))
        try:
            optimum = gtsam.GaussNewtonOptimizer(old_graph, old_values).optimize()
            T_world_root = optimum.atPose2(root.key)
            cov_root = np.asarray(gtsam.Marginals(old_graph, optimum).marginalCovariance(root.key))
        except RuntimeError as exc:
            # conservative fallback (over-confident by the kept factors, but never fails)
            logger.warning("robot %s: marginalization failed (%s)", self.robot_id, exc)
            T_world_root = values.atPose2(root.key)
            cov_root = np.asarray(self._isam.marginalCovariance(root.key))
        marginal = GraphFactor("marginal", -1, root.key, T_world_root,
                               0.5 * (cov_root + cov_root.T), robust=False)
        batch = FactorBatch()
        self.add(batch, marginal)
        for kf in kept:
            batch.values.insert(kf.key, values.atPose2(kf.key))
            for record in self._priors.pop(kf.key, []):
                self.add(batch, record)
            if kf.key in self._between:
                self.add(batch, self._between.pop(kf.key))
        self._isam = gtsam.ISAM2(self._isam.params())
        self.keyframes = list(kept)
        self.stamps = [kf.stamp_ns for kf in kept]
        return self.update(batch)
