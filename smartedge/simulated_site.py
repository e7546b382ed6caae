"""The simulated site as plug-ins of the services: a frame source and a robot adapter.

The services know only their own registries (:mod:`edge_agent.sources`,
:mod:`robot_bridge.adapters.registry`) and never import the simulation; the simulation knows
only :mod:`protocol`. This module, on the top floor, knows both and registers the simulated site
into the services:

- ``--source sim`` of the edge agent: one camera of :class:`simulation.live.LiveSimulation`
  (:class:`simulation.live.CameraFeed`);
- ``--adapter sim`` of the robot bridge: the simulated robot of the same live simulation,
  through :class:`robot_bridge.adapters.sim.SimRobotAdapter`, stepped by the bridge's loop
  (a fleet, ``--sim-robots N``: the robot named by the bridge's ``--robot``, one bridge each).

The composition root (:mod:`smartedge.services`) registers them before a service parses its
options. The service registries are imported only when something is registered into them, so
the edge agent's command never loads the robot bridge.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from typing import TYPE_CHECKING, Any

from core.site import Site
from edge_agent.sources import PipelineSource
from protocol.messages import RobotDetections

if TYPE_CHECKING:
    from robot_bridge.adapters.registry import AdapterSetup

log = logging.getLogger(__name__)



class SimulatedCameraSource:
    """The detections of one camera of the simulated site; the site comes with it."""

    label = "sim"

    def __init__(self, feed: Any, site: Site) -> None:
        self._feed = feed
        self.site = site

    def poll(self, now_ns: int) -> list[RobotDetections]:
        return self._feed.poll(now_ns)


class RenderedCameraSource(PipelineSource):
    """One simulated camera's rendered images through the edge's ONNX pipeline (the closed
    loop: the same models and code as on a real camera); the site comes with it."""

    label = "sim-render"
    #: an RGB-D camera: the renderer's depth with the simulation's depth noise
    provides_depth = True

    def __init__(self, feed: Any, pipeline: Any, site: Site) -> None:
        super().__init__(pipeline)
        self._feed = feed
        self.site = site

    def rgbd_frame(self) -> Any:
        """The last processed frame with its depth (rendered, noisy; made only when asked for,
        at the cloud rate, from the same render)."""
        frame = self.last_frame
        if frame is None:
            return None
        if frame.depth_m is None:
            frame = dataclasses.replace(frame, depth_m=self._feed.depth(frame.stamp_ns))
            self.last_frame = frame
        return frame

    def poll(self, now_ns: int) -> list[RobotDetections]:
        from edge_agent.frames import Frame

        capture_ns = self._feed.due(now_ns)
        if capture_ns is None:
            return []
        t0 = time.perf_counter()
        image = self._feed.render(capture_ns)
        render_s = time.perf_counter() - t0
        frame = Frame(image, capture_ns, self._feed.seq)
        return [self.process(frame, now_ns, self._feed.skipped, {"render": render_s})]

    def health(self) -> tuple[str, str]:
        detail = f"source={self.label} frames={self._feed.seq} skipped={self._feed.skipped}"
        if self._feed.seq > 10 and self._feed.skipped > self._feed.seq:
            return "degraded", f"{detail}; rendering + inference cannot keep up with the rate"
        return "ok", detail


class SimSourcePlugin:
    """``--source sim``: the edge agent of one camera of a live simulation: detections from
    the scenario's noise model (``--detections noise``) or rendered images through the ONNX
    models (``--detections cnn``)."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        from simulation.live import add_sim_arguments

        group = add_sim_arguments(parser)
        group.add_argument("--detections", choices=("noise", "cnn"), default="noise",
                           help="sim source: the detection noise model (default) or rendered "
                           "images through the ONNX detector + keypoint models (--model, "
                           "--threads, --min-score as for the camera source)")
        group.add_argument("--render-rate", type=float, default=None, metavar="HZ",
                           help="sim source with --detections cnn: frames per second "
                           "(default: the scenario's camera rate)")

    def build(self, args: argparse.Namespace, site: Site | None
              ) -> SimulatedCameraSource | RenderedCameraSource:
        from simulation.live import CameraFeed, LiveSimulation, spec_from_args

        live = LiveSimulation(spec_from_args(args))
        if getattr(args, "detections", "noise") == "cnn":
            if len(live.robot_ids) > 1:
                from protocol.errors import UsageError

                raise UsageError("--sim-robots > 1: the rendered cameras draw one robot; use "
                                 "--detections noise for a fleet")
            return self._build_rendered(args, live)
        feed = CameraFeed(live, args.camera)
        log.info(
            "edge agent %s: SIMULATED source (scenario %s, trajectory %s, t0 in %.1f s)",
            args.camera,
            live.scenario.name,
            live.spec.trajectory,
            (live.spec.epoch_ns - time.time_ns()) * 1e-9,
        )
        return SimulatedCameraSource(feed, live.site)

    @staticmethod
    def _build_rendered(args: argparse.Namespace, live: Any) -> RenderedCameraSource:
        from edge_agent.models import RobotKeypointPipeline
        from edge_agent.pipeline import EdgePipeline, far_band_from_args
        from simulation.live import RenderedCameraFeed

        model = live.site.robot_model(live.robot_id)
        threads = getattr(args, "threads", 2)
        models = RobotKeypointPipeline.for_robot(model, getattr(args, "model", None),
                                                 threads=threads)
        feed = RenderedCameraFeed(live, args.camera, rate_hz=args.render_rate)
        camera = live.site.cameras[args.camera]
        pipeline = EdgePipeline(args.camera, models, min_score=getattr(args, "min_score", 0.3),
                                expected_size=(camera.width, camera.height),
                                far_band=far_band_from_args(args, live.site, models))
        log.info("edge agent %s: SIMULATED camera, rendered images through %s at %.1f Hz "
                 "(scenario %s, trajectory %s)", args.camera, models.model_id,
                 feed.rate_hz, live.scenario.name, live.spec.trajectory)
        return RenderedCameraSource(feed, pipeline, live.site)


class SimAdapterPlugin:
    """``--adapter sim``: the simulated robot of a live simulation, stepped by the bridge."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        from simulation.live import add_sim_arguments

        group = add_sim_arguments(parser)
        group.add_argument(
            "--kidnapped",
            action="store_true",
            help="sim adapter: the robot starts without localization",
        )

    def build(self, args: argparse.Namespace, site: Site | None) -> AdapterSetup:
        from robot_bridge.adapters.registry import AdapterSetup
        from robot_bridge.adapters.sim import SimRobotAdapter
        from simulation.live import LiveSimulation, spec_from_args

        live = LiveSimulation(spec_from_args(args))
        robot_id = getattr(args, "robot", None) or live.robot_id
        if robot_id not in live.runs:
            from protocol.errors import UnknownIdError

            raise UnknownIdError(f"--robot {robot_id!r} is not in the simulation; its robots: "
                                 f"{list(live.robot_ids)}")
        run = live.runs[robot_id]
        adapter = SimRobotAdapter(run.robot, localized=not args.kidnapped)

        def advance(now_ns: int) -> None:
            adapter.advance_to(live.t_s(now_ns))

        log.info(
            "robot bridge %s: SIMULATED robot (scenario %s, %s, t0 in %.1f s)",
            robot_id,
            live.scenario.name,
            f"trajectory {live.spec.trajectory}" if len(live.robot_ids) == 1
            else f"crossing route of a fleet of {len(live.robot_ids)}",
            (live.spec.epoch_ns - time.time_ns()) * 1e-9,
        )
        return AdapterSetup(
            factory=lambda session: adapter, advance=advance, site=live.site,
            robot_id=robot_id,
        )


SIM_SOURCE = SimSourcePlugin()
SIM_ADAPTER = SimAdapterPlugin()


def register_sim_source() -> None:
    """Offer ``--source sim`` in the edge agent (idempotent: the registry ignores the same
    plug-in registered again)."""
    from edge_agent.sources import register_source

    register_source("sim", SIM_SOURCE)


def register_sim_adapter() -> None:
    """Offer ``--adapter sim`` in the robot bridge (idempotent, as above)."""
    from robot_bridge.adapters.registry import register_adapter

    register_adapter("sim", SIM_ADAPTER)


def register_simulation() -> None:
    """Register the simulated site into every service registry (idempotent)."""
    register_sim_source()
    register_sim_adapter()
