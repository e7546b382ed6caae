"""``smartedge robot-camera --source ros``: the real robot's head RGB-D camera as semantic clouds.

On a real robot (the paper's HSR) the head camera's driver publishes colour, aligned depth and
``CameraInfo`` as ROS 2 topics, and the head pans and tilts, so the camera's pose in the robot's
``base_link`` changes every frame. This node runs on the robot's computer (or beside the robot
bridge) and, for each frame due at ``--cloud-rate`` (1 Hz by default):

1. takes the newest colour + depth pair of one header stamp from the bus
   (:class:`edge_agent.ros_source.RosImageSource` with a depth topic; rmw_zenoh or
   zenoh-bridge-ros2dds keys), intrinsics and distortion from the ``CameraInfo`` (the site's
   ``head_camera`` of the robot model is only the fallback before the first ``CameraInfo``, and
   the check: a difference is logged once and named in the status);
2. looks up ``T_base_cam`` = the pose of the image's ``header.frame_id`` in ``--base-frame``
   (``base_link``) AT THE IMAGE STAMP in a :class:`core.tf_buffer.TfBuffer` fed from
   ``/tf`` and ``/tf_static`` (:class:`edge_agent.ros_tf.TfListener`): chains of frames,
   interpolation between two transforms of a moving joint;
3. segments the colour image (:class:`edge_agent.networks.SemanticSegmenter`) and builds the
   :class:`protocol.SemanticCloud` in ``base_link`` with ``T_frame_sensor = T_base_cam``
   (:class:`edge_agent.semantic_cloud.SemanticCloudMaker`, the same code as the simulated head
   camera and the static cameras), published reliably on
   ``smartedge/<site>/robot/<robot_id>/cloud``.

TF usually lags the image a little: the frame is kept (one at a time, the newest due) until TF
brackets its stamp, at most ``--tf-wait-s`` (0.3 s). Then a transform that is only a little
older than the stamp (within ``--tf-max-age-s``) is used as it is (counted ``tf_held``);
otherwise the frame is skipped and counted ``tf_stale`` (the newest transform of a joint is
too old), ``tf_missing`` (a frame of the chain unknown, or two trees not joined) or
``tf_extrapolation`` (the stamp is before the history TF holds: skipped at once), and the
error is named in the status. Bad messages never stop the node: they are counted and named
as the edge agent's ROS source does.

Imports only ``protocol`` and ``edge_agent``: it runs on an edge install (``smartedge[edge]``).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import time
from collections.abc import Iterable, Sequence
from typing import Any, Final

import numpy as np

from core.camera import DISTORTION_LENGTHS, CameraModel
from core.runtime import Outgoing, ServiceNode, service_main
from core.session import add_session_arguments
from core.site import Site, load_site
from core.tf_buffer import (
    TfBuffer,
    TfBufferConfig,
    TfError,
    TfExtrapolationError,
    TfMissingError,
    TfStaleError,
)
from edge_agent.ros_source import (
    DEFAULT_SYNC_TOLERANCE_NS,
    TRANSPORTS,
    RosCameraInfo,
    RosFrame,
    RosImageSource,
    RosTopicConfig,
)
from edge_agent.ros_tf import TF_STATIC_TOPIC, TF_TOPIC, TfListener
from edge_agent.semantic_cloud import ROBOT_BASE_FRAME, SemanticCloudMaker
from protocol import keys
from protocol.errors import SmartedgeError, UsageError

log = logging.getLogger(__name__)

#: the HSR's head RGB-D topics (Toyota's hsrb_interface names)
HSR_RGB_TOPIC: Final = "/hsrb/head_rgbd_sensor/rgb/image_rect_color"
HSR_DEPTH_TOPIC: Final = "/hsrb/head_rgbd_sensor/depth_registered/image_rect_raw"
HSR_CAMERA_INFO_TOPIC: Final = "/hsrb/head_rgbd_sensor/rgb/camera_info"
DEFAULT_CLOUD_RATE_HZ: Final = 1.0
DEFAULT_TF_WAIT_S: Final = 0.3
DEFAULT_TF_MAX_AGE_S: Final = 0.1
#: seconds a TF or image error stays in the status after it happened
ERROR_SHOWN_S: Final = 5.0
#: the TF buffer's counters of refused transforms, reported as ``tf_refused_<name>``
_TF_REFUSALS: Final = ("invalid", "two_parents", "loops", "kind_conflict", "too_old",
                       "duplicate", "too_many_frames")
#: distortion models whose coefficients are OpenCV's (plumb_bob: 5, rational_polynomial: 8)
_OPENCV_MODELS: Final = ("plumb_bob", "rational_polynomial", "")


class CameraInfoError(SmartedgeError):
    """A ``CameraInfo`` this node cannot use as intrinsics (``counter`` names it)."""

    def __init__(self, counter: str, message: str) -> None:
        super().__init__(message)
        self.counter = counter


def camera_from_info(info: RosCameraInfo, camera_id: str) -> CameraModel:
    """The :class:`CameraModel` (intrinsics, OpenCV distortion, size; identity extrinsics) of a
    ``CameraInfo``; :class:`CameraInfoError` for an uncalibrated one (K zero) or a distortion
    model OpenCV's pinhole model cannot express (``equidistant`` with non-zero coefficients)."""
    K = np.asarray(info.K, np.float64)
    if not (K[0, 0] > 0.0 and K[1, 1] > 0.0 and K[2, 2] == 1.0):
        raise CameraInfoError("camera_info_uncalibrated", f"CameraInfo of {info.frame_id!r}: "
                              f"K has fx={K[0, 0]:g}, fy={K[1, 1]:g}, K[2][2]={K[2, 2]:g} "
                              "(an uncalibrated camera)")
    D = np.asarray(info.D, np.float64)
    if not np.any(D):
        D = np.zeros(0)
    elif info.distortion_model.lower() not in _OPENCV_MODELS or D.size not in \
            DISTORTION_LENGTHS:
        raise CameraInfoError("camera_info_unsupported", f"CameraInfo of {info.frame_id!r}: "
                              f"distortion model {info.distortion_model!r} with {D.size} "
                              "coefficients (plumb_bob or rational_polynomial expected)")
    return CameraModel(camera_id, int(info.width), int(info.height), K, D, np.eye(4))


@dataclasses.dataclass
class _Waiting:
    """The frame waiting for TF: since when (the node's clock, ns)."""

    got: RosFrame
    since_ns: int


class RosRobotCameraNode(ServiceNode):
    """The real head camera (module docstring).

    ``source``: a :class:`RosImageSource` with a depth topic; ``tf``: a :class:`TfListener`;
    ``tf_buffer`` the buffer it feeds; ``segmenter`` (``None``: no clouds, ``unavailable``
    says why); ``fallback_camera``: the site's head camera (intrinsics before the first
    ``CameraInfo``; ``None``: wait for one)."""

    service = "robot-camera"
    tick_period_s = 0.01

    def __init__(self, site_name: str, robot_id: str, source: RosImageSource, tf: TfListener,
                 segmenter: Any, *, tf_buffer: TfBuffer | None = None,
                 base_frame: str = ROBOT_BASE_FRAME, rate_hz: float = DEFAULT_CLOUD_RATE_HZ,
                 tf_wait_s: float = DEFAULT_TF_WAIT_S,
                 fallback_camera: CameraModel | None = None, unavailable: str = "") -> None:
        super().__init__(site_name, robot_id)
        if not (rate_hz > 0.0 and np.isfinite(rate_hz)):
            raise UsageError(f"--cloud-rate {rate_hz}: must be > 0")
        if not (0.0 <= tf_wait_s <= 10.0):
            raise UsageError(f"--tf-wait-s {tf_wait_s}: expected 0 to 10 s")
        self.robot_id = robot_id
        self.source = source
        self.tf = tf
        self.tf_buffer = tf_buffer or TfBuffer()
        self.base_frame = base_frame
        self.tf_wait_ns = round(tf_wait_s * 1e9)
        self.fallback_camera = fallback_camera
        self.unavailable = unavailable
        self._key = keys.robot_cloud_key(site_name, robot_id)
        self._camera_id = f"{robot_id}_head"
        source.bind_stats(self.stats)
        self.clouds: SemanticCloudMaker | None = None
        if segmenter is not None:
            # camera and T_frame_sensor are set per frame (CameraInfo, TF at the stamp)
            self.clouds = SemanticCloudMaker(
                segmenter, fallback_camera or _placeholder_camera(self._camera_id),
                sensor_id=robot_id, frame_id=ROBOT_BASE_FRAME, T_frame_sensor=np.eye(4),
                rate_hz=rate_hz)
        self._waiting: _Waiting | None = None
        self._info_camera: tuple[RosCameraInfo, CameraModel] | None = None
        self.last_problem = ""
        self._last_problem_ns = 0
        self._problem_logged: set[str] = set()
        self.last_T_base_cam: np.ndarray | None = None

    # -- bus ---------------------------------------------------------------------------------

    def attach(self, session: Any) -> None:
        self.source.attach(session)
        self.tf.attach(session)

    def close(self) -> None:
        self.source.close()
        self.tf.close()
        super().close()

    # -- problems ----------------------------------------------------------------------------

    def _problem(self, counter: str, text: str, now_ns: int) -> None:
        self.stats.count(counter)
        self.last_problem = f"{text} (counted {counter})"
        self._last_problem_ns = now_ns
        if counter not in self._problem_logged:
            self._problem_logged.add(counter)
            log.warning("%s: %s; the frame is skipped (further ones counted %s, not logged)",
                        self.robot_id, text, counter)

    # -- worker ------------------------------------------------------------------------------

    def _due(self, stamp_ns: int) -> bool:
        return self.clouds is not None and self._waiting is None and self.clouds.due(stamp_ns)

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        self.tf.drain(self.tf_buffer)
        got = self.source.take_frame(want=self._due)
        if got is not None:
            self.stats.count("frames")
            if got.frame.depth_m is None:
                self.stats.count("frames_without_depth")
            else:
                self._waiting = _Waiting(got, now_ns)
        if self._waiting is None:
            return []
        return self._try_waiting(now_ns)

    def _try_waiting(self, now_ns: int) -> list[Outgoing]:
        waiting = self._waiting
        assert waiting is not None and self.clouds is not None
        frame, frame_id = waiting.got.frame, waiting.got.frame_id
        waited_ns = now_ns - waiting.since_ns
        patient = waited_ns < self.tf_wait_ns
        held_before = self.tf_buffer.counters["held"]
        try:
            T_base_cam = self.tf_buffer.lookup(self.base_frame, frame_id, frame.stamp_ns)
        except TfExtrapolationError as exc:  # waiting never helps: history starts later
            self._skip("tf_extrapolation", exc, now_ns)
            return []
        except (TfStaleError, TfMissingError) as exc:
            if patient:
                return []
            self._skip("tf_stale" if isinstance(exc, TfStaleError) else "tf_missing", exc,
                       now_ns)
            return []
        except TfError as exc:  # any other lookup failure
            self._skip("tf_missing", exc, now_ns)
            return []
        if self.tf_buffer.counters["held"] > held_before:
            if patient:  # TF does not bracket the stamp yet: wait for the next transform
                return []
            self.stats.count("tf_held")
        self._waiting = None
        self.stats.latency("tf_wait", max(0, waited_ns) * 1e-9)
        return self._cloud(waiting.got, T_base_cam, now_ns)

    def _skip(self, counter: str, exc: TfError, now_ns: int) -> None:
        self._waiting = None
        self._problem(counter, f"no T_{self.base_frame}_cam at the image stamp: {exc}", now_ns)

    def _camera(self, now_ns: int) -> CameraModel | None:
        info = self.source.latest_info
        if info is None:
            return self.fallback_camera
        cached = self._info_camera
        if cached is not None and cached[0] is info:
            return cached[1]
        try:
            camera = camera_from_info(info, self._camera_id)
        except (CameraInfoError, SmartedgeError, ValueError) as exc:
            counter = getattr(exc, "counter", "camera_info_unusable")
            self._problem(counter, str(exc), now_ns)
            return None
        self._info_camera = (info, camera)
        return camera

    def _cloud(self, got: RosFrame, T_base_cam: np.ndarray, now_ns: int) -> list[Outgoing]:
        frame = got.frame
        depth_m = frame.depth_m
        assert self.clouds is not None and depth_m is not None
        camera = self._camera(now_ns)
        if camera is None:
            if self.source.latest_info is None:
                self._problem("clouds_skipped_no_camera_info", "no CameraInfo yet on "
                              f"{self.source.config.info_key} and no head_camera in the "
                              "site's robot model", now_ns)
            return []
        h, w = frame.image_rgb.shape[:2]
        if (w, h) != (camera.width, camera.height):
            self._problem("camera_info_size_mismatch", f"image {w}x{h}, its CameraInfo says "
                          f"{camera.width}x{camera.height}", now_ns)
            return []
        self.clouds.camera = camera
        self.clouds.T_frame_sensor = np.array(T_base_cam, dtype=np.float64)
        self.last_T_base_cam = self.clouds.T_frame_sensor
        cloud = self.clouds.make_for_service(frame.image_rgb, depth_m, frame.stamp_ns,
                                             self.stats)
        if cloud is None:
            return []
        self.stats.latency("capture_to_publish", max(0, time.time_ns() - frame.stamp_ns) * 1e-9)
        return [Outgoing(self._key, cloud, reliable=True)]

    # -- status ------------------------------------------------------------------------------

    def counters(self) -> dict[str, int]:
        """The node's counters, the TF listener's (messages, decode errors) and the transforms
        the TF buffer refused (``tf_refused_<why>``)."""
        out = self.stats.snapshot_counters()
        out.update({k: int(v) for k, v in self.tf.counters.items()})
        out.update({f"tf_refused_{k}": int(self.tf_buffer.counters[k]) for k in _TF_REFUSALS
                    if self.tf_buffer.counters.get(k)})
        return out

    def state(self) -> tuple[str, str]:
        state, detail = self.source.health()
        tf_line = self.tf_buffer.detail().split("; last error:")[0]
        detail = f"{detail}; {tf_line}; clouds={self.stats.counters.get('clouds_published', 0)}"
        if self.clouds is None:
            return "degraded", f"{detail}; no clouds: {self.unavailable}"
        if state != "ok":
            return state, detail
        now = self.clock()
        if self.last_problem and now - self._last_problem_ns < ERROR_SHOWN_S * 1e9:
            return "degraded", f"{detail}; {self.last_problem}"
        if self.tf.last_error and time.monotonic() - self.tf.last_error_s < ERROR_SHOWN_S:
            return "degraded", f"{detail}; {self.tf.last_error}"
        return "ok", detail


def _placeholder_camera(camera_id: str) -> CameraModel:
    """A camera for the maker's constructor until the first ``CameraInfo`` (never used for a
    cloud: :meth:`RosRobotCameraNode._cloud` sets the real one first)."""
    return CameraModel(camera_id, 1, 1, np.eye(3), np.zeros(0), np.eye(4))


# --------------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smartedge robot-camera --source ros",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--source", choices=("ros",), default="ros",
                        help="ros: the real robot's topics (this command); sim: the simulated "
                        "head camera (smartedge robot-camera --source sim)")
    parser.add_argument("--site", required=True, help="site file (the robot, and its robot "
                        "model's head_camera as the fallback and check of the CameraInfo)")
    parser.add_argument("--robot", help="robot id (default: the site's only robot)")
    g = parser.add_argument_group("ROS 2 topics")
    g.add_argument("--ros-transport", choices=TRANSPORTS, default="rmw_zenoh",
                   help="rmw_zenoh (default) or ros2dds (zenoh-bridge-ros2dds)")
    g.add_argument("--ros-domain-id", type=int, default=None, metavar="N",
                   help="rmw_zenoh: the ROS domain id (default: $ROS_DOMAIN_ID, else 0)")
    g.add_argument("--ros-namespace", default="", metavar="NS",
                   help="ros2dds: the bridge's namespace prefixed to its keys")
    g.add_argument("--rgb-topic", default=HSR_RGB_TOPIC, metavar="TOPIC",
                   help=f"colour Image, or CompressedImage when it ends in /compressed "
                   f"(default {HSR_RGB_TOPIC})")
    g.add_argument("--depth-topic", default=HSR_DEPTH_TOPIC, metavar="TOPIC",
                   help=f"depth Image aligned to the colour (16UC1 mm or 32FC1 m; default "
                   f"{HSR_DEPTH_TOPIC})")
    g.add_argument("--camera-info-topic", default=HSR_CAMERA_INFO_TOPIC, metavar="TOPIC",
                   help=f"the colour camera's CameraInfo (default {HSR_CAMERA_INFO_TOPIC}; "
                   "'none': the site's head_camera only)")
    g.add_argument("--tf-topic", default=TF_TOPIC, metavar="TOPIC",
                   help=f"moving transforms (default {TF_TOPIC})")
    g.add_argument("--tf-static-topic", default=TF_STATIC_TOPIC, metavar="TOPIC",
                   help=f"static transforms, read with history (default {TF_STATIC_TOPIC})")
    g.add_argument("--sync-tolerance-ms", type=float, default=DEFAULT_SYNC_TOLERANCE_NS / 1e6,
                   metavar="MS", help="largest stamp difference of a colour image and its "
                   f"depth image (default {DEFAULT_SYNC_TOLERANCE_NS / 1e6:g} ms)")
    c = parser.add_argument_group("clouds")
    c.add_argument("--base-frame", default=ROBOT_BASE_FRAME, metavar="FRAME",
                   help=f"the TF frame the clouds are expressed in; the backend places them "
                   f"with the robot's pose (default {ROBOT_BASE_FRAME})")
    c.add_argument("--cloud-rate", type=float, default=DEFAULT_CLOUD_RATE_HZ, metavar="HZ",
                   help=f"clouds per second (default {DEFAULT_CLOUD_RATE_HZ:g})")
    c.add_argument("--tf-wait-s", type=float, default=DEFAULT_TF_WAIT_S, metavar="S",
                   help="how long a frame waits for TF to cover its stamp (default "
                   f"{DEFAULT_TF_WAIT_S:g} s)")
    c.add_argument("--tf-max-age-s", type=float, default=DEFAULT_TF_MAX_AGE_S, metavar="S",
                   help="after the wait, a transform at most this much older than the image "
                   f"is used as it is (default {DEFAULT_TF_MAX_AGE_S:g} s)")
    c.add_argument("--segmentation-model", metavar="ONNX",
                   help="segmentation network (default: the shipped one)")
    c.add_argument("--threads", type=int, default=2, help="onnxruntime threads (default 2)")
    c.add_argument("--providers", default="CPUExecutionProvider",
                   help="onnxruntime execution providers of the segmentation network, "
                   "comma-separated, or auto (default CPU)")
    add_session_arguments(parser)
    return parser


def _domain_id(value: int | None) -> int:
    if value is None:
        text = os.environ.get("ROS_DOMAIN_ID", "").strip() or "0"
        if not text.isdigit():
            raise UsageError(f"ROS_DOMAIN_ID={text!r}: expected an integer >= 0")
        return int(text)
    if value < 0:
        raise UsageError(f"--ros-domain-id {value}: expected an integer >= 0")
    return value


def build_node(args: argparse.Namespace, segmenter: Any = None,
               site: Site | None = None) -> RosRobotCameraNode:
    """The node of ``args``; ``segmenter``: use this instead of loading
    ``--segmentation-model``; ``site``: instead of loading ``--site`` (tests)."""
    site = site or load_site(args.site)
    robot_model = site.robot_model(args.robot)
    robot_id = args.robot or next(iter(site.robots))
    if not (args.cloud_rate > 0):
        raise UsageError(f"--cloud-rate {args.cloud_rate}: must be > 0")
    if not 0.0 <= args.tf_max_age_s <= 10.0:
        raise UsageError(f"--tf-max-age-s {args.tf_max_age_s}: expected 0 to 10 s")
    if not 0.0 <= args.sync_tolerance_ms <= 1000.0:
        raise UsageError(f"--sync-tolerance-ms {args.sync_tolerance_ms}: expected 0 to 1000")
    head = robot_model.head_camera
    fallback = head.camera_model(f"{robot_id}_head") if head is not None else None
    info = args.camera_info_topic
    config = RosTopicConfig(
        args.ros_transport, args.rgb_topic,
        compressed=args.rgb_topic.rstrip("/").endswith("/compressed"),
        info_topic=None if info == "none" else info, domain_id=_domain_id(args.ros_domain_id),
        namespace=args.ros_namespace, depth_topic=args.depth_topic,
        sync_tolerance_ns=round(args.sync_tolerance_ms * 1e6))
    config.image_key, config.info_key, config.depth_key  # noqa: B018 (names checked early)
    if config.info_key is None and fallback is None:
        raise UsageError("--camera-info-topic none needs a head_camera in the site's robot "
                         f"model of {robot_id!r} (the intrinsics)")
    tf = TfListener(args.ros_transport, domain_id=config.domain_id,
                    namespace=args.ros_namespace, tf_topic=args.tf_topic,
                    static_topic=args.tf_static_topic)
    source = RosImageSource(config, None, fallback)
    source.label = f"ros:{args.ros_transport}:{args.rgb_topic}+depth"
    unavailable = ""
    if segmenter is None:
        try:
            from edge_agent.networks import SemanticSegmenter
            from edge_agent.providers import providers_available

            providers = providers_available() if args.providers == "auto" else [
                p.strip() for p in args.providers.split(",") if p.strip()]
            segmenter = SemanticSegmenter(args.segmentation_model, threads=args.threads,
                                          providers=providers)
        except (ImportError, SmartedgeError, OSError, RuntimeError) as exc:
            unavailable = f"the segmentation model cannot be loaded: {exc}"
            log.error("%s: no robot clouds: %s", robot_id, unavailable)
    node = RosRobotCameraNode(
        site.name, robot_id, source, tf, segmenter,
        tf_buffer=TfBuffer(TfBufferConfig(max_age_s=args.tf_max_age_s)),
        base_frame=args.base_frame, rate_hz=args.cloud_rate, tf_wait_s=args.tf_wait_s,
        fallback_camera=fallback, unavailable=unavailable)
    log.info("%s: REAL head camera from %s (+ %s, %s), T_%s_cam from TF at each image stamp, "
             "clouds at %g Hz", robot_id, config.image_key, config.depth_key,
             config.info_key or "site head_camera", args.base_frame, args.cloud_rate)
    return node


def main(argv: Sequence[str]) -> int:
    return service_main("robot-camera", argv, build_parser, build_node)
