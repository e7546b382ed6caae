"""``smartedge edge-agent``: one camera's edge service.

Frames come from a source, the robot keypoint detector turns them into
:class:`protocol.RobotDetections`, which are published on
``smartedge/<site>/edge/<camera_id>/detections`` (best effort: a stale frame is worthless).

Sources are plug-ins (:mod:`edge_agent.sources`); ``--source`` offers the registered ones:

- ``camera``: frames from OpenCV (``--device``: a V4L2 index or path, an RTSP/HTTP URL, a video
  file), an image folder (``--images``) or a RealSense (``--realsense``), through the ONNX
  detector + keypoint models of the site's robot model (default: the shipped ones in
  ``edge_agent/models/``; ``--model`` overrides). A camera that fails to open or stops
  delivering is reported in the status and retried with back-off.
- ``ros`` (:mod:`edge_agent.ros_source`): ``sensor_msgs/Image`` or ``CompressedImage`` from a
  ROS 2 topic on the bus (rmw_zenoh or zenoh-bridge-ros2dds), the header stamp as capture time,
  the topic's ``CameraInfo`` checked against the site's calibration.
- ``sim`` (registered by ``smartedge edge-agent``, see :mod:`smartedge.services`): the
  simulated site; detections computed from the simulated robot's ground truth with the scenario's
  detector noise model. Clearly labelled ``source=sim`` in the status.

Semantic clouds (paper Sec. III-C): a source with depth (a RealSense, the rendered simulated
camera) also feeds the segmentation network (:class:`edge_agent.networks.SemanticSegmenter`);
``--cloud-rate`` times a second (default 1 Hz where the source has depth) the processed frame
becomes a :class:`protocol.SemanticCloud` in the site's world frame
(:mod:`edge_agent.semantic_cloud`), published reliably on
``smartedge/<site>/edge/<camera_id>/cloud``. The status counts ``clouds_published`` and
``clouds_skipped_*`` and reports ``segmentation`` / ``cloud`` latencies.

Frame capture (``--capture DIR``, :mod:`edge_agent.capture`): the processed frames saved as
``DIR/<camera_id>/<stamp_ns>.png`` at ``--capture-rate``, within ``--capture-budget-mb``, for a
lab's own dataset (``smartedge dataset``).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Iterable, Sequence
from typing import Any, Final

import edge_agent.ros_source  # noqa: F401 (registers --source ros)
from core.runtime import Outgoing, ServiceNode, service_main
from core.session import add_session_arguments
from core.site import Site, load_site
from edge_agent.capture import FrameCapture
from edge_agent.semantic_cloud import SemanticCloudMaker
from edge_agent.sources import FrameSource, add_source_arguments, get_source, source_names
from protocol import keys
from protocol.errors import SmartedgeError, UsageError

log = logging.getLogger(__name__)

__all__ = ["EdgeAgentNode", "FrameSource", "build_node", "build_parser", "main"]

#: semantic clouds per second of a source with depth when ``--cloud-rate`` is not given
DEFAULT_CLOUD_RATE_HZ: Final = 1.0


class EdgeAgentNode(ServiceNode):
    """Publishes what the source detects; counts frames with and without a robot. With
    ``clouds`` (a :class:`SemanticCloudMaker` of this camera) it also turns the source's RGB-D
    frames (``source.rgbd_frame()``) into semantic clouds at the maker's rate."""

    service = "edge-agent"

    def __init__(
        self, site: Site, camera_id: str, source: FrameSource, tick_period_s: float = 0.01,
        preview_rate_hz: float = 0.0, clouds: SemanticCloudMaker | None = None,
        capture: FrameCapture | None = None,
    ) -> None:
        super().__init__(site.name, camera_id)
        site.camera(camera_id)  # raises a clear KeyError for an unknown camera
        self.camera_id = camera_id
        self.source = source
        self.tick_period_s = tick_period_s
        self._key = keys.detections_key(site.name, camera_id)
        self._image_key = keys.image_key(site.name, camera_id)
        self._preview_period_ns = round(1e9 / preview_rate_hz) if preview_rate_hz > 0 else 0
        self._last_preview_ns: int | None = None
        self._last_preview_stamp: int | None = None
        bind = getattr(source, "bind_stats", None)
        if bind is not None:
            bind(self.stats)
        self.clouds = clouds
        self._cloud_key = keys.edge_cloud_key(site.name, camera_id)
        self.capture = capture
        if capture is not None and capture.stats is None:
            capture.stats = self.stats
        self._last_offered_stamp: int | None = None

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        out = []
        for msg in self.source.poll(now_ns):
            self.stats.count("frames")
            self.stats.count("frames_with_robot" if msg.detections else "frames_without_robot")
            self.stats.event("detections")
            self.stats.latency("capture_to_publish", max(0, now_ns - msg.stamp_ns) * 1e-9)
            out.append(Outgoing(self._key, msg, reliable=False))
        if self._preview_period_ns and out:
            out.extend(self._preview(now_ns))
        if self.clouds is not None and out:
            out.extend(self._cloud())
        if self.capture is not None and out:
            self._capture()
        return out

    def _capture(self) -> None:
        """Offer the last processed frame to the capture (it keeps its own rate and budget)."""
        assert self.capture is not None
        frame = getattr(self.source, "last_frame", None)
        if frame is None or frame.stamp_ns == self._last_offered_stamp:
            return
        self._last_offered_stamp = frame.stamp_ns
        self.capture.offer(frame.image_rgb, frame.stamp_ns)

    def _cloud(self) -> list[Outgoing]:
        """The last processed RGB-D frame as a semantic cloud, when one is due. Runs the
        segmentation network in the worker loop (~1 Hz; detections wait that long)."""
        assert self.clouds is not None
        rgbd = getattr(self.source, "rgbd_frame", None)
        frame = rgbd() if rgbd is not None else None
        if frame is None or not self.clouds.due(frame.stamp_ns):
            return []
        cloud = self.clouds.make_for_service(frame.image_rgb, frame.depth_m, frame.stamp_ns,
                                             self.stats)
        return [] if cloud is None else [Outgoing(self._cloud_key, cloud, reliable=True)]

    def _preview(self, now_ns: int) -> list[Outgoing]:
        """The last processed frame as a JPEG for the viewer, at most at the preview rate."""
        frame = getattr(self.source, "last_frame", None)
        if frame is None or frame.stamp_ns == self._last_preview_stamp or (
                self._last_preview_ns is not None
                and now_ns - self._last_preview_ns < self._preview_period_ns):
            return []
        from edge_agent.preview import encode_preview

        self._last_preview_ns = now_ns
        self._last_preview_stamp = frame.stamp_ns
        try:
            msg = encode_preview(frame, self.camera_id)
        except (ValueError, TypeError) as exc:  # a preview must never stop the agent
            self.stats.count("preview_errors")
            log.warning("%s: no preview: %s", self.camera_id, exc)
            return []
        self.stats.count("previews")
        return [Outgoing(self._image_key, msg, reliable=False)]

    def state(self) -> tuple[str, str]:
        health = getattr(self.source, "health", None)
        state, detail = health() if health is not None else ("ok", f"source={self.source.label}")
        if self.capture is not None:
            detail = f"{detail}; {self.capture.status()}"
        return state, detail

    def attach(self, session: Any) -> None:
        """A source that reads the bus itself (``--source ros``) subscribes on the service's
        session."""
        attach = getattr(self.source, "attach", None)
        if attach is not None:
            attach(session)

    def close(self) -> None:
        closer = getattr(self.source, "close", None)
        if closer is not None:
            closer()
        if self.capture is not None:
            self.capture.close()
        super().close()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smartedge edge-agent",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--site", help="site file (optional with a source that brings its own site, e.g. sim)"
    )
    parser.add_argument("--camera", required=True, help="camera id in the site file")
    parser.add_argument("--preview-rate", type=float, default=0.0, metavar="HZ",
                        help="publish the processed frame as a JPEG for the viewer at most this "
                        "often (default 0: never; images leave the board only when asked for)")
    parser.add_argument("--cloud-rate", type=float, default=None, metavar="HZ",
                        help="semantic clouds per second from a source with depth (default "
                        f"{DEFAULT_CLOUD_RATE_HZ:g} where the source has depth; 0: none)")
    parser.add_argument("--segmentation-model", metavar="ONNX",
                        help="segmentation network for the clouds (default: the shipped one)")
    cap = parser.add_argument_group("frame capture (a lab's own dataset, edge_agent/capture.py)")
    cap.add_argument("--capture", metavar="DIR",
                     help="save processed frames to DIR/<camera>/<stamp_ns>.<png|jpg>")
    cap.add_argument("--capture-rate", type=float, default=1.0, metavar="HZ",
                     help="frames per second of capture time at most (1)")
    cap.add_argument("--capture-budget-mb", type=float, default=1000.0, metavar="MB",
                     help="disk this camera's capture may use, files already there included; "
                     "the capture stops there, detecting goes on (1000)")
    cap.add_argument("--capture-format", choices=("png", "jpg"), default="png",
                     help="png: lossless (default); jpg: --capture-jpeg-quality")
    cap.add_argument("--capture-jpeg-quality", type=int, default=95, metavar="Q",
                     help="JPEG quality 1-100 (95)")
    add_session_arguments(parser)
    add_source_arguments(parser, default="camera")
    return parser


def build_cloud_maker(args: argparse.Namespace, site: Site, camera_id: str, source: Any,
                      segmenter: Any = None) -> SemanticCloudMaker | None:
    """The cloud maker ``--cloud-rate`` asks for, or ``None`` (rate 0; a source without depth
    or a segmentation model that cannot be loaded: logged once, the agent runs without
    clouds). ``segmenter``: use this instead of loading ``--segmentation-model``."""
    rate = getattr(args, "cloud_rate", None)
    has_depth = bool(getattr(source, "provides_depth", False))
    if rate is None:
        rate = DEFAULT_CLOUD_RATE_HZ if has_depth else 0.0
    if not rate >= 0:
        raise UsageError(f"--cloud-rate {rate}: must be >= 0")
    if rate == 0:
        return None
    if not has_depth:
        log.warning("%s: --cloud-rate %g Hz, but source %s gives no depth: no semantic clouds",
                    camera_id, rate, getattr(source, "label", "?"))
        return None
    if segmenter is None:
        try:
            from edge_agent.networks import SemanticSegmenter
            from edge_agent.sources import execution_providers_from_args

            # the same providers as the detector (--providers, --fp16, --trt-cache)
            segmenter = SemanticSegmenter(getattr(args, "segmentation_model", None),
                                          threads=getattr(args, "threads", 2),
                                          providers=execution_providers_from_args(args))
        except (ImportError, SmartedgeError, OSError, RuntimeError) as exc:
            log.error("%s: no semantic clouds: the segmentation model cannot be loaded: %s",
                      camera_id, exc)
            return None
    camera = site.camera(camera_id)
    maker = SemanticCloudMaker(segmenter, camera, sensor_id=camera_id,
                               frame_id=site.world_frame, T_frame_sensor=camera.T_world_cam,
                               rate_hz=rate)
    execution = getattr(segmenter, "execution", None)
    log.info("%s: semantic clouds at %g Hz in frame %s through %s%s", camera_id, rate,
             site.world_frame, getattr(segmenter, "model_id", type(segmenter).__name__),
             "" if execution is None else
             f" on {execution.describe(getattr(segmenter, 'providers_used', []))}")
    return maker


def build_node(args: argparse.Namespace) -> EdgeAgentNode:
    """The edge agent for ``args``: the chosen source plug-in builds the frame source."""
    if not args.preview_rate >= 0:
        raise UsageError(f"--preview-rate {args.preview_rate}: must be >= 0")
    if args.cloud_rate is not None and not args.cloud_rate >= 0:
        raise UsageError(f"--cloud-rate {args.cloud_rate}: must be >= 0")
    site = load_site(args.site) if args.site else None
    capture = None
    if getattr(args, "capture", None):  # checked before a source starts its threads
        try:
            capture = FrameCapture(args.capture, args.camera, rate_hz=args.capture_rate,
                                   budget_mb=args.capture_budget_mb, fmt=args.capture_format,
                                   jpeg_quality=args.capture_jpeg_quality)
        except ValueError as exc:
            raise UsageError(str(exc)) from exc
        except OSError as exc:
            raise UsageError(f"--capture {args.capture}: {exc}") from exc
    try:
        source = get_source(args.source).build(args, site)
        site = site or getattr(source, "site", None)
        if site is None:
            raise UsageError(f"--site is required with --source {args.source}")
        clouds = build_cloud_maker(args, site, args.camera, source)
    except BaseException:
        if capture is not None:
            capture.close()
        raise
    return EdgeAgentNode(site, args.camera, source, preview_rate_hz=args.preview_rate,
                         clouds=clouds, capture=capture)


def main(argv: Sequence[str]) -> int:
    args = build_parser().parse_args(list(argv))
    unavailable = getattr(get_source(args.source), "unavailable", None)
    if unavailable:
        others = [n for n in source_names() if not getattr(get_source(n), "unavailable", None)]
        hint = (
            "use " + " or ".join(f"--source {n}" for n in others)
            if others
            else "no other frame source is registered"
        )
        print(f"smartedge edge-agent: {unavailable}; {hint}", file=sys.stderr)
        return 2
    return service_main("edge-agent", argv, build_parser, build_node)
