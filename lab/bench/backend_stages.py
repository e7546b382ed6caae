"""CPU per frame-set by stage of the backend's pipeline, against a finite-difference peer.

The same :class:`~backend_service.pipeline.BackendPipeline` the service runs is driven
in-process (no Zenoh) with the ring site's detections, and the deployed functions are wrapped
with thread-CPU timers (about a microsecond each): decode (``protocol.decode``), sync
(:meth:`FrameSetSynchronizer.push` / ``poll``), solve (``estimate_pose`` without the
propagated covariance), covariance (``propagate_correlated``), averaging
(:meth:`MultiFrameAverager.add`), fusion (the GTSAM pose graph's updates) and publish
(``protocol.encode`` of the outputs). The peer is the finite-difference propagated
covariance: the extrinsic Jacobian by one-sided finite differences, six perturbed cameras per
camera
(:func:`finite_difference_extrinsic_jacobian`), swapped in for the closed form; everything
else is the same code in the same run, so a regression shows as a ratio.

The per-stage figures are the steady state: the first ``warmup`` frame-sets run through the
same pipeline but are not counted. The first of them has no prior (a kidnapped robot) and
is initialized by per-view PnP, which costs tens of times a steady solve at 64 cameras; it is
reported on its own (``StageFigures.first_solve_ms``), not averaged into the solve column,
where 40 frame-sets made one PnP initialization look like 5 ms of every solve.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import math
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

import protocol
from backend_service import covariance, estimate, fusion, multi_frame, pipeline, sync
from core.camera import CameraModel
from core.geometry import invert_transform, rotation_from_rotvec
from simulation.camera_ring import detection_payloads, robot_pose, write_ring_site

#: the stages, in the order a frame-set goes through them
STAGES: Final = ("decode", "sync", "solve", "covariance", "averaging", "fusion", "publish")
#: the finite-difference peer's steps: rotation (rad), translation (m)
FD_STEP_ROT: Final = 1e-4
FD_STEP_T: Final = 1e-3


def finite_difference_extrinsic_jacobian(cameras: Sequence[CameraModel],
                                         points_world: np.ndarray
                                         ) -> tuple[np.ndarray, np.ndarray]:
    """The finite-difference peer's ``(uv, G)`` of
    :func:`backend_service.covariance.project_with_extrinsic_jacobian`: per camera, six
    cameras perturbed on the left (rotation about the optical centre, world axes; position),
    each built and validated as a :class:`CameraModel` and projected."""
    uvs, Gs = [], []
    for cam in cameras:
        uv0, _ = cam.project(points_world)
        cols = []
        for k in range(6):
            rotvec, dt = np.zeros(3), np.zeros(3)
            step = FD_STEP_ROT if k < 3 else FD_STEP_T
            (rotvec if k < 3 else dt)[k % 3] = step
            T_world_cam = invert_transform(cam.T_cam_world)
            T_world_cam[:3, :3] = rotation_from_rotvec(rotvec) @ T_world_cam[:3, :3]
            T_world_cam[:3, 3] += dt
            moved = dataclasses.replace(cam, T_cam_world=invert_transform(T_world_cam))
            uv, _ = moved.project(points_world)
            cols.append((uv - uv0) / step)
        uvs.append(uv0)
        Gs.append(np.stack(cols, axis=-1))
    return np.stack(uvs), np.stack(Gs)


class NestedStageTimer:
    """Thread-CPU seconds per stage; nested stages are subtracted from their parent."""

    def __init__(self) -> None:
        self.seconds: collections.Counter[str] = collections.Counter()
        self._stack: list[list[float]] = []

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        self._stack.append([0.0])
        t0 = time.thread_time()
        try:
            yield
        finally:
            spent = time.thread_time() - t0
            inner = self._stack.pop()[0]
            self.seconds[name] += spent - inner
            if self._stack:
                self._stack[-1][0] += spent

    def wrap(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            with self.stage(name):
                return fn(*args, **kwargs)

        return timed


@contextlib.contextmanager
def _patched(clock: NestedStageTimer, finite_difference: bool) -> Iterator[None]:
    """Wrap the deployed functions with the stage timers (and swap in the peer's Jacobian)."""
    targets: list[tuple[Any, str, str]] = [
        (sync.FrameSetSynchronizer, "push", "sync"),
        (sync.FrameSetSynchronizer, "poll", "sync"),
        (pipeline, "estimate_pose", "solve"),
        (estimate, "propagate_correlated", "covariance"),
        (multi_frame.MultiFrameAverager, "add", "averaging"),
        (fusion.PoseGraphFusion, "add_camera_estimate", "fusion"),
        (fusion.PoseGraphFusion, "add_odometry", "fusion"),
    ]
    saved = [(owner, attr, getattr(owner, attr)) for owner, attr, _ in targets]
    saved.append((covariance, "project_with_extrinsic_jacobian",
                  covariance.project_with_extrinsic_jacobian))
    try:
        for owner, attr, stage in targets:
            setattr(owner, attr, clock.wrap(stage, getattr(owner, attr)))
        if finite_difference:
            covariance.project_with_extrinsic_jacobian = finite_difference_extrinsic_jacobian
        yield
    finally:
        for owner, attr, original in saved:
            setattr(owner, attr, original)


@dataclasses.dataclass(frozen=True)
class StageFigures:
    """CPU milliseconds per frame-set by stage (``per_stage_ms``, steady state: after the
    warm-up frame-sets), their sum, how many frame-sets were counted, and the CPU of the very
    first frame-set's solve and covariance (``first_solve_ms``: no prior, PnP initialization;
    once per robot start or loss)."""

    cameras: int
    frame_sets: int
    per_stage_ms: dict[str, float]
    first_solve_ms: float = math.nan

    @property
    def total_ms(self) -> float:
        return sum(self.per_stage_ms.values())


def measure_stages(n_cameras: int, frames: int = 60, *, finite_difference: bool = False,
                   rate_hz: float = 30.0, warmup: int = 5) -> StageFigures:
    """Drive one :class:`BackendPipeline` over ``warmup + frames`` frame-sets of
    ``n_cameras`` ring cameras and return the CPU per frame-set by stage of the last
    ``frames`` (``warmup`` >= 1: the first frame-set is the PnP initialization, reported
    separately)."""
    if warmup < 1:
        raise ValueError("measure_stages: warmup must be >= 1 (the PnP-initialized first "
                         "frame-set is never a steady-state figure)")
    with tempfile.TemporaryDirectory(prefix="smartedge-stages-") as tmp:
        site = write_ring_site(Path(tmp) / "ring.yaml", n_cameras)
    rng = np.random.default_rng(0)
    period_ns = round(1e9 / rate_hz)
    start_ns = 1_000_000_000
    payloads = [detection_payloads(site, robot_pose(k / rate_hz), start_ns + k * period_ns, k,
                                   rng) for k in range(warmup + frames)]
    clock = NestedStageTimer()
    solved = 0
    first_solve_ms = math.nan
    warming = True
    with _patched(clock, finite_difference):
        pipe = pipeline.BackendPipeline(site)
        for k, frame in enumerate(payloads):
            arrival_ns = start_ns + k * period_ns + 2_000_000
            for _, payload in frame:
                with clock.stage("decode"):
                    msg = protocol.decode(payload)
                out = pipe.poll(arrival_ns)
                out += pipe.feed(msg, arrival_ns)
                solved += len(out.solves)
                with clock.stage("publish"):
                    for est in (*out.camera, *out.fused):
                        protocol.encode(est)
                if solved >= 1 and math.isnan(first_solve_ms):
                    first_solve_ms = (clock.seconds["solve"] + clock.seconds["covariance"]) * 1e3
                if warming and solved >= warmup:
                    # the warm-up is over: count from here (the frame-sets solved so far,
                    # the PnP-initialized first among them, are not steady state)
                    clock.seconds.clear()
                    solved -= warmup
                    warming = False
        out = pipe.flush()
        solved += len(out.solves)
    per = {s: clock.seconds[s] * 1e3 / max(solved, 1) for s in STAGES}
    return StageFigures(n_cameras, solved, per, first_solve_ms)


def print_stage_table(camera_counts: Sequence[int], frames: int) -> None:
    """The breakdown for each camera count, the closed-form covariance against the
    finite-difference peer."""
    print(f"CPU per frame-set by stage, in-process pipeline, {frames} frame-sets per case "
          "after 5 unmeasured (ms; peer = the finite-difference covariance, "
          "same run)")
    head = "".join(f"{s:>11}" for s in STAGES)
    print(f"{'cameras':>8} {'covariance':>12}{head}{'total':>9}{'ratio':>7}{'first':>9}")
    for n in camera_counts:
        measure_stages(n, 5)  # warm-up: CasADi builds its functions for this problem size
        now = measure_stages(n, frames)
        before = measure_stages(n, frames, finite_difference=True)
        for label, fig in (("closed", now), ("finite-d", before)):
            cells = "".join(f"{fig.per_stage_ms[s]:>11.3f}" for s in STAGES)
            ratio = fig.total_ms / now.total_ms if now.total_ms > 0 else math.nan
            print(f"{n:>8} {label:>12}{cells}{fig.total_ms:>9.2f}{ratio:>6.1f}x"
                  f"{fig.first_solve_ms:>9.1f}", flush=True)
    print("first: solve + covariance CPU of the first frame-set (no prior: per-view PnP "
          "initialization, once per robot start or loss), not in the per-stage figures")
