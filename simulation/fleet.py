"""Several robots on one simulated site: a fleet, as the cameras see it.

Every robot drives its own route through its own :class:`~simulation.runner.SimulationRun`
(its motion, drifting odometry, own localization and the detection noise model, from its own
seed); the runs share the cameras' capture phases (one camera takes one image of all robots),
and each camera image's detections of all robots are merged into one
:class:`~protocol.messages.RobotDetections` message in random order with no robot id, as an
edge agent reports robots it cannot tell apart. Which robot each detection truly is stays
beside the stream (:attr:`FleetRun.truth`), never in it.

A fleet may mix robot types (a :data:`FleetSpec`: robot id → robot model, e.g.
:data:`MIXED_FLEET`: two HSR-like robots and a box base): each robot moves, is occluded and
is detected with its own model's keypoints and footprint, and its detections carry the model's
name in ``Detection.robot_model``, as an edge that runs one detector per type reports them
(``typed``; ``typed=False`` strips it: an untyped edge). The models a site file lacks are
taken from the built-in two-type lab (``simulation/sites/two_types_lab.yaml``), so the fleet
can stand on any site with the paper lab's cameras.

The messages are generated lazily and in arrival order (:meth:`FleetRun.messages`), so a
consumer that reacts to them (a robot bridge pushing corrections) sees every robot respond,
as :meth:`SimulationRun.messages` allows for one robot.

The detection model knows one robot per image: robots do not occlude each other in the
merged images (docs/evaluation.md, "Fleet").
"""

from __future__ import annotations

import dataclasses
import heapq
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np
import yaml

from core.site import RobotModel, Site, parse_site
from protocol.messages import Message, RobotDetections
from simulation.runner import SimulationRun, TimedMessage
from simulation.scenario import SITES_DIR, Scenario, Waypoint, load_scenario

#: route waypoints: (x m, y m, heading deg) in the world frame
RoutePoints = Sequence[tuple[float, float, float]]
#: a fleet: robot id → the name of its robot model (in the site's ``robot_models``)
FleetSpec = Mapping[str, str]

#: three identical robots on the paper lab whose routes cross and pass within 0.5 m: ``hsr_a``
#: and ``hsr_b`` drive past each other on lanes 0.48 m apart (centres), ``hsr_c`` crosses both
#: lanes north to south behind them and comes back, passing each on its way
CROSSING_ROUTES: Mapping[str, RoutePoints] = {
    "hsr_a": ((8.5, 5.76, 0.0), (11.5, 5.76, 0.0), (11.5, 4.2, -90.0)),
    "hsr_b": ((11.5, 6.24, 180.0), (8.5, 6.24, 180.0), (8.5, 7.8, 90.0)),
    "hsr_c": ((10.0, 8.4, -90.0), (10.0, 3.6, -90.0), (10.6, 3.6, 0.0)),
}


#: the second robot type of a mixed fleet: the built-in box base (simulation/robot_mesh.py)
BOX_MODEL = "box_base"
#: the site whose ``robot_models`` define the built-in types a site file may lack
TWO_TYPES_SITE = SITES_DIR / "two_types_lab.yaml"
#: a fleet of two types: the HSR-like ``hsr_a`` and ``hsr_b`` passing each other 0.47-0.49 m
#: apart (centres), and the box base ``box_c`` crossing both lanes north to south behind them
#: (:data:`BOX_ROUTE`)
MIXED_FLEET: Mapping[str, str] = {"hsr_a": "hsr", "hsr_b": "hsr", "box_c": BOX_MODEL}
#: the box base's crossing route: ``hsr_c``'s, started 0.2 m further north, so that its wider
#: body (0.5 x 0.4 m) passes behind ``hsr_b`` with 5-8 cm between the bodies (0.58-0.61 m
#: between the centres, seeds 3-7) where the round ``hsr_c`` passes 0.44-0.47 m from it
BOX_ROUTE: RoutePoints = ((10.0, 8.6, -90.0), (10.0, 3.6, -90.0), (10.6, 3.6, 0.0))
#: the route of every fleet robot id: :data:`CROSSING_ROUTES` and the box base's
FLEET_ROUTES: Mapping[str, RoutePoints] = {**CROSSING_ROUTES, "box_c": BOX_ROUTE}


def fleet_robot_ids(count: int, mixed: bool = False) -> list[str]:
    """The ids of a fleet of ``count`` robots (:func:`fleet_spec`)."""
    return list(fleet_spec(count, mixed))


def fleet_spec(count: int, mixed: bool = False) -> dict[str, str]:
    """A fleet of ``count`` robots (1 to 3) on the crossing routes, robot id → model: all
    HSR-like (the first of :data:`CROSSING_ROUTES`), or ``mixed``: the last one a box base
    (``box_c`` on :data:`BOX_ROUTE`; three robots: :data:`MIXED_FLEET`)."""
    ids = list(CROSSING_ROUTES)
    if not 1 <= count <= len(ids):
        raise ValueError(f"fleet: {count} robots: the crossing routes take 1 to {len(ids)}")
    if not mixed:
        return dict.fromkeys(ids[:count], "hsr")
    if count < 2:
        raise ValueError("fleet: a mixed fleet needs at least 2 robots (an HSR and a box base)")
    return {**dict.fromkeys(ids[:count - 1], "hsr"), "box_c": BOX_MODEL}


def fleet_routes(robot_ids: Sequence[str]) -> dict[str, RoutePoints]:
    """The crossing routes of ``robot_ids`` (ids of :data:`FLEET_ROUTES`)."""
    unknown = [r for r in robot_ids if r not in FLEET_ROUTES]
    if unknown:
        raise ValueError(f"fleet: no crossing route for {unknown}; known: "
                         f"{list(FLEET_ROUTES)}")
    return {rid: FLEET_ROUTES[rid] for rid in robot_ids}


def _as_spec(robots: Sequence[str] | FleetSpec, model: str) -> dict[str, str]:
    """``robots`` as a :data:`FleetSpec` (a sequence of ids: all of ``model``)."""
    if isinstance(robots, Mapping):
        return {str(k): str(v) for k, v in robots.items()}
    ids = list(robots)
    if len(set(ids)) != len(ids):
        raise ValueError(f"fleet: robot ids must be distinct and at least one: {ids!r}")
    return dict.fromkeys(ids, model)


def _fleet_document(path: Path, spec: Mapping[str, str], namespaces: bool
                    ) -> dict[str, object]:
    """The site file at ``path`` as a document with its robots replaced by ``spec``; a model
    the file lacks is copied from :data:`TWO_TYPES_SITE` (the built-in types)."""
    if not spec:
        raise ValueError("fleet: robot ids must be distinct and at least one: []")
    doc = yaml.safe_load(path.read_text())
    models = doc.setdefault("robot_models", {})
    missing = sorted(set(spec.values()) - set(models))
    if missing:
        builtin = yaml.safe_load(TWO_TYPES_SITE.read_text())["robot_models"]
        unknown = [m for m in missing if m not in builtin]
        if unknown:
            raise ValueError(f"fleet: robot model(s) {unknown} are neither in {path} nor "
                             f"built in ({sorted(builtin)})")
        models.update({m: builtin[m] for m in missing})
    doc["robots"] = [{"id": rid, "model": model, **({"ros": {"namespace": rid}}
                                                    if namespaces else {})}
                     for rid, model in spec.items()]
    return doc


def fleet_site(robots: Sequence[str] | FleetSpec, site_path: str | Path | None = None,
               model: str = "hsr", namespaces: bool = True) -> Site:
    """The site of ``site_path`` (default: the paper lab) with its robots replaced by
    ``robots``: ids, all of ``model``, or a :data:`FleetSpec` (id → model; a model the site
    file lacks comes from :data:`TWO_TYPES_SITE`); ``namespaces``: each robot's ROS topics in
    its own namespace (its id), as a fleet's site file needs them (``smartedge site check``)."""
    path = Path(site_path) if site_path is not None else SITES_DIR / "paper_lab.yaml"
    doc = _fleet_document(path, _as_spec(robots, model), namespaces)
    return parse_site(doc, str(path), path.parent)


def fleet_site_document(site: Site, robots: Sequence[str] | FleetSpec, model: str = "hsr"
                        ) -> dict[str, object]:
    """The site file (as a YAML document) of ``site`` with ``robots`` (ids of ``model``, or
    a :data:`FleetSpec`) in their own ROS namespaces: what the demo writes for a fleet.
    Written elsewhere than ``site``'s folder, relative file paths in it (robot model files)
    would resolve against the new folder: the paper lab has none."""
    return _fleet_document(Path(site.source_path), _as_spec(robots, model), True)


def route_waypoints(robot_id: str, points: RoutePoints) -> list[Waypoint]:
    """A robot's route as scenario waypoints (names ``<robot>_<i>``, headings in radians)."""
    return [Waypoint(f"{robot_id}_{i}", float(x), float(y), math.radians(float(t)))
            for i, (x, y, t) in enumerate(points)]


def robot_scenario(base: Scenario, site: Site, robot_id: str,
                   route: Sequence[Waypoint]) -> Scenario:
    """``base`` on ``site`` for ``robot_id`` with one route named ``route``."""
    waypoints = {w.name: w for w in route}
    return base.with_overrides(site=site, robot_id=robot_id,
                               route_waypoints={**base.route_waypoints, **waypoints},
                               routes={**base.routes, "route": tuple(waypoints)})


def robot_seed(seed: int, index: int) -> np.random.SeedSequence:
    """The seed of the ``index``-th robot of a fleet run: the same robot driving alone with
    this seed moves, drifts and is detected exactly as in the fleet."""
    return np.random.SeedSequence([int(seed), int(index)])


@dataclasses.dataclass(frozen=True, eq=False)
class FleetRun:
    """A fleet's run. ``runs``: each robot's simulation run (ground truth:
    :meth:`true_pose`); ``until_s``: simulated seconds (the shortest route when not given);
    ``truth``: filled while :meth:`messages` runs: for each merged detections message (by
    ``id``; the messages are kept alive with it), the true robot of each of its detections,
    in order. A robot whose route ends before ``until_s`` stops sending (its run ends).
    ``typed``: every detection names its robot's model (``Detection.robot_model``, as an edge
    running one detector per type reports it); ``False``: ``""`` (an untyped edge)."""

    site: Site
    runs: Mapping[str, SimulationRun]
    until_s: float
    seed: int
    typed: bool = True
    truth: dict[int, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    _kept: list[Message] = dataclasses.field(default_factory=list, repr=False)

    @property
    def robot_ids(self) -> tuple[str, ...]:
        return tuple(self.runs)

    def model_of(self, robot_id: str) -> str:
        """The name of ``robot_id``'s robot model."""
        return self.site.robots[robot_id]

    def true_pose(self, robot_id: str, stamp_ns: int) -> np.ndarray:
        """(3,) the robot's true pose at a common-clock stamp."""
        return self.runs[robot_id].ground_truth_at(np.array([stamp_ns]))[0]

    def true_poses(self, stamp_ns: int) -> dict[str, np.ndarray]:
        return {rid: self.true_pose(rid, stamp_ns) for rid in self.runs}

    def messages(self, localization_rate_hz: float | None = None,
                 localization: Sequence[str] | None = None,
                 on_step: Callable[[str, float], None] | None = None
                 ) -> Iterator[TimedMessage]:
        """Every robot's messages in arrival order, the detections of one camera image merged
        (random order, no robot id, the robot's model when :attr:`typed`; arrival: the latest
        of the robots' parts).
        ``localization``: the robots whose own localization is published at
        ``localization_rate_hz`` (default: all). ``on_step(robot_id, t_s)``: after each
        simulation event of that robot's run (it may correct the robot). Once per run: the
        robots' simulations are stepped as the messages are made."""
        if self._kept or self.truth:
            # a SimulationRun is stepped once: its robot and generators have moved on
            raise RuntimeError("fleet: a FleetRun's messages can be generated once; build "
                               "a new one (fleet_run) for another pass")
        with_loc = set(self.runs if localization is None else localization)
        gens: dict[str, Iterator[TimedMessage]] = {}
        for rid, run in self.runs.items():
            step = None if on_step is None else _bind(on_step, rid)
            gens[rid] = run.messages(
                until_s=self.until_s, on_step=step,
                localization_rate_hz=localization_rate_hz if rid in with_loc else None)
        rng = np.random.default_rng(self.seed)
        order = {rid: k for k, rid in enumerate(self.runs)}
        heap: list[tuple[int, int, TimedMessage]] = []
        for rid, gen in gens.items():
            _push(heap, gen, order[rid])
        names = list(self.runs)
        #: (camera, stamp) → the robots' parts so far: (arrival, message, robot)
        frames: dict[tuple[str, int], list[tuple[int, RobotDetections, str]]] = {}
        while heap:
            arrival, k, tm = heapq.heappop(heap)
            _push(heap, gens[names[k]], k)
            msg = tm.message
            if not isinstance(msg, RobotDetections):
                yield tm
                continue
            key = (msg.camera_id, int(msg.stamp_ns))
            parts = frames.setdefault(key, [])
            parts.append((arrival, msg, names[k]))
            if len(parts) >= self._robots_in_frame(msg):
                del frames[key]
                yield self._merge(parts, rng)
        if frames:  # the runs disagree on which images exist: a bug, not a fleet
            raise RuntimeError(f"fleet: {len(frames)} camera images incomplete at the end, "
                               f"e.g. {next(iter(frames))}")

    def _robots_in_frame(self, msg: RobotDetections) -> int:
        """How many of the robots' runs take the image of ``msg``: those whose run has not
        ended at its capture time (a run ends at ``until_s`` or at the end of its route)."""
        run0 = next(iter(self.runs.values()))
        cam = self.site.cameras[msg.camera_id]
        period_s = 1.0 / run0.scenario.cameras.rate_hz
        t_s = (int(msg.stamp_ns) + int(cam.clock_offset_ns)
               - run0.scenario.start_stamp_ns) * 1e-9
        k = round((t_s - run0.camera_phase_s[msg.camera_id]) / period_s)
        t_capture = run0.camera_phase_s[msg.camera_id] + k * period_s
        return sum(1 for r in self.runs.values()
                   if t_capture <= min(self.until_s, r.duration_s) + 1e-9)

    def _merge(self, parts: list[tuple[int, RobotDetections, str]],
               rng: np.random.Generator) -> TimedMessage:
        dets = [(d, rid) for _, m, rid in parts for d in m.detections]
        order = rng.permutation(len(dets))
        msg = dataclasses.replace(parts[0][1], detections=tuple(
            dataclasses.replace(dets[i][0], robot_id="",
                                robot_model=self.model_of(dets[i][1]) if self.typed else "")
            for i in order))
        self.truth[id(msg)] = tuple(dets[i][1] for i in order)
        self._kept.append(msg)  # its id stays its own while the truth is kept
        return TimedMessage(max(a for a, _, _ in parts), msg)

    def min_distance(self, step_s: float = 0.05) -> tuple[float, float, str, str]:
        """Closest approach of two robots over the run (true poses): (distance m, time s since
        the start, robot, robot)."""
        ids = list(self.runs)
        t = np.arange(0.0, self.until_s + 1e-9, step_s)
        xy = {rid: self.runs[rid].plan.pose_at(t)[:, :2] for rid in ids}
        best = (math.inf, 0.0, "", "")
        for i, a in enumerate(ids):
            for b in ids[i + 1:]:
                d = np.hypot(*(xy[a] - xy[b]).T)
                j = int(np.argmin(d))
                if d[j] < best[0]:
                    best = (float(d[j]), float(t[j]), a, b)
        return best


def _bind(on_step: Callable[[str, float], None], robot_id: str) -> Callable[[float], None]:
    return lambda t_s: on_step(robot_id, t_s)


def _push(heap: list[tuple[int, int, TimedMessage]], gen: Iterator[TimedMessage], k: int
          ) -> None:
    nxt = next(gen, None)
    if nxt is not None:
        heapq.heappush(heap, (nxt.arrival_ns, k, nxt))


def fleet_run(routes: Mapping[str, RoutePoints], until_s: float | None = None, seed: int = 3,
              site: Site | None = None, scenario: Scenario | None = None,
              typed: bool = True) -> FleetRun:
    """The robots of ``routes`` (robot id → waypoints (x m, y m, heading deg), world frame)
    on ``site`` (default: :func:`fleet_site` of the paper lab with these robots, all
    HSR-like), each driving its route from ``robot_seed(seed, index)``, for ``until_s``
    simulated seconds (default: until the shortest route ends, so every robot is in every
    image); ``typed``: :attr:`FleetRun.typed`. Each robot moves and is detected with its own
    model of ``site`` (keypoints, footprint, height)."""
    ids = list(routes)
    site = site or fleet_site(ids)
    missing = [rid for rid in ids if rid not in site.robots]
    if missing:
        raise ValueError(f"fleet: robots {missing} are not on site {site.name!r}")
    base = scenario or load_scenario()
    runs: dict[str, SimulationRun] = {}
    for k, rid in enumerate(ids):
        runs[rid] = SimulationRun(
            robot_scenario(base, site, rid, route_waypoints(rid, routes[rid])), "route",
            seed=robot_seed(seed, k))
    first = runs[ids[0]]
    for rid in ids[1:]:
        runs[rid].camera_phase_s = dict(first.camera_phase_s)  # one camera, one capture time
    end_s = min(r.duration_s for r in runs.values())
    return FleetRun(site, runs, end_s if until_s is None else until_s, seed, typed)


def alone_run(fleet: FleetRun, robot_id: str, scenario: Scenario | None = None
              ) -> SimulationRun:
    """``robot_id`` of ``fleet`` driving its route alone: a site with only that robot (of its
    model), the same seed and camera phases, so it moves, drifts and is detected as in the
    fleet."""
    ids = list(fleet.runs)
    fr = fleet.runs[robot_id]
    site = fleet_site({robot_id: fleet.model_of(robot_id)}, fleet.site.source_path)
    base = scenario or load_scenario()
    run = SimulationRun(robot_scenario(base, site, robot_id, fr.waypoints), "route",
                        seed=robot_seed(fleet.seed, ids.index(robot_id)))
    run.camera_phase_s = dict(fr.camera_phase_s)
    return run


def footprint_gap_m(fleet: FleetRun, a: str, b: str, pose_a: np.ndarray, pose_b: np.ndarray
                    ) -> float:
    """Free space between robots ``a`` and ``b`` of ``fleet`` at planar poses ``pose_a`` /
    ``pose_b`` (world frame): each robot's body outline is the convex hull of its keypoints'
    floor projections, grown to its footprint radius for a round base (an HSR: a circle); a
    negative gap is an overlap. Sampled outlines (72 points per circle), exact to ~1 mm."""
    pa = _outline(fleet.site.robot_model(a), pose_a)
    pb = _outline(fleet.site.robot_model(b), pose_b)
    if _inside_any(pa, pb) or _inside_any(pb, pa):
        return -1.0
    return float(min(_point_segment_m(pa, pb).min(), _point_segment_m(pb, pa).min()))


def _outline(model: RobotModel, pose: np.ndarray) -> np.ndarray:
    """(K, 2) world-frame outline (counter-clockwise) of a robot model's base at ``pose``."""
    kp = np.asarray(model.keypoints_base_m, np.float64)[:, :2]
    r = float(model.footprint_radius_m)
    radii = np.hypot(kp[:, 0], kp[:, 1])
    if np.ptp(radii) < 0.1 * r:  # keypoints (nearly) on a circle: a round base
        ang = np.linspace(0.0, 2 * math.pi, 72, endpoint=False)
        pts = np.column_stack([r * np.cos(ang), r * np.sin(ang)])
    else:  # a polygonal base: the hull of its keypoints
        pts = _hull(kp)
    x, y, th = (float(v) for v in np.asarray(pose, np.float64)[:3])
    c, s = math.cos(th), math.sin(th)
    return pts @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def _hull(points: np.ndarray) -> np.ndarray:
    """Convex hull (counter-clockwise) of (N, 2) points (monotone chain)."""
    pts = sorted({(float(p[0]), float(p[1])) for p in points})

    def half(seq: list[tuple[float, float]]) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        for p in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _inside_any(points: np.ndarray, polygon: np.ndarray) -> bool:
    """Whether any of ``points`` lies inside the convex counter-clockwise ``polygon``."""
    a, b = polygon, np.roll(polygon, -1, axis=0)
    cross = ((b[None, :, 0] - a[None, :, 0]) * (points[:, None, 1] - a[None, :, 1])
             - (b[None, :, 1] - a[None, :, 1]) * (points[:, None, 0] - a[None, :, 0]))
    return bool(np.any(np.all(cross >= 0.0, axis=1)))


def _point_segment_m(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(N,) distance of each point to the nearest edge of ``polygon``."""
    a, b = polygon, np.roll(polygon, -1, axis=0)
    ab = b - a
    ap = points[:, None, :] - a[None]
    t = np.clip(np.sum(ap * ab[None], axis=2) / np.maximum(np.sum(ab * ab, axis=1), 1e-12),
                0.0, 1.0)
    d = ap - t[..., None] * ab[None]
    return np.min(np.hypot(d[..., 0], d[..., 1]), axis=1)


def min_footprint_gap(fleet: FleetRun, step_s: float = 0.05) -> tuple[float, float, str, str]:
    """The smallest :func:`footprint_gap_m` of two robots over the run (true poses):
    (gap m, time s since the start, robot, robot)."""
    ids = list(fleet.runs)
    t = np.arange(0.0, fleet.until_s + 1e-9, step_s)
    poses = {rid: fleet.runs[rid].plan.pose_at(t) for rid in ids}
    best = (math.inf, 0.0, "", "")
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            d = np.hypot(*(poses[a][:, :2] - poses[b][:, :2]).T)
            for j in np.flatnonzero(d < 1.5):  # only near each other can they touch
                gap = footprint_gap_m(fleet, a, b, poses[a][j], poses[b][j])
                if gap < best[0]:
                    best = (gap, float(t[j]), a, b)
    return best


def merged_messages(fleet: FleetRun, localization_rate_hz: float | None = None,
                    localization: Sequence[str] | None = None) -> list[tuple[int, Message]]:
    """All of :meth:`FleetRun.messages` as (arrival_ns, message) pairs."""
    return [(tm.arrival_ns, tm.message)
            for tm in fleet.messages(localization_rate_hz, localization)]
