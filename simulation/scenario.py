"""Scenario files: what happens on a simulated site (room, obstacles, waypoints, trajectories,
motion, sensor noise, seeds). The cameras and the robot model come from the site file the
scenario names, so the simulation and the services read the very same calibration.

Loading validates everything and raises :class:`ScenarioError` naming the file and the dotted
key (``waypoints.WP3.xy_m``, ``noise.sigma_px``...). Unknown keys are errors.
See ``simulation/sites/paper_lab.scenario.yaml`` for every key, documented.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

import numpy as np

from core.config_file import ConfigReader, read_yaml_file
from core.geometry import rotation_z, wrap_angle
from core.site import Site, load_site
from protocol.errors import ConfigFileError, SiteConfigError

SITES_DIR: Final = Path(__file__).resolve().parent / "sites"
PAPER_SCENARIO: Final = SITES_DIR / "paper_lab.scenario.yaml"


class ScenarioError(ConfigFileError, ValueError):
    """A scenario file is missing or invalid; names the file and the key."""


@dataclasses.dataclass(frozen=True, eq=False)
class Box:
    """An obstacle: a box standing on the floor (or raised by ``z_min_m``).

    ``center_xy_m``: (2,) centre in the world frame; ``size_m``: (3,) extent along its own
    x, y and z; ``yaw_rad``: rotation about world z; ``z_min_m``: height of its bottom face.
    """

    name: str
    center_xy_m: np.ndarray
    size_m: np.ndarray
    yaw_rad: float = 0.0
    z_min_m: float = 0.0


@dataclasses.dataclass(frozen=True)
class Waypoint:
    """A named stop pose (x, y in metres, theta in radians) in the world frame."""

    name: str
    x: float
    y: float
    theta: float


@dataclasses.dataclass(frozen=True)
class MotionConfig:
    """Differential drive: straight legs and turns in place with trapezoidal profiles; the robot
    dwells ``stop_s`` at each waypoint (``start_s`` at the first) and stops within
    ``goal_sigma_m``/``goal_sigma_deg`` (std) of it, like a navigation goal tolerance."""

    max_speed_mps: float = 0.3
    accel_mps2: float = 0.3
    max_yaw_rate_radps: float = 0.6
    yaw_accel_radps2: float = 1.0
    stop_s: float = 6.0
    start_s: float = 2.0
    goal_sigma_m: float = 0.02
    goal_sigma_deg: float = 1.0


@dataclasses.dataclass(frozen=True)
class OdometryConfig:
    """Wheel odometry: rate, systematic scale errors and random walk per metre / radian."""

    rate_hz: float = 20.0
    scale_sigma: float = 0.01
    yaw_scale_sigma: float = 0.01
    sigma_m_per_sqrt_m: float = 0.005
    sigma_rad_per_sqrt_m: float = 0.004
    sigma_rad_per_sqrt_rad: float = 0.01


@dataclasses.dataclass(frozen=True)
class LocalizationConfig:
    """Internal (LiDAR/particle-filter) localization error: an Ornstein-Uhlenbeck process over
    travelled distance (mean-reverting: it does not grow without bound, like AMCL on a map
    that does not match the cluttered room). Stationary std per axis ``stationary_sigma_m``,
    correlation length ``correlation_length_m``; heading likewise, turning in place counting as
    ``turn_equivalent_m_per_rad`` metres per radian. ``init_*``: error right after the
    initialization from the cameras at the start of a run."""

    stationary_sigma_m: float = 0.16
    correlation_length_m: float = 6.0
    stationary_sigma_deg: float = 1.2
    turn_equivalent_m_per_rad: float = 0.5
    init_sigma_m: float = 0.02
    init_sigma_deg: float = 0.5


@dataclasses.dataclass(frozen=True)
class CameraSimConfig:
    """Camera timing and calibration error.

    ``rate_hz`` frames per second; ``phase_spread_ms``: the cameras free-run at the same rate
    with capture phases spread uniformly over this interval (NTP-synchronized, not
    hardware-triggered); ``latency_ms`` mean capture→arrival delay, ``jitter_ms`` its
    std (arrival only, half-normal); ``clock_residual_ms``: std of each camera's remaining clock
    error after the site's ``clock_offset_ns`` is applied; ``calib_translation_sigma_m`` /
    ``calib_rotation_sigma_deg``: std of the difference between the true camera pose and the
    calibrated one in the site file; ``max_range_m``: robot farther away is not detected.
    """

    rate_hz: float = 15.0
    phase_spread_ms: float = 10.0
    latency_ms: float = 60.0
    jitter_ms: float = 8.0
    clock_residual_ms: float = 1.0
    calib_translation_sigma_m: float = 0.015
    calib_rotation_sigma_deg: float = 0.1
    max_range_m: float = 11.0
    min_visible_keypoints: int = 6
    miss_probability: float = 0.02


@dataclasses.dataclass(frozen=True)
class NoiseConfig:
    """Keypoint detector error model (pixels unless stated).

    Each detection gets a common shift (``sigma_shift_px``) and a relative scale error about its
    centroid (``sigma_scale``: top-down detectors resize a crop, so bounding-box errors move
    all keypoints together), then independent noise per keypoint ``sigma_px`` (times
    ``self_occluded_factor`` for keypoints on the far side of the robot). Keypoints drop out
    with ``dropout_probability`` (score 0) and become gross outliers with
    ``outlier_probability`` (displaced uniformly by up to ``outlier_max_px``, high score).
    """

    sigma_px: float = 1.0
    sigma_shift_px: float = 0.5
    sigma_scale: float = 0.025
    self_occluded_factor: float = 1.5
    dropout_probability: float = 0.03
    outlier_probability: float = 0.01
    outlier_max_px: float = 25.0
    obstacle_occluded_score: float = 0.15


@dataclasses.dataclass(frozen=True)
class Seeds:
    """``calibration``: the (fixed) calibration error of the site; ``run``: base of per-run
    seeds (motion noise, odometry, localization, detections)."""

    calibration: int = 7
    run: int = 0


@dataclasses.dataclass(frozen=True, eq=False)
class ClutterRegion:
    """An axis-aligned floor area (``min_xy_m``, ``max_xy_m``: (2,) world frame, metres) where
    the LiDAR sees mostly clutter that is not in its map: the internal localization's
    stationary error (position and heading) is ``localization_sigma_factor`` times larger."""

    name: str
    min_xy_m: np.ndarray
    max_xy_m: np.ndarray
    localization_sigma_factor: float = 1.0

    def contains(self, xy: np.ndarray) -> bool:
        p = np.asarray(xy, dtype=np.float64)[:2]
        return bool(np.all(p >= self.min_xy_m) and np.all(p <= self.max_xy_m))


@dataclasses.dataclass(frozen=True)
class RobustnessConfig:
    """Failure model of the robustness experiment (paper Sec. IV-D, docs/simulation.md).

    A run fails with "WP not reached" when, on arrival at a waypoint, the robot's true position
    is more than ``waypoint_tolerance_m`` from where its localization says it is (the goal
    tolerance of a navigation stack), and with "emergency stop" when its true footprint
    (radius of the robot model plus ``collision_margin_m``) touches an obstacle or a wall.
    ``runs``: runs per condition (paper: 5 without and 5 with correction feedback).
    """

    waypoint_tolerance_m: float = 0.3
    collision_margin_m: float = 0.0
    runs: int = 5


@dataclasses.dataclass(frozen=True, eq=False)
class Scenario:
    """A loaded, validated scenario with its site."""

    name: str
    site: Site
    robot_id: str
    room_min_xy_m: np.ndarray
    room_max_xy_m: np.ndarray
    room_height_m: float
    obstacles: tuple[Box, ...]
    waypoints: Mapping[str, Waypoint]
    trajectories: Mapping[str, tuple[str, ...]]
    motion: MotionConfig
    odometry: OdometryConfig
    localization: LocalizationConfig
    cameras: CameraSimConfig
    noise: NoiseConfig
    seeds: Seeds
    start_stamp_ns: int
    source_path: str = "<memory>"
    #: waypoint sequences used by single experiments (not part of the Table I/II set)
    routes: Mapping[str, tuple[str, ...]] = dataclasses.field(default_factory=dict)
    #: waypoints only routes use (Fig. 6 and Table I show ``waypoints`` only)
    route_waypoints: Mapping[str, Waypoint] = dataclasses.field(default_factory=dict)
    clutter: tuple[ClutterRegion, ...] = ()
    robustness: RobustnessConfig = dataclasses.field(default_factory=RobustnessConfig)

    def trajectory(self, name: str, reverse: bool = False) -> tuple[Waypoint, ...]:
        """The waypoints of a trajectory or route, in order (reversed for the reverse run)."""
        names = self.trajectories.get(name, self.routes.get(name))
        if names is None:
            raise KeyError(
                f"trajectory {name!r} is not in {self.source_path}; known: "
                f"{sorted(self.trajectories)}, routes {sorted(self.routes)}"
            )
        seq = tuple(self.waypoints[n] if n in self.waypoints else self.route_waypoints[n]
                    for n in names)
        return tuple(reversed(seq)) if reverse else seq

    def with_overrides(self, **changes: Any) -> Scenario:
        """A copy with some top-level fields replaced (e.g. ``noise=...``, ``motion=...``)."""
        return dataclasses.replace(self, **changes)

    def localization_sigma_factor_at(self, xy: np.ndarray) -> float:
        """Factor on the internal localization's stationary error at floor point ``xy`` (2,):
        the largest factor of the clutter regions containing it, 1 outside all of them."""
        factor = 1.0
        for region in self.clutter:
            if region.contains(xy):
                factor = max(factor, region.localization_sigma_factor)
        return factor


# --------------------------------------------------------------------------------------------
# parsing
# --------------------------------------------------------------------------------------------

_TOP_KEYS: Final = {
    "scenario", "site_file", "robot_id", "room", "obstacles", "waypoints", "trajectories",
    "motion", "odometry", "localization", "cameras", "noise", "seeds", "start_stamp_s",
    "routes", "route_waypoints", "clutter", "robustness",
}


class _Ctx(ConfigReader):
    """The shared config checks, raising :class:`ScenarioError`, plus scenario sections."""

    def __init__(self, path: str) -> None:
        super().__init__(path, ScenarioError)

    def config(self, key: str, value: Any, cls: type) -> Any:
        section = self.section(key, value, cls)
        for f in dataclasses.fields(cls):
            val = getattr(section, f.name)
            if f.name.endswith("probability") and val > 1.0:
                raise self.fail(f"{key}.{f.name}", "a probability must lie in [0, 1]")
            if f.name.endswith("rate_hz") and val <= 0:
                raise self.fail(f"{key}.{f.name}", "must be > 0")
        return section


def parse_scenario(doc: Any, path: str = "<memory>", base_dir: Path | None = None,
                   site: Site | None = None) -> Scenario:
    """Validate an already-parsed scenario document; ``site`` overrides ``site_file``."""
    ctx = _Ctx(path)
    base_dir = base_dir or Path(".")
    top = ctx.mapping("", doc)
    ctx.no_unknown("", top, _TOP_KEYS)
    name = str(top.get("scenario", Path(path).stem))
    if site is None:
        if "site_file" not in top:
            raise ctx.fail("site_file", "required key is missing")
        site_path = Path(str(top["site_file"]))
        if not site_path.is_absolute():
            site_path = base_dir / site_path
        try:
            site = load_site(site_path)
        except SiteConfigError as exc:
            raise ctx.fail("site_file", f"invalid site file: {exc}") from None
    robot_id = str(top.get("robot_id", next(iter(site.robots))))
    if robot_id not in site.robots:
        raise ctx.fail("robot_id", f"{robot_id!r} is not a robot of the site {sorted(site.robots)}")

    room = ctx.mapping("room", top.get("room"))
    ctx.no_unknown("room", room, {"min_xy_m", "max_xy_m", "height_m"})
    if "min_xy_m" not in room or "max_xy_m" not in room:
        raise ctx.fail("room", "needs min_xy_m and max_xy_m")
    rmin = ctx.vector("room.min_xy_m", room["min_xy_m"], 2)
    rmax = ctx.vector("room.max_xy_m", room["max_xy_m"], 2)
    if np.any(rmax <= rmin):
        raise ctx.fail("room.max_xy_m", "must be larger than min_xy_m on both axes")
    height = ctx.number("room.height_m", room.get("height_m", 3.0), lo=0.5, hi=100.0)

    obstacles: list[Box] = []
    obs_node = top.get("obstacles", []) or []
    if not isinstance(obs_node, list):
        raise ctx.fail("obstacles", "expected a list of boxes")
    for i, ob in enumerate(obs_node):
        key = f"obstacles[{i}]"
        ob = ctx.mapping(key, ob)
        ctx.no_unknown(key, ob, {"name", "center_xy_m", "size_m", "yaw_deg", "z_min_m"})
        for req in ("center_xy_m", "size_m"):
            if req not in ob:
                raise ctx.fail(f"{key}.{req}", "required key is missing")
        size = ctx.vector(f"{key}.size_m", ob["size_m"], 3)
        if np.any(size <= 0):
            raise ctx.fail(f"{key}.size_m", "sizes must be > 0")
        obstacles.append(Box(
            name=str(ob.get("name", f"box{i}")),
            center_xy_m=ctx.vector(f"{key}.center_xy_m", ob["center_xy_m"], 2),
            size_m=size,
            yaw_rad=math.radians(ctx.number(f"{key}.yaw_deg", ob.get("yaw_deg", 0.0))),
            z_min_m=ctx.number(f"{key}.z_min_m", ob.get("z_min_m", 0.0), lo=0.0),
        ))

    wp_node = ctx.mapping("waypoints", top.get("waypoints"))
    if len(wp_node) < 2:
        raise ctx.fail("waypoints", "define at least two waypoints")
    waypoints = _waypoints(ctx, "waypoints", wp_node, rmin, rmax, obstacles)
    route_waypoints = _waypoints(
        ctx, "route_waypoints", ctx.mapping("route_waypoints", top.get("route_waypoints") or {}),
        rmin, rmax, obstacles)
    for wp_name in route_waypoints:
        if wp_name in waypoints:
            raise ctx.fail(f"route_waypoints.{wp_name}", "a waypoint has the same name")

    tr_node = ctx.mapping("trajectories", top.get("trajectories"))
    if not tr_node:
        raise ctx.fail("trajectories", "define at least one trajectory")
    trajectories = _sequences(ctx, "trajectories", tr_node, waypoints)
    routes = _sequences(ctx, "routes", ctx.mapping("routes", top.get("routes") or {}),
                        {**waypoints, **route_waypoints})
    for route_name in routes:
        if route_name in trajectories:
            raise ctx.fail(f"routes.{route_name}", "a trajectory has the same name")

    clutter: list[ClutterRegion] = []
    cl_node = top.get("clutter", []) or []
    if not isinstance(cl_node, list):
        raise ctx.fail("clutter", "expected a list of regions")
    for i, reg in enumerate(cl_node):
        key = f"clutter[{i}]"
        reg = ctx.mapping(key, reg)
        ctx.no_unknown(key, reg, {"name", "min_xy_m", "max_xy_m", "localization_sigma_factor"})
        for req in ("min_xy_m", "max_xy_m"):
            if req not in reg:
                raise ctx.fail(f"{key}.{req}", "required key is missing")
        lo = ctx.vector(f"{key}.min_xy_m", reg["min_xy_m"], 2)
        hi = ctx.vector(f"{key}.max_xy_m", reg["max_xy_m"], 2)
        if np.any(hi <= lo):
            raise ctx.fail(f"{key}.max_xy_m", "must be larger than min_xy_m on both axes")
        clutter.append(ClutterRegion(
            name=str(reg.get("name", f"clutter{i}")), min_xy_m=lo, max_xy_m=hi,
            localization_sigma_factor=ctx.number(
                f"{key}.localization_sigma_factor", reg.get("localization_sigma_factor", 1.0),
                lo=0.0, hi=100.0),
        ))
    robustness = ctx.config("robustness", top.get("robustness"), RobustnessConfig)
    if robustness.runs < 1:
        raise ctx.fail("robustness.runs", "must be >= 1")

    seeds = ctx.config("seeds", top.get("seeds"), Seeds)
    start_s = ctx.number("start_stamp_s", top.get("start_stamp_s", 1.7e9), lo=0.0, hi=4e9)
    return Scenario(
        name=name, site=site, robot_id=robot_id, room_min_xy_m=rmin, room_max_xy_m=rmax,
        room_height_m=height, obstacles=tuple(obstacles), waypoints=waypoints,
        trajectories=trajectories,
        motion=ctx.config("motion", top.get("motion"), MotionConfig),
        odometry=ctx.config("odometry", top.get("odometry"), OdometryConfig),
        localization=ctx.config("localization", top.get("localization"), LocalizationConfig),
        cameras=ctx.config("cameras", top.get("cameras"), CameraSimConfig),
        noise=ctx.config("noise", top.get("noise"), NoiseConfig),
        seeds=seeds, start_stamp_ns=round(start_s * 1e9), source_path=path,
        routes=routes, route_waypoints=route_waypoints, clutter=tuple(clutter),
        robustness=robustness,
    )


def _waypoints(ctx: _Ctx, section: str, node: Mapping[str, Any], rmin: np.ndarray,
               rmax: np.ndarray, obstacles: list[Box]) -> dict[str, Waypoint]:
    """Validated waypoints of ``waypoints`` or ``route_waypoints``."""
    out: dict[str, Waypoint] = {}
    for wp_name, wp in node.items():
        key = f"{section}.{wp_name}"
        wp = ctx.mapping(key, wp)
        ctx.no_unknown(key, wp, {"xy_m", "theta_deg"})
        if "xy_m" not in wp:
            raise ctx.fail(f"{key}.xy_m", "required key is missing")
        xy = ctx.vector(f"{key}.xy_m", wp["xy_m"], 2)
        if np.any(xy <= rmin) or np.any(xy >= rmax):
            raise ctx.fail(f"{key}.xy_m", "lies outside the room")
        for b in obstacles:
            if point_in_box_xy(xy, b):
                raise ctx.fail(f"{key}.xy_m", f"lies inside obstacle {b.name!r}")
        theta = math.radians(ctx.number(f"{key}.theta_deg", wp.get("theta_deg", 0.0),
                                        lo=-360, hi=360))
        out[str(wp_name)] = Waypoint(str(wp_name), float(xy[0]), float(xy[1]), wrap_angle(theta))
    return out


def _sequences(ctx: _Ctx, section: str, node: Mapping[str, Any],
               waypoints: Mapping[str, Waypoint]) -> dict[str, tuple[str, ...]]:
    """Validated waypoint sequences of ``trajectories`` or ``routes``."""
    out: dict[str, tuple[str, ...]] = {}
    for tr_name, seq in node.items():
        key = f"{section}.{tr_name}"
        if not isinstance(seq, list) or len(seq) < 2:
            raise ctx.fail(key, "expected a list of at least two waypoint names")
        for j, wp_name in enumerate(seq):
            if str(wp_name) not in waypoints:
                raise ctx.fail(f"{key}[{j}]", f"unknown waypoint {wp_name!r}")
            if j and str(seq[j - 1]) == str(wp_name):
                raise ctx.fail(f"{key}[{j}]", "repeats the previous waypoint")
        out[str(tr_name)] = tuple(str(s) for s in seq)
    return out


def load_scenario(path: str | Path = PAPER_SCENARIO, site: Site | None = None) -> Scenario:
    """Load and validate a scenario file (default: the paper's lab)."""
    p = Path(path)
    doc = read_yaml_file(p, "scenario file", ScenarioError)
    return parse_scenario(doc, str(p), p.parent, site)


def point_in_box_xy(xy: np.ndarray, box: Box, margin_m: float = 0.0) -> bool:
    """Whether a floor point lies inside a box's footprint (grown by ``margin_m``)."""
    local = (np.asarray(xy, float) - box.center_xy_m) @ rotation_z(box.yaw_rad)[:2, :2]  # box frame
    return bool(np.all(np.abs(local) <= box.size_m[:2] / 2 + margin_m))
