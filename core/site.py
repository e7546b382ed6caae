"""The site file: cameras, robot models, robots, thresholds and the clock policy of one site.

A site file is YAML (see ``deploy/site.example.yaml`` for every key, documented). Loading it
validates everything and raises :class:`~protocol.errors.SiteConfigError` naming the file and the
dotted key that is wrong (``cameras[2].K``, ``thresholds.sync_windw_ms``...). Camera intrinsics can
also come from an OpenCV ``FileStorage`` YAML or a ROS ``camera_info`` YAML
(:func:`load_camera_calibration`). The ``clock`` section is the site's one clock policy
(:class:`ClockPolicy`): every service judges stamps with it.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

import numpy as np
import yaml

from core.camera import DISTORTION_LENGTHS, CameraModel
from core.config_file import ConfigReader, join_key, read_yaml_file
from core.geometry import invert_transform, quaternion_to_rotation, rotation_from_rpy
from protocol.errors import SiteConfigError, UnknownIdError

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True, eq=False)
class HeadCamera:
    """A robot's own RGB-D camera (the HSR's head Xtion), rigidly mounted on the base.

    ``width``, ``height`` in pixels; ``K`` (3, 3) intrinsics in pixels; ``dist`` OpenCV
    distortion coefficients (0, 4, 5 or 8); ``T_base_cam`` (4, 4) maps the camera's optical
    frame (z forward, x right, y down) into the robot base frame (x forward, y left, z up, origin
    on the ground at the rotation centre), metres, with the head at rest (pan = tilt = 0). Depth
    is aligned to the colour image. A head that pans or tilts publishes the camera's pose on
    ``/tf``; ``smartedge robot-camera --source ros`` looks it up at each image's stamp and uses
    this block only to check the robot's ``CameraInfo``.
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    T_base_cam: np.ndarray

    def camera_model(self, camera_id: str = "head",
                     T_world_base: np.ndarray | None = None) -> CameraModel:
        """The camera as a :class:`CameraModel` whose "world" is the frame ``T_world_base``
        maps the base into (``None``: the base frame itself)."""
        T_world_cam = self.T_base_cam if T_world_base is None else (
            np.asarray(T_world_base, np.float64) @ self.T_base_cam)
        return CameraModel(camera_id, self.width, self.height, np.array(self.K),
                           np.array(self.dist), invert_transform(T_world_cam))


@dataclasses.dataclass(frozen=True, eq=False)
class RobotModel:
    """Keypoints defined on the rigid robot base.

    ``keypoints_base_m``: (M, 3) keypoint positions in the robot base frame (x forward, y left,
    z up, origin on the ground at the rotation centre), metres, in the order the detector
    outputs them. ``footprint_radius_m``: radius of the base. ``height_m``: height of the body
    (used for occlusion and rendering in simulation). ``detector_onnx`` / ``keypoints_onnx``:
    the edge's models for this robot (site file key ``models: {detector, keypoints}``, paths
    relative to the site file; ``None``: the shipped models of the built-in robot).
    ``head_camera``: the robot's own RGB-D camera (site file key ``head_camera``), ``None``
    when it has none.
    """

    name: str
    keypoint_names: tuple[str, ...]
    keypoints_base_m: np.ndarray
    footprint_radius_m: float
    height_m: float = 1.0
    detector_onnx: Path | None = None
    keypoints_onnx: Path | None = None
    head_camera: HeadCamera | None = None

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoint_names)


@dataclasses.dataclass(frozen=True)
class Thresholds:
    """Tunable parameters of the pipeline; all have defaults, units in the names.

    Sync: ``sync_window_ms`` (stamps within this window form one frame-set),
    ``sync_max_wait_ms`` (how long a frame-set waits for late cameras), ``camera_timeout_s``
    (a camera silent for longer is considered gone), ``max_camera_rate_hz`` (a camera sending
    faster is flagged as a rogue source and its excess frames dropped); how far ahead or how
    old a stamp may be is the ``clock`` section's (:class:`ClockPolicy`). Pose:
    ``min_keypoint_score``, ``min_keypoints`` (per view),
    ``max_reprojection_rmse_px`` (estimates above are rejected), ``single_camera_max_dtheta_deg``
    and ``single_camera_max_ddepth_m`` (the paper's d_theta and d_depth), ``multi_frame_count``
    (frame-sets averaged while static). Robot bridge: ``static_max_speed_mps``,
    ``static_max_yaw_rate_radps``, ``static_dwell_s``, ``correction_min_offset_m``,
    ``correction_min_offset_deg``, ``correction_max_jump_m`` and ``correction_max_jump_deg``
    (distance and heading limits of one correction, also against the localization without the
    bridge's corrections of the window), ``correction_max_std_m``, ``correction_min_interval_s``,
    ``correction_window_s`` with ``correction_window_max_m`` / ``correction_window_max_deg``
    (total correction allowed per window).
    """

    sync_window_ms: float = 20.0
    sync_max_wait_ms: float = 100.0
    camera_timeout_s: float = 2.0
    max_camera_rate_hz: float = 60.0
    min_keypoint_score: float = 0.3
    min_keypoints: int = 4
    max_reprojection_rmse_px: float = 20.0
    single_camera_max_dtheta_deg: float = 10.0
    single_camera_max_ddepth_m: float = 0.15
    multi_frame_count: int = 5
    static_max_speed_mps: float = 0.01
    static_max_yaw_rate_radps: float = 0.02
    static_dwell_s: float = 1.0
    correction_min_offset_m: float = 0.05
    correction_min_offset_deg: float = 2.0
    correction_max_jump_m: float = 1.0
    correction_max_jump_deg: float = 30.0
    correction_max_std_m: float = 0.15
    correction_min_interval_s: float = 2.0
    correction_window_s: float = 60.0
    correction_window_max_m: float = 1.0
    correction_window_max_deg: float = 30.0


@dataclasses.dataclass(frozen=True)
class ClockPolicy:
    """The site's one clock policy (site file section ``clock``): how every service judges a
    message's ``stamp_ns`` against its own clock (its wall clock on the site's common time
    base, e.g. chrony; in a replay, the ``now_ns`` the replay passes).

    ``max_future_ms``: how far ahead of the receiver's clock a stamp may be; a message stamped
    further ahead is refused and counted (backend synchronizer ``future``, backend pipeline
    ``odometry_future`` / ``localization_future``, robot bridge ``future_stamp_*``, mapper
    ``future_stamp``): one such stamp would otherwise hold back every message after it.
    ``max_age_ms``: how old an input may be when it is used: a pose older than this when it
    would be published is dropped (backend ``stale_dropped``, the bridge's pose output
    ``stale_*``); a solve's prior (the robot's own localization, the last camera estimate) is
    used only when stamped within this of the frame-set; a camera estimate waits for the
    odometry to cover its stamp only when it is at most this far ahead of the newest odometry
    (fusion ``camera_future``). The mapper derives its longer horizon for semantic clouds from
    it (``mapper.mapping.CLOUD_AGE_FACTOR``).
    """

    max_future_ms: float = 100.0
    max_age_ms: float = 1000.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_future_ms) and self.max_future_ms >= 0):
            raise ValueError(f"max_future_ms must be finite and >= 0, got {self.max_future_ms}")
        if not (math.isfinite(self.max_age_ms) and self.max_age_ms > 0):
            raise ValueError(f"max_age_ms must be finite and > 0, got {self.max_age_ms}")

    @property
    def max_future_ns(self) -> int:
        return round(self.max_future_ms * 1e6)

    @property
    def max_age_ns(self) -> int:
        return round(self.max_age_ms * 1e6)

    def too_far_ahead(self, stamp_ns: int, now_ns: int) -> bool:
        """``stamp_ns`` is more than ``max_future_ms`` after ``now_ns`` (the receiver's clock)."""
        return stamp_ns - now_ns > self.max_future_ns

    def too_old(self, stamp_ns: int, now_ns: int) -> bool:
        """``stamp_ns`` is more than ``max_age_ms`` before ``now_ns`` (the receiver's clock)."""
        return now_ns - stamp_ns > self.max_age_ns


@dataclasses.dataclass(frozen=True)
class Site:
    """A loaded, validated site: ``cameras`` by id, ``robot_models`` by name, ``robots`` maps a
    robot id to its model name; ``robot_ros`` the raw per-robot overrides of the ``ros`` section
    (a robot entry's ``ros:`` mapping; :meth:`ros_section` merges them)."""

    name: str
    world_frame: str
    cameras: Mapping[str, CameraModel]
    robot_models: Mapping[str, RobotModel]
    robots: Mapping[str, str]
    thresholds: Thresholds = dataclasses.field(default_factory=Thresholds)
    source_path: str = "<memory>"
    #: raw package-owned sections (:data:`PACKAGE_SECTIONS`); each package parses its own
    sections: Mapping[str, Mapping[str, Any]] = dataclasses.field(
        default_factory=lambda: MappingProxyType({}))
    clock: ClockPolicy = dataclasses.field(default_factory=ClockPolicy)
    robot_ros: Mapping[str, Mapping[str, Any]] = dataclasses.field(
        default_factory=lambda: MappingProxyType({}))

    def ros_section(self, robot_id: str | None = None) -> Mapping[str, Any]:
        """The ``ros`` section as it applies to ``robot_id``: the site-wide keys with the robot
        entry's own ``ros:`` keys on top (a fleet gives each robot its namespace there);
        ``None``: the site-wide section."""
        base = dict(self.section("ros"))
        if robot_id:
            if robot_id not in self.robots:
                raise UnknownIdError(
                    f"robot {robot_id!r} is not in site {self.name!r}; known: "
                    f"{sorted(self.robots)}")
            base.update(self.robot_ros.get(robot_id, {}))
        return MappingProxyType(base)

    def section_reader(self) -> ConfigReader:
        """A reader whose errors name this site file (for a package parsing its section)."""
        return ConfigReader(self.source_path)

    def section(self, name: str) -> Mapping[str, Any]:
        """The raw mapping of a package-owned section (empty when the file has none)."""
        if name not in PACKAGE_SECTIONS:
            raise KeyError(f"{name!r} is not a package section; known: {PACKAGE_SECTIONS}")
        return self.sections.get(name, MappingProxyType({}))

    def camera(self, camera_id: str) -> CameraModel:
        """The camera with this id; ``KeyError`` naming the known ids if it is not in the site."""
        try:
            return self.cameras[camera_id]
        except KeyError:
            raise UnknownIdError(
                f"camera {camera_id!r} is not in site {self.name!r} ({self.source_path}); "
                f"known: {sorted(self.cameras)}"
            ) from None

    def robot_model(self, robot_id: str | None = None) -> RobotModel:
        """The robot model of ``robot_id`` (or of the only robot when ``None``)."""
        if robot_id is None or robot_id == "":
            if len(self.robots) != 1:
                raise UnknownIdError(f"site {self.name!r} has {len(self.robots)} robots; name one")
            robot_id = next(iter(self.robots))
        try:
            return self.robot_models[self.robots[robot_id]]
        except KeyError:
            raise UnknownIdError(
                f"robot {robot_id!r} is not in site {self.name!r}; known: {sorted(self.robots)}"
            ) from None


# --------------------------------------------------------------------------------------------
# parsing helpers: each names the file and the dotted key on failure
# --------------------------------------------------------------------------------------------


def look_at_T_world_cam(position_m: np.ndarray, target_m: np.ndarray) -> np.ndarray:
    """(4, 4) camera→world for an optical frame at ``position_m`` looking at ``target_m``,
    image "down" (optical y) pointing as close to world -z as possible."""
    z = np.asarray(target_m, float) - np.asarray(position_m, float)
    z /= np.linalg.norm(z)
    down = np.array([0.0, 0.0, -1.0])
    x = np.cross(down, z)
    if np.linalg.norm(x) < 1e-6:  # looking straight down: pick world +x as image right
        x = np.array([0.0, -1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = position_m
    return T


def _parse_transform(ctx: ConfigReader, key: str, value: Any) -> np.ndarray:
    """A rigid transform: a 4x4 matrix, or {translation_m, quaternion_xyzw | rpy_deg | matrix},
    or {position_m, look_at_m} (only meaningful for T_world_cam)."""
    if isinstance(value, list):
        T = ctx.matrix(key, value, 4, 4)
    else:
        node = ctx.mapping(key, value)
        if "look_at_m" in node:
            ctx.no_unknown(key, node, {"position_m", "look_at_m"})
            pos = ctx.matrix(
                join_key(key, "position_m"), ctx.require(key, node, "position_m"), 3, None
            )
            tgt = ctx.matrix(join_key(key, "look_at_m"), node["look_at_m"], 3, None)
            if pos.shape != (3,) or tgt.shape != (3,):
                raise ctx.fail(key, "position_m and look_at_m need 3 numbers each")
            if np.linalg.norm(tgt - pos) < 1e-6:
                raise ctx.fail(join_key(key, "look_at_m"), "coincides with position_m")
            return look_at_T_world_cam(pos, tgt)
        ctx.no_unknown(key, node, {"translation_m", "quaternion_xyzw", "rpy_deg", "matrix"})
        t = ctx.matrix(
            join_key(key, "translation_m"), ctx.require(key, node, "translation_m"), 3, None
        )
        if t.shape != (3,):
            raise ctx.fail(join_key(key, "translation_m"), "expected 3 numbers")
        given = [k for k in ("quaternion_xyzw", "rpy_deg", "matrix") if k in node]
        if len(given) != 1:
            raise ctx.fail(key, "give exactly one of quaternion_xyzw, rpy_deg, matrix")
        rkey = join_key(key, given[0])
        if given[0] == "quaternion_xyzw":
            q = ctx.matrix(rkey, node["quaternion_xyzw"], 4, None)
            if q.shape != (4,) or np.linalg.norm(q) < 1e-9:
                raise ctx.fail(rkey, "expected 4 numbers, not all zero")
            R = quaternion_to_rotation(q)
        elif given[0] == "rpy_deg":
            rpy = ctx.matrix(rkey, node["rpy_deg"], 3, None)
            if rpy.shape != (3,):
                raise ctx.fail(rkey, "expected 3 numbers")
            R = rotation_from_rpy(*(float(a) for a in np.deg2rad(rpy)))
        else:
            R = ctx.matrix(rkey, node["matrix"], 3, 3)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = t
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise ctx.fail(key, "rotation part is not a proper rotation matrix")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise ctx.fail(key, "last row must be [0, 0, 0, 1]")
    return T


# --------------------------------------------------------------------------------------------
# OpenCV / ROS calibration files
# --------------------------------------------------------------------------------------------


class _CalibLoader(yaml.SafeLoader):
    """SafeLoader that understands OpenCV's ``!!opencv-matrix`` tag."""


def _opencv_matrix(loader: yaml.SafeLoader, node: yaml.Node) -> dict[str, Any]:
    return loader.construct_mapping(node, deep=True)  # type: ignore[arg-type]


_CalibLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", _opencv_matrix)


@dataclasses.dataclass(frozen=True, eq=False)
class CameraCalibration:
    """Intrinsics (and optionally extrinsics) read from a calibration file."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    T_cam_world: np.ndarray | None = None


def _calib_matrix(
    ctx: ConfigReader, key: str, value: Any, rows: int | None, cols: int | None
) -> np.ndarray:
    if isinstance(value, Mapping):  # OpenCV matrix or ROS {rows, cols, data}
        data = ctx.require(key, value, "data")
        r = ctx.integer(join_key(key, "rows"), value.get("rows", rows or 1), lo=1, hi=16)
        c = ctx.integer(join_key(key, "cols"), value.get("cols", cols or len(data)), lo=1, hi=16)
        arr = ctx.matrix(join_key(key, "data"), data, r, c)
        return arr if cols is not None else arr.reshape(-1)
    return ctx.matrix(key, value, rows, cols)


#: ROS ``distortion_model`` names of OpenCV's standard lens model (5 or 8 coefficients)
SUPPORTED_DISTORTION_MODELS: Final = ("plumb_bob", "rational_polynomial")


def _check_K(ctx: ConfigReader, key: str, K: np.ndarray) -> np.ndarray:
    """``K`` if it is a camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with f > 0 (whether
    it came inline or from a calibration file), else a :class:`SiteConfigError` naming ``key``."""
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise ctx.fail(key, "not a camera matrix [[fx,s,cx],[0,fy,cy],[0,0,1]], f>0")
    return K


def load_camera_calibration(path: str | Path) -> CameraCalibration:
    """Read intrinsics from an OpenCV ``FileStorage`` YAML (``camera_matrix``,
    ``distortion_coefficients``, ``image_width``, ``image_height``; the ``%YAML:1.0`` header and
    ``!!opencv-matrix`` tags are understood) or a ROS ``camera_info`` YAML (same key names with
    plain ``{rows, cols, data}`` maps). An optional ``T_cam_world`` 4x4 matrix is read too. The
    camera matrix gets the same checks as an inline ``K``; a ``distortion_model`` other than
    OpenCV's standard one (e.g. ROS's ``equidistant`` fisheye) is refused with the reason."""
    ctx = ConfigReader(str(path))
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ctx.fail("", f"cannot read calibration file: {exc.strerror}") from None
    text = re.sub(r"^%YAML:\s*1\.\d+\s*\n", "", text)
    try:
        doc = yaml.load(text, Loader=_CalibLoader)
    except yaml.YAMLError as exc:
        raise ctx.fail("", f"not valid YAML: {exc}") from None
    doc = ctx.mapping("", doc)
    K = _check_K(ctx, "camera_matrix",
                 _calib_matrix(ctx, "camera_matrix", ctx.require("", doc, "camera_matrix"), 3, 3))
    model = doc.get("distortion_model", "plumb_bob")
    if model not in SUPPORTED_DISTORTION_MODELS:
        raise ctx.fail("distortion_model", f"{model!r} is not supported: smartedge projects with "
                       f"OpenCV's standard (radial-tangential) model "
                       f"({', '.join(SUPPORTED_DISTORTION_MODELS)}); a fisheye (equidistant) "
                       "calibration would be misread. Recalibrate with the standard model or "
                       "rectify the images first")
    dist_node = doc.get("distortion_coefficients", [])
    dist = _calib_matrix(ctx, "distortion_coefficients", dist_node, None, None).reshape(-1)
    if dist.size not in DISTORTION_LENGTHS:
        raise ctx.fail("distortion_coefficients", f"length {dist.size} not in {DISTORTION_LENGTHS}")
    width = ctx.integer("image_width", ctx.require("", doc, "image_width"), lo=1, hi=65535)
    height = ctx.integer("image_height", ctx.require("", doc, "image_height"), lo=1, hi=65535)
    T = None
    if "T_cam_world" in doc:
        T = _parse_transform(
            ctx, "T_cam_world", _calib_matrix(ctx, "T_cam_world", doc["T_cam_world"], 4, 4).tolist()
        )
    return CameraCalibration(width, height, K, dist, T)


# --------------------------------------------------------------------------------------------
# site file
# --------------------------------------------------------------------------------------------

_CAMERA_KEYS: Final = {
    "id",
    "resolution",
    "K",
    "intrinsics",
    "distortion",
    "T_cam_world",
    "T_world_cam",
    "calibration_file",
    "clock_offset_ns",
}
#: Sections owned by a service package: the site file holds them, the package parses them into
#: its own dataclass (``backend_service``: pose, multi_frame, fusion, camera_health,
#: association, areas;
#: ``robot_bridge``: bridge, pose_output, map_output, ros; map and edge are reserved for the
#: semantic map and the edge pipeline).
PACKAGE_SECTIONS: Final = (
    "pose", "multi_frame", "fusion", "camera_health", "association", "bridge", "pose_output",
    "map_output", "ros", "map", "edge", "areas")
_TOP_KEYS: Final = {
    "site", "world_frame", "cameras", "robot_models", "robots", "thresholds", "clock",
    *PACKAGE_SECTIONS,
}
#: settings the clock policy replaced: (section, key) -> the ``clock`` key that holds it now.
#: ``thresholds.max_future_ms`` (the old site-wide value) is still read, with a warning; the
#: per-service ones are errors that name the new key.
_CLOCK_PREDECESSORS: Final = {
    ("thresholds", "max_future_ms"): "max_future_ms",
    ("bridge", "clock_tolerance_ms"): "max_future_ms",
    ("map", "max_future_s"): "max_future_ms",
    ("fusion", "max_future_s"): "max_age_ms",
    ("map", "max_age_s"): "max_age_ms",
    ("pose", "prior_max_age_s"): "max_age_ms",
    ("pose", "publish_max_age_s"): "max_age_ms",
    ("pose_output", "max_age_s"): "max_age_ms",
}


def _parse_K(ctx: ConfigReader, key: str, node: Mapping[str, Any]) -> np.ndarray:
    if "K" in node and "intrinsics" in node:
        raise ctx.fail(join_key(key, "K"), "give either K or intrinsics, not both")
    if "K" in node:
        K = ctx.matrix(join_key(key, "K"), node["K"], 3, 3)
    elif "intrinsics" in node:
        ik = join_key(key, "intrinsics")
        intr = ctx.mapping(ik, node["intrinsics"])
        ctx.no_unknown(ik, intr, {"fx", "fy", "cx", "cy"})
        fx, fy, cx, cy = (
            ctx.number(join_key(ik, n), ctx.require(ik, intr, n)) for n in ("fx", "fy", "cx", "cy")
        )
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    else:
        raise ctx.fail(
            join_key(key, "K"), "required key is missing (or give intrinsics/calibration_file)"
        )
    return _check_K(ctx, join_key(key, "K"), K)


def _parse_inline_intrinsics(ctx: ConfigReader, key: str, node: Mapping[str, Any]
                             ) -> tuple[int, int, np.ndarray, np.ndarray]:
    """``resolution`` [width, height], ``K`` or ``intrinsics``, ``distortion`` of a camera
    node (a site camera or a robot's head camera)."""
    res_key = join_key(key, "resolution")
    res = ctx.require(key, node, "resolution")
    if not isinstance(res, list) or len(res) != 2:
        raise ctx.fail(res_key, "expected [width, height] in pixels")
    width = ctx.integer(res_key, res[0], lo=1, hi=65535)
    height = ctx.integer(res_key, res[1], lo=1, hi=65535)
    K = _parse_K(ctx, key, node)
    dist = ctx.matrix(join_key(key, "distortion"), node.get("distortion", []), None, None)
    if dist.size not in DISTORTION_LENGTHS:
        raise ctx.fail(join_key(key, "distortion"), f"length {dist.size} not in "
                       f"{DISTORTION_LENGTHS}")
    return width, height, K, dist


def _parse_camera(ctx: ConfigReader, key: str, value: Any, base_dir: Path) -> CameraModel:
    node = ctx.mapping(key, value)
    ctx.no_unknown(key, node, _CAMERA_KEYS)
    cam_id = ctx.ident(join_key(key, "id"), ctx.require(key, node, "id"))
    T_cam_world: np.ndarray | None = None
    if "calibration_file" in node:
        for clash in ("K", "intrinsics", "distortion", "resolution"):
            if clash in node:
                raise ctx.fail(join_key(key, clash), "also given by calibration_file; give one")
        calib_path = Path(str(node["calibration_file"]))
        if not calib_path.is_absolute():
            calib_path = base_dir / calib_path
        calib = load_camera_calibration(calib_path)
        width, height, K, dist = calib.width, calib.height, calib.K, calib.dist
        T_cam_world = calib.T_cam_world
    else:
        width, height, K, dist = _parse_inline_intrinsics(ctx, key, node)
    given = [k for k in ("T_cam_world", "T_world_cam") if k in node]
    if len(given) > 1:
        raise ctx.fail(key, "give T_cam_world or T_world_cam, not both")
    if given:
        T = _parse_transform(ctx, join_key(key, given[0]), node[given[0]])
        T_cam_world = T if given[0] == "T_cam_world" else invert_transform(T)
    if T_cam_world is None:
        raise ctx.fail(join_key(key, "T_world_cam"), "required key is missing (camera extrinsics)")
    offset = ctx.integer(
        join_key(key, "clock_offset_ns"), node.get("clock_offset_ns", 0), lo=-(10**15), hi=10**15
    )
    return CameraModel(cam_id, width, height, K, dist, T_cam_world, offset)


def _parse_robot_model(ctx: ConfigReader, key: str, name: str, value: Any,
                       base_dir: Path = Path(".")) -> RobotModel:
    node = ctx.mapping(key, value)
    ctx.no_unknown(key, node, {"keypoints", "footprint_radius_m", "height_m", "models",
                               "head_camera"})
    kkey = join_key(key, "keypoints")
    kps = ctx.require(key, node, "keypoints")
    if not isinstance(kps, list) or len(kps) < 3:
        raise ctx.fail(kkey, "expected a list of at least 3 keypoints {name, xyz_m}")
    names: list[str] = []
    xyz: list[np.ndarray] = []
    for i, kp in enumerate(kps):
        ik = f"{kkey}[{i}]"
        kp = ctx.mapping(ik, kp)
        ctx.no_unknown(ik, kp, {"name", "xyz_m"})
        kp_name = ctx.ident(join_key(ik, "name"), ctx.require(ik, kp, "name"))
        if kp_name in names:
            raise ctx.fail(join_key(ik, "name"), f"duplicate keypoint name {kp_name!r}")
        p = ctx.matrix(join_key(ik, "xyz_m"), ctx.require(ik, kp, "xyz_m"), 3, None)
        if p.shape != (3,):
            raise ctx.fail(join_key(ik, "xyz_m"), "expected 3 numbers")
        names.append(kp_name)
        xyz.append(p)
    radius = ctx.number(
        join_key(key, "footprint_radius_m"),
        ctx.require(key, node, "footprint_radius_m"),
        lo=0.01,
        hi=10.0,
    )
    height = ctx.number(join_key(key, "height_m"), node.get("height_m", 1.0), lo=0.01, hi=10.0)
    pts = np.stack(xyz)
    pts.setflags(write=False)
    onnx: dict[str, Path | None] = {"detector": None, "keypoints": None}
    if "models" in node:
        mkey = join_key(key, "models")
        models = ctx.mapping(mkey, node["models"])
        ctx.no_unknown(mkey, models, set(onnx))
        for kind in onnx:
            if kind not in models:
                raise ctx.fail(join_key(mkey, kind), "required key is missing (give both "
                               "models, or neither for the shipped ones)")
            raw = models[kind]
            if not isinstance(raw, str) or not raw.strip():
                raise ctx.fail(join_key(mkey, kind), "expected the path of an .onnx file")
            path = Path(raw).expanduser()
            onnx[kind] = path if path.is_absolute() else base_dir / path
    head = None
    if "head_camera" in node:
        head = _parse_head_camera(ctx, join_key(key, "head_camera"), node["head_camera"])
    return RobotModel(name, tuple(names), pts, radius, height, onnx["detector"],
                      onnx["keypoints"], head)


_HEAD_CAMERA_KEYS: Final = {"resolution", "K", "intrinsics", "distortion", "T_base_cam"}


def _parse_head_camera(ctx: ConfigReader, key: str, value: Any) -> HeadCamera:
    """``head_camera: {resolution, K | intrinsics, distortion, T_base_cam}`` of a robot model;
    ``T_base_cam`` in any form :func:`_parse_transform` reads (4x4, translation_m + rpy_deg /
    quaternion_xyzw / matrix, or position_m + look_at_m in the base frame)."""
    node = ctx.mapping(key, value)
    ctx.no_unknown(key, node, set(_HEAD_CAMERA_KEYS))
    width, height, K, dist = _parse_inline_intrinsics(ctx, key, node)
    T = _parse_transform(ctx, join_key(key, "T_base_cam"), ctx.require(key, node, "T_base_cam"))
    for arr in (K, dist, T):
        arr.setflags(write=False)
    return HeadCamera(width, height, K, dist.reshape(-1), T)


def _parse_thresholds(ctx: ConfigReader, value: Any) -> Thresholds:
    node = {k: v for k, v in ctx.mapping("thresholds", value).items() if k != "max_future_ms"}
    return ctx.section("thresholds", node, Thresholds, int_lo=1)


def _parse_clock(ctx: ConfigReader, top: Mapping[str, Any]) -> ClockPolicy:
    """The ``clock`` section; the settings it replaced (:data:`_CLOCK_PREDECESSORS`) are
    refused naming the new key, but for ``thresholds.max_future_ms``, read with a warning."""
    node = dict(ctx.mapping("clock", top.get("clock") or {}))
    for (section, key), new in _CLOCK_PREDECESSORS.items():
        old_node = top.get(section)
        if not isinstance(old_node, Mapping) or key not in old_node:
            continue
        old = join_key(section, key)
        if section != "thresholds":
            raise ctx.fail(old, f"removed: the site's one clock policy sets it, clock.{new} "
                           "(docs/configuration.md)")
        if new in node:
            raise ctx.fail(old, f"replaced by clock.{new}, which is given too: remove {old}")
        node[new] = ctx.number(old, old_node[key], lo=0.0)
        log.warning("%s: %s is deprecated and read as clock.%s: move it there", ctx.path, old,
                    new)
    return ctx.section("clock", node, ClockPolicy)


def parse_site(doc: Any, path: str = "<memory>", base_dir: Path | None = None) -> Site:
    """Validate an already-parsed YAML document as a site (``path`` is used in errors)."""
    ctx = ConfigReader(path)
    base_dir = base_dir or Path(".")
    top = ctx.mapping("", doc)
    ctx.no_unknown("", top, _TOP_KEYS)
    name = ctx.ident("site", ctx.require("", top, "site"))
    world_frame = ctx.ident("world_frame", top.get("world_frame", "map"))
    cams = ctx.require("", top, "cameras")
    if not isinstance(cams, list) or not cams:
        raise ctx.fail("cameras", "expected a non-empty list of cameras")
    cameras: dict[str, CameraModel] = {}
    for i, cam in enumerate(cams):
        model = _parse_camera(ctx, f"cameras[{i}]", cam, base_dir)
        if model.camera_id in cameras:
            raise ctx.fail(f"cameras[{i}].id", f"duplicate camera id {model.camera_id!r}")
        cameras[model.camera_id] = model
    models_node = ctx.mapping("robot_models", ctx.require("", top, "robot_models"))
    if not models_node:
        raise ctx.fail("robot_models", "define at least one robot model")
    robot_models = {
        ctx.ident(f"robot_models.{n}", n):
            _parse_robot_model(ctx, f"robot_models.{n}", n, v, base_dir)
        for n, v in models_node.items()
    }
    robots_node = ctx.require("", top, "robots")
    if not isinstance(robots_node, list) or not robots_node:
        raise ctx.fail("robots", "expected a non-empty list of {id, model}")
    robots: dict[str, str] = {}
    robot_ros: dict[str, Mapping[str, Any]] = {}
    for i, r in enumerate(robots_node):
        rk = f"robots[{i}]"
        r = ctx.mapping(rk, r)
        ctx.no_unknown(rk, r, {"id", "model", "ros"})
        rid = ctx.ident(join_key(rk, "id"), ctx.require(rk, r, "id"))
        model_name = ctx.require(rk, r, "model")
        if model_name not in robot_models:
            raise ctx.fail(
                join_key(rk, "model"),
                f"unknown robot model {model_name!r}; defined: {sorted(robot_models)}",
            )
        if rid in robots:
            raise ctx.fail(join_key(rk, "id"), f"duplicate robot id {rid!r}")
        robots[rid] = model_name
        if r.get("ros") is not None:  # robot_bridge's RosConfig parses the keys
            robot_ros[rid] = MappingProxyType(dict(ctx.mapping(join_key(rk, "ros"), r["ros"])))
    thresholds = _parse_thresholds(ctx, top.get("thresholds", {}) or {})
    clock = _parse_clock(ctx, top)
    sections = {
        name: MappingProxyType(dict(ctx.mapping(name, top.get(name) or {})))
        for name in PACKAGE_SECTIONS
    }
    return Site(name, world_frame, cameras, robot_models, robots, thresholds, path,
                MappingProxyType(sections), clock, MappingProxyType(robot_ros))


def load_site(path: str | Path) -> Site:
    """Load and validate a site YAML file; :class:`SiteConfigError` names file and key."""
    p = Path(path)
    doc = read_yaml_file(p, "site file", SiteConfigError)
    return parse_site(doc, str(p), p.parent)
