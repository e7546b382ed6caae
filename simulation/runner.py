"""Runs a scenario trajectory in simulated time and hands out the messages in arrival order.

:class:`SimulationRun` steps the robot (odometry at its rate) and the cameras (each at its own
phase) through one trajectory run, and yields :class:`TimedMessage` (``arrival_ns`` on the
common clock, the ``protocol`` message) sorted by arrival, as fast as the CPU allows. The same
stream can be published over Zenoh by :mod:`simulation.publisher`. Ground truth, the robot's
internal localization and the waypoint stops are recorded for evaluation.
"""

from __future__ import annotations

import dataclasses
import heapq
import logging
from collections.abc import Callable, Iterator

import numpy as np

from protocol.messages import Message, Odometry, PoseEstimate, RobotDetections
from simulation.detections import DetectionSimulator, FrameRequest
from simulation.robot import MotionPlan, SimulatedRobot, WaypointStop
from simulation.scenario import Scenario
from simulation.world import World

log = logging.getLogger(__name__)

#: robot → backend link latency of odometry and localization messages
LINK_LATENCY_NS = 5_000_000


@dataclasses.dataclass(frozen=True, eq=False)
class TimedMessage:
    """A message and the time (common clock, ns) it reaches the backend."""

    arrival_ns: int
    message: Message


@dataclasses.dataclass
class RunLog:
    """What happened in a run, for evaluation. Arrays grow as the run is stepped.

    ``stamps_ns`` (N,): odometry tick times; ``ground_truth`` / ``localization`` (N, 3): the
    true pose and the robot's internal localization (map frame) at those times.
    """

    stamps_ns: list[int] = dataclasses.field(default_factory=list)
    ground_truth: list[np.ndarray] = dataclasses.field(default_factory=list)
    localization: list[np.ndarray] = dataclasses.field(default_factory=list)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(stamps_ns (N,), ground truth (N, 3), localization (N, 3))."""
        return (np.array(self.stamps_ns, dtype=np.int64),
                np.array(self.ground_truth).reshape(-1, 3),
                np.array(self.localization).reshape(-1, 3))


def run_seed(scenario: Scenario, trajectory: str, reverse: bool, iteration: int,
             base_seed: int | None = None) -> np.random.SeedSequence:
    """The seed sequence of one run: distinct per (base seed, trajectory, direction,
    iteration), stable across Python processes (no ``hash()``)."""
    base = scenario.seeds.run if base_seed is None else base_seed
    tr_key = [ord(c) for c in trajectory]
    return np.random.SeedSequence([int(base), int(reverse), int(iteration), *tr_key])


class SimulationRun:
    """One run of a scenario trajectory.

    ``seed``: int or ``numpy.random.SeedSequence``; the motion, odometry, localization and
    each camera get independent child generators, so e.g. adding a camera does not change the
    robot's drift.
    """

    def __init__(self, scenario: Scenario, trajectory: str, reverse: bool = False,
                 seed: int | np.random.SeedSequence = 0,
                 world: World | None = None,
                 detector: DetectionSimulator | None = None) -> None:
        self.scenario = scenario
        self.trajectory = trajectory
        self.reverse = reverse
        if isinstance(seed, np.random.SeedSequence):
            # a fresh copy: spawn() advances the caller's sequence, and the same seed must give
            # the same run however often it is used
            ss = np.random.SeedSequence(seed.entropy, spawn_key=seed.spawn_key,
                                        pool_size=seed.pool_size)
        else:
            ss = np.random.SeedSequence(seed)
        child = ss.spawn(3 + len(scenario.site.cameras))
        self.waypoints = scenario.trajectory(trajectory, reverse)
        self.plan = MotionPlan(self.waypoints, scenario.motion, np.random.default_rng(child[0]))
        self.robot = SimulatedRobot(scenario, self.plan, np.random.default_rng(child[1]))
        self.world = world or World(scenario)
        self.detector = detector or DetectionSimulator(scenario, self.world)
        self.camera_ids = tuple(sorted(scenario.site.cameras))
        self._cam_rng = {c: np.random.default_rng(child[3 + i])
                         for i, c in enumerate(self.camera_ids)}
        phase_rng = np.random.default_rng(child[2])
        period_s = 1.0 / scenario.cameras.rate_hz
        #: first capture time (s since run start) per camera: cameras are not triggered together
        spread_s = min(scenario.cameras.phase_spread_ms * 1e-3, period_s)
        self.camera_phase_s = {c: float(phase_rng.uniform(0.0, spread_s)) for c in self.camera_ids}
        self.log = RunLog()
        self.stops: list[WaypointStop] = list(self.plan.stops)
        #: cameras that can see the robot at each stop's nominal waypoint (geometry only)
        self.stop_cameras: dict[int, tuple[str, ...]] = {
            st.index: self.detector.cameras_seeing(
                np.array([self.waypoints[st.index].x, self.waypoints[st.index].y,
                          self.waypoints[st.index].theta]))
            for st in self.stops
        }

    @property
    def duration_s(self) -> float:
        return self.plan.duration_s

    def stamp_ns(self, t_s: float) -> int:
        return self.scenario.start_stamp_ns + round(t_s * 1e9)

    def ground_truth_at(self, stamp_ns: int | np.ndarray) -> np.ndarray:
        """(N, 3) true poses at common-clock stamps."""
        t = (np.asarray(stamp_ns, dtype=np.int64) - self.scenario.start_stamp_ns) * 1e-9
        return self.plan.pose_at(t)

    def messages(self, until_s: float | None = None,
                 on_step: Callable[[float], None] | None = None,
                 localization_rate_hz: float | None = None) -> Iterator[TimedMessage]:
        """Generate the run's messages in arrival order (until the plan ends, or ``until_s``).

        ``on_step(t_s)`` is called after each simulation event (a camera frame or an odometry
        tick) and may call ``self.robot.apply_correction``: a consumer that reacts to the
        messages already yielded sees the robot respond like the real one.
        ``localization_rate_hz``: also yield the robot's own localization as a
        :class:`PoseEstimate` (source ``robot``) at about this rate, as the robot bridge
        publishes it (default: none).
        """
        end_s = self.duration_s if until_s is None else min(until_s, self.duration_s)
        cfg = self.scenario.cameras
        period_s = 1.0 / cfg.rate_hz
        odom_period_s = 1.0 / self.scenario.odometry.rate_hz
        # event queue: (t_s, order, camera_id or "" for odometry, frame index); times are
        # computed from the index, not accumulated, so no floating-point drift over long runs
        events: list[tuple[float, int, str, int]] = []
        for i, c in enumerate(self.camera_ids):
            heapq.heappush(events, (self.camera_phase_s[c], i + 1, c, 0))
        heapq.heappush(events, (odom_period_s, 0, "", 1))
        # every frame's capture time and true pose are known in advance (the plan does not
        # depend on the messages), so the detector can prepare its geometry for all at once
        frame_poses = {c: self._frame_poses(c, end_s) for c in self.camera_ids}
        for c, poses in frame_poses.items():
            self.detector.prepare_frames(c, poses)
        pending: list[tuple[int, int, Message]] = []
        counter = 0
        seq = dict.fromkeys(self.camera_ids, 0)
        #: detections of frames made ahead of their event, (camera, frame index) → message
        ready: dict[tuple[str, int], Message] = {}
        loc_every = 0
        if localization_rate_hz:
            loc_every = max(1, round(self.scenario.odometry.rate_hz / localization_rate_hz))
        loc_seq = 0
        self._record(0.0)
        while events:
            t_s, order, cam, k = heapq.heappop(events)
            if t_s > end_s + 1e-9:
                break
            now_ns = self.stamp_ns(t_s)
            while pending and pending[0][0] <= now_ns:
                arr, _, msg = heapq.heappop(pending)
                yield TimedMessage(arr, msg)
            if cam:
                rng = self._cam_rng[cam]
                frame_msg = ready.pop((cam, k), None)
                if frame_msg is None:
                    frames = self._capture(cam, k, now_ns, frame_poses, seq, ready, end_s)
                    detected = self.detector.detect_many(frames)
                    for f, m in zip(frames[1:], detected[1:], strict=True):
                        ready[(f.camera_id, f.seq)] = m
                    frame_msg = detected[0]
                seq[cam] += 1
                arrival = now_ns + self.detector.arrival_delay_ns(rng)
                heapq.heappush(events, (self.camera_phase_s[cam] + (k + 1) * period_s, order,
                                        cam, k + 1))
                heapq.heappush(pending, (arrival, counter, frame_msg))
                counter += 1
            else:
                for odom in self.robot.step_to(t_s):
                    # odometry travels over the robot's link: small constant latency
                    heapq.heappush(pending, (odom.stamp_ns + LINK_LATENCY_NS, counter, odom))
                    counter += 1
                self._record(t_s)
                if loc_every and k % loc_every == 0:
                    loc = self._localization_message(now_ns, loc_seq)
                    loc_seq += 1
                    heapq.heappush(pending, (now_ns + LINK_LATENCY_NS, counter, loc))
                    counter += 1
                heapq.heappush(events, ((k + 1) * odom_period_s, 0, "", k + 1))
            if on_step is not None:
                on_step(t_s)
        while pending:
            arr, _, msg = heapq.heappop(pending)
            yield TimedMessage(arr, msg)

    def _capture(self, camera_id: str, k: int, now_ns: int,
                 frame_poses: dict[str, np.ndarray], seq: dict[str, int],
                 ready: dict[tuple[str, int], Message], end_s: float) -> list[FrameRequest]:
        """The frame ``k`` of ``camera_id`` (captured now) and, when the detector batches
        frames (``batches_frames``), frame ``k`` of every other camera whose frame ``k - 1``
        is done: the cameras capture within one frame period of each other, and a frame's
        detections depend only on the camera, its capture time, the plan's pose then and the
        camera's own generator, which no other event draws from in between (a camera's
        arrival delay is drawn after its detections, as before)."""
        frames = [FrameRequest(camera_id, now_ns, self._frame_pose(camera_id, k, frame_poses),
                               k, self._cam_rng[camera_id])]
        if not self.detector.batches_frames:
            return frames
        period_s = 1.0 / self.scenario.cameras.rate_hz
        for c in self.camera_ids:
            # the capture time exactly as the event queue computes it
            t_c = self.camera_phase_s[c] + k * period_s if k else self.camera_phase_s[c]
            if c == camera_id or seq[c] != k or (c, k) in ready or t_c > end_s + 1e-9:
                continue
            frames.append(FrameRequest(c, self.stamp_ns(t_c),
                                       self._frame_pose(c, k, frame_poses), k,
                                       self._cam_rng[c]))
        return frames

    def _frame_pose(self, camera_id: str, k: int, frame_poses: dict[str, np.ndarray]
                    ) -> np.ndarray:
        poses = frame_poses[camera_id]
        if k < len(poses):
            return poses[k]
        period_s = 1.0 / self.scenario.cameras.rate_hz
        return self.plan.state_at(self.camera_phase_s[camera_id] + k * period_s)[0]

    def _frame_poses(self, camera_id: str, end_s: float) -> np.ndarray:
        """(N, 3) true poses at the capture times of ``camera_id``'s frames up to ``end_s``
        (the times :meth:`messages` steps through: phase + k / rate, s since the start)."""
        period_s = 1.0 / self.scenario.cameras.rate_hz
        phase_s = self.camera_phase_s[camera_id]
        poses: list[np.ndarray] = []
        k = 0
        t_s = phase_s
        while t_s <= end_s + 1e-9:
            poses.append(self.plan.state_at(t_s)[0])
            k += 1
            t_s = phase_s + k * period_s
        return np.array(poses).reshape(-1, 3)

    def _localization_message(self, stamp_ns: int, seq: int) -> PoseEstimate:
        x, y, theta = (float(v) for v in self.robot.localization_pose())
        return PoseEstimate(self.scenario.robot_id, stamp_ns, seq, x, y, theta,
                            self.robot.localization_covariance(), "robot",
                            frame_id=self.scenario.site.world_frame)

    def _record(self, t_s: float) -> None:
        self.log.stamps_ns.append(self.stamp_ns(t_s))
        self.log.ground_truth.append(self.robot.ground_truth())
        self.log.localization.append(self.robot.localization_pose())

    def run_all(self) -> list[TimedMessage]:
        """All messages of the run, in arrival order."""
        return list(self.messages())


def split_messages(stream: list[TimedMessage]) -> tuple[list[TimedMessage], list[TimedMessage]]:
    """(detections, odometry) of a message list, order kept."""
    dets = [m for m in stream if isinstance(m.message, RobotDetections)]
    odom = [m for m in stream if isinstance(m.message, Odometry)]
    return dets, odom
