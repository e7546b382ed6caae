"""Frame sources of the edge agent and the registry the ``--source`` option is built from.

A source plug-in is registered under a name (:func:`register_source`); the edge agent's parser
offers every registered name as a ``--source`` choice, lets each plug-in add its own argument
group, and builds the chosen source with ``plugin.build(args, site)``.

The edge agent registers only what it ships (``camera``: OpenCV, image folders, RealSense
through the ONNX models). Anything else, such as the simulated
site, is registered from the top floor (:mod:`smartedge.simulated_site`): this package never imports
the code that provides it.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any, Protocol

from core.plugins import PluginRegistry
from core.site import Site
from edge_agent.far_band import FAR_BAND_CHOICES
from protocol.errors import UsageError
from protocol.messages import RobotDetections

log = logging.getLogger(__name__)


class FrameSource(Protocol):
    """Produces the detections of one camera that are due at ``now_ns``.

    ``label`` names the source in the status (``sim``, ``camera``...). A source that brings its
    own site (the simulated one) may also have a ``site`` attribute: the edge agent uses it when
    no ``--site`` was given. An RGB-D source has ``provides_depth = True`` and a method
    ``rgbd_frame() -> Frame | None`` returning its last processed frame with ``depth_m`` (the
    edge agent turns some of them into semantic clouds).
    """

    label: str

    def poll(self, now_ns: int) -> list[RobotDetections]: ...


class SourcePlugin(Protocol):
    """A kind of frame source, as registered under a ``--source`` name.

    ``add_arguments(parser)`` adds the plug-in's own argument group (it is called once per
    parser for every registered plug-in, whichever source is chosen). ``build(args, site)``
    returns the source for the parsed ``args``; ``site`` is the site file given with
    ``--site`` (``None`` when there was none). Bad options raise ``ValueError`` or
    ``KeyError`` with a message for the user.

    A plug-in may have an ``unavailable`` attribute: a non-empty string saying why it cannot
    run in this installation; the edge agent then prints it and exits with code 2.
    """

    def add_arguments(self, parser: argparse.ArgumentParser) -> None: ...

    def build(self, args: argparse.Namespace, site: Site | None) -> FrameSource: ...


#: the ``--source`` plug-ins (the service registers its own; the top floor adds more)
SOURCES: PluginRegistry[SourcePlugin] = PluginRegistry("--source", "frame source")


def register_source(name: str, plugin: SourcePlugin) -> None:
    """Offer ``plugin`` as ``--source name`` (see :meth:`PluginRegistry.register`)."""
    SOURCES.register(name, plugin)


def source_names() -> tuple[str, ...]:
    """The registered ``--source`` names, sorted."""
    return SOURCES.names()


def get_source(name: str) -> SourcePlugin:
    """The plug-in registered as ``name`` (``KeyError`` naming the known ones otherwise)."""
    return SOURCES.get(name)


def add_source_arguments(parser: argparse.ArgumentParser, default: str) -> None:
    """``--source`` with the registered names as choices, then every plug-in's own group."""
    SOURCES.add_arguments(parser, default)


class PipelineSource:
    """What every image source shares: frames through the ONNX pipeline
    (:class:`edge_agent.pipeline.EdgePipeline`), per-stage latencies, skipped frames and (several
    robot types) duplicate boxes dropped across types recorded in the service's stats, and the
    last processed frame kept for the viewer's preview (:attr:`last_frame`, the frame of the
    last message :meth:`process` returned)."""

    label = "camera"
    #: whether the frames carry depth (:meth:`rgbd_frame`)
    provides_depth = False

    def __init__(self, pipeline: Any) -> None:
        self.pipeline = pipeline
        self.last_frame: Any = None
        self._stats: Any = None
        #: totals already added to the service's counters, per counter
        self._counted: dict[str, int] = {}

    def rgbd_frame(self) -> Any:
        """The last processed frame if it has depth (``Frame.depth_m``), else ``None``."""
        frame = self.last_frame
        return frame if frame is not None and frame.depth_m is not None else None

    def bind_stats(self, stats: Any) -> None:
        """Record per-stage latencies and skipped frames in the service's stats."""
        self._stats = stats

    def process(self, frame: Any, now_ns: int, skipped_total: int,
                extra_latency_s: dict[str, float] | None = None) -> RobotDetections:
        """``frame`` through the pipeline; ``skipped_total``: frames the source skipped so far;
        ``extra_latency_s``: more stages to record (e.g. ``render``)."""
        msg, lat = self.pipeline.process(frame)
        self.last_frame = frame
        stats = self._stats
        if stats is not None:
            for stage, seconds in (extra_latency_s or {}).items():
                stats.latency(stage, seconds)
            stats.latency("detector", lat.detector_s)
            stats.latency("keypoints", lat.keypoints_s)
            stats.latency("grab_to_detections", max(0, now_ns - frame.stamp_ns) * 1e-9
                          + lat.detector_s + lat.keypoints_s)
            models = getattr(self.pipeline, "models", None)
            for counter, total in (
                    ("frames_skipped", skipped_total),
                    # boxes whose keypoints were not found: no robot
                    ("boxes_without_keypoints", getattr(models, "unconfirmed", 0)),
                    # far robots only the far band found (--far-band)
                    ("far_band_boxes", getattr(models, "far_band_added", 0)),
                    # several robot types: boxes of two types' detectors on one robot, the
                    # weaker dropped; boxes of another type's robot
                    ("duplicate_boxes_dropped", getattr(models, "duplicates_dropped", 0)),
                    ("boxes_not_of_their_type", getattr(models, "type_rejected", 0))):
                self._count_total(stats, counter, total)
        return msg

    def _count_total(self, stats: Any, counter: str, total: int) -> None:
        """Add to ``counter`` what ``total`` (a running count kept elsewhere) grew by."""
        seen = self._counted.get(counter, 0)
        if total > seen:
            stats.count(counter, total - seen)
            self._counted[counter] = total


class CameraFrameSource(PipelineSource):
    """A camera (or stream, file, image folder) through the ONNX pipeline: each poll takes the
    newest frame from the reader thread and turns it into a :class:`RobotDetections`."""

    def __init__(self, reader: Any, pipeline: Any, label: str) -> None:
        super().__init__(pipeline)
        self.reader = reader
        self.label = label
        self.provides_depth = bool(getattr(reader.grabber, "depth", False))
        self._refused_seen = 0

    def poll(self, now_ns: int) -> list[RobotDetections]:
        frame = self.reader.take()
        if frame is None:
            return []
        refused = int(getattr(self.reader.grabber, "stamps_refused", 0))
        if refused > self._refused_seen and self._stats is not None:
            self._stats.count("stamps_refused", refused - self._refused_seen)
            self._refused_seen = refused
        return [self.process(frame, now_ns, self.reader.status().skipped)]

    def health(self) -> tuple[str, str]:
        st = self.reader.status()
        detail = f"source={self.label} frames={st.grabbed} skipped={st.skipped}"
        extra = runtime_detail(self.pipeline, self.reader.grabber)
        if extra:
            detail += " " + extra
        if st.state == "ok":
            if providers_fell_back(self.pipeline):  # e.g. a Jetson running on its CPU
                return "degraded", f"{detail}; the networks run on less than was asked"
            return "ok", detail
        if st.state == "ended":
            return "degraded", f"{detail}; the source ended"
        if st.state == "opening":
            return "starting", detail
        if st.state == "stopped":
            return "stopping", detail
        return "degraded", f"{detail}; {st.error} (retry in {st.retry_in_s:.1f} s)"

    def close(self) -> None:
        self.reader.stop()


def execution_providers_from_args(args: argparse.Namespace) -> Any:
    """The :class:`edge_agent.providers.ExecutionProviders` of ``--providers``, ``--fp16`` and
    ``--trt-cache`` (the same for every network of the agent); ``UsageError`` for an unknown
    provider name or a cache folder that cannot be created."""
    from edge_agent.model_cards import ModelError
    from edge_agent.providers import execution_providers

    try:
        return execution_providers(getattr(args, "providers", "auto") or "auto",
                                   fp16=bool(getattr(args, "fp16", False)),
                                   engine_cache=getattr(args, "trt_cache", None))
    except (ValueError, ModelError) as exc:
        raise UsageError(str(exc)) from None


def runtime_detail(pipeline: Any, grabber: Any = None) -> str:
    """The status words on what the networks run on (``providers=...``, naming a fallback)
    and, for a grabber that says, where frame stamps come from (``stamp_source=driver|grab``
    and the driver stamps refused)."""
    parts = []
    models = getattr(pipeline, "models", None)
    note = getattr(models, "providers_note", None)
    if note is not None:
        parts.append(f"providers={note()}")
    stamps = getattr(grabber, "stamp_source", None)
    if stamps:
        parts.append(f"stamp_source={stamps}")
        refused = int(getattr(grabber, "stamps_refused", 0))
        if refused:
            parts.append(f"stamps_refused={refused}")
    return " ".join(parts)


def providers_fell_back(pipeline: Any) -> bool:
    """Whether the pipeline's networks run on less than ``--providers`` asked for (asked
    TensorRT, got CUDA or the CPU; ``auto``: less than the best this onnxruntime has)."""
    models = getattr(pipeline, "models", None)
    execution = getattr(models, "execution", None)
    if execution is None:
        return False
    return bool(execution.fell_back(models.providers_used))


class CameraSourcePlugin:
    """``--source camera``: frames from OpenCV (``--device``: index, device path, stream URL or
    video file), an image folder (``--images``) or a RealSense (``--realsense``), through the
    site robot model's ONNX models (``--model`` overrides)."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        g = parser.add_argument_group("camera source (--source camera)")
        what = g.add_mutually_exclusive_group()
        what.add_argument("--device", metavar="URI",
                          help="OpenCV input: device index (0), device path (/dev/video0), "
                          "stream URL (rtsp://..., http://...), video file, GStreamer "
                          "pipeline ending in appsink, or csi://N (a Jetson CSI camera at the "
                          "calibration's size; both need an OpenCV with GStreamer)")
        what.add_argument("--images", metavar="DIR", help="a folder of images, in name order")
        what.add_argument("--realsense", nargs="?", const="", metavar="SERIAL",
                          help="an Intel RealSense colour stream, with depth aligned to it "
                          "unless --cloud-rate 0 (needs pyrealsense2)")
        g.add_argument("--rate", type=float, default=10.0,
                       help="--images: frames per second (0: every image in turn, each as soon "
                       "as the previous one is processed; default 10)")
        g.add_argument("--loop", action="store_true", help="--images / video file: loop")
        g.add_argument("--model", metavar="DIR",
                       help="model folder (detector.onnx + keypoints.onnx with their cards); "
                       "default: the site's robot model's models, else the shipped ones")
        g.add_argument("--threads", type=int, default=2, help="onnxruntime threads (default 2)")
        g.add_argument("--providers", default="auto",
                       help="onnxruntime execution providers for all networks (detector, "
                       "keypoints, segmentation), comma-separated: tensorrt, cuda, cpu or "
                       "onnxruntime's names; each falls back to the next (tensorrt → cuda → "
                       "cpu); auto (default): the best this onnxruntime has. Asked vs got is "
                       "logged and shown in the status")
        g.add_argument("--fp16", action="store_true",
                       help="TensorRT: build FP16 engines (faster on a Jetson; check accuracy "
                       "with smartedge evaluate)")
        g.add_argument("--trt-cache", metavar="DIR", default=None,
                       help="TensorRT engine cache (default $SMARTEDGE_TRT_CACHE, else "
                       "trt_engines in the service's state directory, $STATE_DIRECTORY)")
        g.add_argument("--min-score", type=float, default=0.3,
                       help="detector score below which a box is dropped (default 0.3)")
        g.add_argument("--far-band", choices=FAR_BAND_CHOICES, default="auto",
                       help="on: the detector also runs the rows where robots 7 m and more "
                       "from the camera appear, at twice its scale (computed from the camera's "
                       "calibration; docs/models.md, 'The far band'); off: the whole frame "
                       "only; auto (default): on where the networks run on a GPU, off on the "
                       "CPU (there the networks take 1.6-1.7x as long with it)")

    def build(self, args: argparse.Namespace, site: Site | None) -> FrameSource:
        from edge_agent.frames import (
            FrameSourceError,
            ImageFolderGrabber,
            LatestFrameReader,
            OpenCVGrabber,
            RealSenseGrabber,
            check_gstreamer,
            expand_device_uri,
        )
        from edge_agent.models import RobotTypesPipeline, models_for_site
        from edge_agent.pipeline import EdgePipeline, far_band_from_args

        if site is None:
            raise UsageError("--source camera needs --site (the camera's calibration and the "
                             "robot model)")
        camera = site.camera(args.camera)
        if args.images:
            grabber: Any = ImageFolderGrabber(args.images, rate_hz=args.rate, loop=args.loop)
        elif args.realsense is not None:
            grabber = RealSenseGrabber(args.realsense or None, width=camera.width,
                                       height=camera.height,
                                       depth=getattr(args, "cloud_rate", None) != 0)
        elif args.device:
            try:  # a GStreamer pipeline on an OpenCV without GStreamer: fail at start
                check_gstreamer(args.device)
                expand_device_uri(args.device, camera.width, camera.height, None)
            except FrameSourceError as exc:
                raise UsageError(str(exc)) from None
            grabber = OpenCVGrabber(args.device, width=camera.width, height=camera.height,
                                    loop=args.loop)
        else:
            raise UsageError("--source camera needs --device URI, --images DIR or --realsense")
        providers = execution_providers_from_args(args)
        # the networks of every robot model (type) of the site, one set per model (a
        # ModelError names the model and its files)
        models = models_for_site(site, args.model, threads=args.threads, providers=providers)
        files = (models.describe() if isinstance(models, RobotTypesPipeline)
                 else f"{models.detector.path} and {models.keypoints.path}")
        log.info("%s: models %s on %s, %d thread(s)", args.camera, files,
                 models.providers_note(), args.threads)
        pipeline = EdgePipeline(args.camera, models, min_score=args.min_score,
                                expected_size=(camera.width, camera.height),
                                far_band=far_band_from_args(args, site, models))
        lossless = bool(args.images) and args.rate <= 0
        reader = LatestFrameReader(grabber, lossless=lossless).start()
        return CameraFrameSource(reader, pipeline, grabber.label)


register_source("camera", CameraSourcePlugin())
