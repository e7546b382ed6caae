"""The simulated site in real time, for the services (``--source sim`` / ``--adapter sim``,
registered into the services by :mod:`smartedge.simulated_site`; this module knows no service).

Every process that takes part in a live simulation builds the same :class:`LiveSimulation`
from the same :class:`LiveSimSpec` (scenario, trajectory, seed and the wall-clock epoch of
t = 0): the ground-truth motion is deterministic, so edge agents in separate processes see the
same robot the robot bridge drives, without exchanging ground truth. Stamps are wall-clock
nanoseconds (the scenario's start stamp is set to the epoch), so live services can compare them
with their own clock.

A fleet (``robots`` > 1, ``--sim-robots N``): N identical HSR-like robots on the crossing
routes of :mod:`simulation.fleet` (the trajectory option is not used), or with ``mixed``
(``--sim-mixed-types``) the last of them a box base (:func:`simulation.fleet.fleet_spec`), on
the scenario's site with its robots replaced by the fleet (each in its own ROS namespace:
:func:`simulation.fleet.fleet_site`); a camera's detections of all robots in one image are
merged, in random order and without robot ids, each naming its robot's model
(``Detection.robot_model``, as an edge running each type's detector reports it); each robot
bridge drives one robot (``--robot``). The rendered camera feeds draw one robot: a fleet
takes its detections from the noise model.
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from protocol.errors import UnknownIdError
from protocol.messages import RobotDetections
from simulation.runner import SimulationRun
from simulation.scenario import PAPER_SCENARIO, Scenario, load_scenario
from simulation.site_cameras import DepthNoise, SensorNoise, SiteCameraRenderer

if TYPE_CHECKING:
    from simulation.head import SimulatedHead


@dataclasses.dataclass(frozen=True)
class LiveSimSpec:
    """What all processes of one live simulation agree on."""

    scenario_path: str = str(PAPER_SCENARIO)
    trajectory: str = "traj3"
    reverse: bool = False
    seed: int = 0
    epoch_ns: int = 0
    stop_s: float | None = None
    max_speed_mps: float | None = None
    #: robots in the simulation (more than one: a fleet on the crossing routes)
    robots: int = 1
    #: a fleet of two types: the last robot a box base (``box_c``), the others HSR-like
    mixed: bool = False

    def to_argv(self) -> list[str]:
        out = [
            "--sim-scenario",
            self.scenario_path,
            "--sim-trajectory",
            self.trajectory,
            "--sim-seed",
            str(self.seed),
            "--sim-epoch-ns",
            str(self.epoch_ns),
        ]
        if self.stop_s is not None:
            out += ["--sim-stop-s", repr(self.stop_s)]
        if self.max_speed_mps is not None:
            out += ["--sim-max-speed", repr(self.max_speed_mps)]
        if self.robots != 1:
            out += ["--sim-robots", str(self.robots)]
        if self.mixed:
            out.append("--sim-mixed-types")
        return out + (["--sim-reverse"] if self.reverse else [])


def add_sim_arguments(parser: argparse.ArgumentParser) -> argparse._ArgumentGroup:
    """The ``--sim-*`` options of :class:`LiveSimSpec` (see :func:`spec_from_args`), in their
    own group, which is returned so that a plug-in can add its own simulation options."""
    group = parser.add_argument_group("simulation (only with the simulated source/adapter)")
    group.add_argument(
        "--sim-scenario",
        default=str(PAPER_SCENARIO),
        metavar="FILE",
        help="scenario file (default: the paper's lab)",
    )
    group.add_argument("--sim-trajectory", default="traj3", help="trajectory name")
    group.add_argument("--sim-reverse", action="store_true", help="run the trajectory backwards")
    group.add_argument("--sim-seed", type=int, default=0, help="noise seed")
    group.add_argument(
        "--sim-epoch-ns",
        type=int,
        default=0,
        help="wall-clock ns of t=0; every process of one simulation must agree "
        "(default: now + 2 s, fine for a single process)",
    )
    group.add_argument("--sim-stop-s", type=float, help="override the dwell at each waypoint")
    group.add_argument("--sim-max-speed", type=float, help="override the robot's top speed (m/s)")
    group.add_argument("--sim-robots", type=int, default=1, metavar="N",
                       help="identical robots on crossing routes (default 1: the scenario's "
                       "robot on --sim-trajectory)")
    group.add_argument("--sim-mixed-types", action="store_true",
                       help="a fleet of two types: the last of the --sim-robots a box base "
                       "(box_c), the others HSR-like")
    return group


def spec_from_args(args: argparse.Namespace) -> LiveSimSpec:
    epoch = args.sim_epoch_ns or time.time_ns() + 2_000_000_000
    return LiveSimSpec(
        args.sim_scenario,
        args.sim_trajectory,
        bool(args.sim_reverse),
        int(args.sim_seed),
        int(epoch),
        args.sim_stop_s,
        args.sim_max_speed,
        int(getattr(args, "sim_robots", 1) or 1),
        bool(getattr(args, "sim_mixed_types", False)),
    )


class LiveSimulation:
    """One scenario run whose t = 0 is ``spec.epoch_ns`` on the wall clock."""

    def __init__(self, spec: LiveSimSpec, scenario: Scenario | None = None) -> None:
        self.spec = spec
        base = scenario or load_scenario(Path(spec.scenario_path))
        motion = base.motion
        if spec.stop_s is not None:
            motion = dataclasses.replace(motion, stop_s=float(spec.stop_s))
        if spec.max_speed_mps is not None:
            motion = dataclasses.replace(motion, max_speed_mps=float(spec.max_speed_mps))
        self.scenario = base.with_overrides(start_stamp_ns=spec.epoch_ns, motion=motion)
        #: every robot's run, by robot id (one, unless a fleet)
        self.runs: dict[str, SimulationRun] = {}
        if spec.mixed and spec.robots < 2:
            raise ValueError("live simulation: a mixed fleet (--sim-mixed-types) needs "
                             "--sim-robots 2 or 3")
        if spec.robots == 1:
            self.runs[self.scenario.robot_id] = SimulationRun(
                self.scenario, spec.trajectory, spec.reverse, seed=spec.seed)
        else:
            self._build_fleet(spec)
        self.robot_id = next(iter(self.runs))
        self.run = self.runs[self.robot_id]
        self.site = self.scenario.site

    def _build_fleet(self, spec: LiveSimSpec) -> None:
        from simulation.fleet import (
            fleet_routes,
            fleet_site,
            fleet_spec,
            robot_scenario,
            robot_seed,
            route_waypoints,
        )

        models = fleet_spec(spec.robots, spec.mixed)
        ids = list(models)
        site = fleet_site(models, self.scenario.site.source_path)
        self.scenario = self.scenario.with_overrides(site=site, robot_id=ids[0])
        routes = fleet_routes(ids)
        for k, rid in enumerate(ids):
            self.runs[rid] = SimulationRun(
                robot_scenario(self.scenario, site, rid, route_waypoints(rid, routes[rid])),
                "route", seed=robot_seed(spec.seed, k))
        first = self.runs[ids[0]]
        for rid in ids[1:]:
            self.runs[rid].camera_phase_s = dict(first.camera_phase_s)

    @property
    def robot_ids(self) -> tuple[str, ...]:
        return tuple(self.runs)

    @property
    def duration_s(self) -> float:
        """Until the last robot ends its route."""
        return max(r.duration_s for r in self.runs.values())

    def t_s(self, now_ns: int) -> float:
        """Simulated time at wall-clock ``now_ns`` (negative before the start)."""
        return (now_ns - self.spec.epoch_ns) * 1e-9

    def ground_truth(self, stamp_ns: int, robot_id: str | None = None) -> np.ndarray:
        """(3,) true planar pose of ``robot_id`` (default: the first robot) at ``stamp_ns``
        (before the start / after the end of its route: held)."""
        run = self.runs[robot_id] if robot_id is not None else self.run
        t = min(max(self.t_s(stamp_ns), 0.0), run.duration_s)
        return run.plan.pose_at(t).reshape(-1, 3)[0]

    def finished(self, now_ns: int) -> bool:
        return self.t_s(now_ns) > self.duration_s


class CameraFeed:
    """The frames of one simulated camera as they would arrive from its edge board.

    :meth:`poll` captures every frame due up to ``now_ns`` (at the scenario's frame rate and
    this camera's phase), runs the detection model on the ground truth, and returns the
    detections whose simulated capture→arrival delay has elapsed."""

    def __init__(self, live: LiveSimulation, camera_id: str) -> None:
        if camera_id not in live.site.cameras:
            raise UnknownIdError(
                f"camera {camera_id!r} is not in the simulated site; known: "
                f"{sorted(live.site.cameras)}"
            )
        self.live = live
        self.camera_id = camera_id
        index = sorted(live.site.cameras).index(camera_id)
        self._rng = np.random.default_rng([live.spec.seed, 1000 + index])
        #: a fleet: each further robot's detection noise and the merge order, their own streams
        self._robot_rngs = {rid: np.random.default_rng([live.spec.seed, 1000 + index, k])
                            for k, rid in enumerate(live.robot_ids) if k > 0}
        self._merge_rng = np.random.default_rng([live.spec.seed, 5000 + index])
        self._period_ns = round(1e9 / live.scenario.cameras.rate_hz)
        self._phase_ns = round(live.run.camera_phase_s[camera_id] * 1e9)
        self._next_frame = 0
        self._seq = 0
        self._pending: list[tuple[int, int, RobotDetections]] = []

    def _capture_ns(self, frame: int) -> int:
        return self.live.spec.epoch_ns + self._phase_ns + frame * self._period_ns

    def poll(self, now_ns: int) -> list[RobotDetections]:
        if self._next_frame == 0 and now_ns > self._capture_ns(0):
            # joining late (or restarted): start at the current frame, not at t = 0
            self._next_frame = max(0, (now_ns - self._capture_ns(0)) // self._period_ns)
        detector = self.live.run.detector
        while self._capture_ns(self._next_frame) <= now_ns:
            capture_ns = self._capture_ns(self._next_frame)
            pose = self.live.ground_truth(capture_ns)
            msg = detector.detect(self.camera_id, capture_ns, pose, self._seq, self._rng)
            if self._robot_rngs:
                msg = self._with_fleet(msg, capture_ns)
            arrival = capture_ns + detector.arrival_delay_ns(self._rng)
            heapq.heappush(self._pending, (arrival, self._seq, msg))
            self._seq += 1
            self._next_frame += 1
        out = []
        while self._pending and self._pending[0][0] <= now_ns:
            out.append(heapq.heappop(self._pending)[2])
        return out

    def _with_fleet(self, msg: RobotDetections, capture_ns: int) -> RobotDetections:
        """``msg`` (the first robot's detection) with every other robot's in the same image,
        in random order, unnamed, each with its robot's model (a typed edge; the detection
        model's robots never occlude each other)."""
        models = self.live.site.robots
        dets = [(d, models[self.live.robot_id]) for d in msg.detections]
        for rid, rng in self._robot_rngs.items():
            other = self.live.runs[rid].detector.detect(
                self.camera_id, capture_ns, self.live.ground_truth(capture_ns, rid), self._seq,
                rng)
            dets.extend((d, models[rid]) for d in other.detections)
        order = self._merge_rng.permutation(len(dets))
        return dataclasses.replace(msg, detections=tuple(
            dataclasses.replace(dets[i][0], robot_id="", robot_model=dets[i][1])
            for i in order))


class RenderedCameraFeed:
    """The images one simulated camera takes: the site rendered from the camera's *true* pose
    (calibration error included) with the robot at its ground-truth pose at the capture time,
    plus per-frame sensor noise (:mod:`simulation.site_cameras`).

    Same capture schedule as :class:`CameraFeed` (the scenario's rate, the camera's phase);
    ``rate_hz`` overrides the rate (a CPU that cannot render and infer every frame). A caller
    that falls behind gets the newest due frame; :attr:`skipped` counts the ones it missed.
    The GL renderer is created on first use, in the calling process."""

    def __init__(self, live: LiveSimulation, camera_id: str, rate_hz: float | None = None,
                 texture_seed: int = 0, noise: SensorNoise | None = None) -> None:
        if camera_id not in live.site.cameras:
            raise UnknownIdError(
                f"camera {camera_id!r} is not in the simulated site; known: "
                f"{sorted(live.site.cameras)}"
            )
        self.live = live
        self.camera_id = camera_id
        self.images = SiteCameraRenderer(live.scenario, texture_seed=texture_seed, noise=noise)
        self.camera = self.images.camera(camera_id)
        rate = rate_hz or live.scenario.cameras.rate_hz
        self.rate_hz = float(rate)
        self._period_ns = round(1e9 / rate)
        self._phase_ns = round(live.run.camera_phase_s[camera_id] * 1e9)
        index = sorted(live.site.cameras).index(camera_id)
        self._rng = np.random.default_rng([live.spec.seed, 2000 + index])
        self._depth_rng: np.random.Generator | None = None
        self._next_frame: int | None = None
        self.skipped = 0
        self.seq = 0

    def _capture_ns(self, frame: int) -> int:
        return self.live.spec.epoch_ns + self._phase_ns + frame * self._period_ns

    def due(self, now_ns: int) -> int | None:
        """The capture stamp of the newest frame due at ``now_ns`` not yet taken, or None."""
        newest = (now_ns - self._capture_ns(0)) // self._period_ns
        if newest < 0:
            return None
        if self._next_frame is None:
            self._next_frame = int(newest)  # joining late: start at the current frame
        if newest < self._next_frame:
            return None
        self.skipped += int(newest - self._next_frame)
        self._next_frame = int(newest) + 1
        self.seq += 1
        return self._capture_ns(int(newest))

    def render(self, capture_ns: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB image at ``capture_ns``."""
        return self.images.render(self.camera_id, self.live.ground_truth(capture_ns), self._rng)

    def depth(self, capture_ns: int) -> np.ndarray:
        """(H, W) float32 depth aligned to the image at ``capture_ns`` (camera-frame z, metres,
        0 = none), with the depth noise (its own random stream, so asking for depth does not
        change the colour images). Reuses the render of that frame."""
        if self._depth_rng is None:
            index = sorted(self.live.site.cameras).index(self.camera_id)
            self._depth_rng = np.random.default_rng([self.live.spec.seed, 3000 + index])
        return self.images.depth(self.camera_id, self.live.ground_truth(capture_ns),
                                 self._depth_rng)


class HeadCameraFeed:
    """The robot's head RGB-D camera (the site file's ``head_camera`` of the robot model),
    rendered from the robot's *true* pose at ``rate_hz`` (frames at t = k / rate_hz), with
    sensor and depth noise. A caller that falls behind gets the newest due frame
    (:attr:`skipped` counts the others). The GL renderer is created on first use.

    ``head``: a :class:`simulation.head.SimulatedHead` that pans and tilts; each frame is
    rendered with its true ``T_base_cam`` at the capture stamp (:meth:`T_base_cam`).
    ``None``: the fixed mounting of the site file."""

    def __init__(self, live: LiveSimulation, rate_hz: float = 1.0, texture_seed: int = 0,
                 noise: SensorNoise | None = None, depth_noise: DepthNoise | None = None,
                 head: SimulatedHead | None = None) -> None:
        head_camera = live.site.robot_model(live.robot_id).head_camera
        if head_camera is None:
            raise UnknownIdError(
                f"robot model of {live.robot_id!r} has no head_camera in "
                f"{live.site.source_path}")
        if not rate_hz > 0:
            raise ValueError(f"head camera rate {rate_hz} Hz: must be > 0")
        self.live = live
        self.head = head_camera
        self.moving_head = head
        self.camera_id = f"{live.robot_id}_head"
        self.camera = head_camera.camera_model(self.camera_id)
        self.images = SiteCameraRenderer(live.scenario, texture_seed=texture_seed, noise=noise,
                                         depth_noise=depth_noise)
        self.rate_hz = float(rate_hz)
        self._period_ns = round(1e9 / self.rate_hz)
        self._rng = np.random.default_rng([live.spec.seed, 4000])
        self._next_frame: int | None = None
        self.skipped = 0
        self.seq = 0

    def due(self, now_ns: int) -> int | None:
        """The capture stamp of the newest frame due at ``now_ns`` not yet taken, or None."""
        newest = (now_ns - self.live.spec.epoch_ns) // self._period_ns
        if newest < 0:
            return None
        if self._next_frame is None:
            self._next_frame = int(newest)
        if newest < self._next_frame:
            return None
        self.skipped += int(newest - self._next_frame)
        self._next_frame = int(newest) + 1
        self.seq += 1
        return self.live.spec.epoch_ns + int(newest) * self._period_ns

    def T_base_cam(self, capture_ns: int) -> np.ndarray:
        """The camera's true (4, 4) pose in the robot base at ``capture_ns`` (the fixed
        mounting, or the moving head's)."""
        if self.moving_head is None:
            return np.array(self.head.T_base_cam, np.float64)
        return self.moving_head.T_base_cam(capture_ns)

    def render(self, capture_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The frame at ``capture_ns``: (H, W, 3) uint8 RGB with sensor noise, (H, W) float32
        depth (optical-frame z, metres, 0 = none) with depth noise, and the renderer's exact
        (H, W) int32 class ids (for tests and ground-truth segmentation)."""
        out = self.images.render_head(
            self.head, self.live.ground_truth(capture_ns), self.camera_id,
            None if self.moving_head is None else self.moving_head.T_base_cam(capture_ns))
        image = self.images.add_noise(out.color_rgb, self._rng) \
            if self.images.noise.sigma_dn > 0 else out.color_rgb
        depth = self.images.depth_noise.apply(out.depth_m, self._rng)
        return image, depth, out.class_id

    def release(self) -> None:
        self.images.release()
