"""Your own camera as an edge agent's frame source: a grabber around a vendor SDK, offered as
``--source vendor`` next to the sources the edge agent ships (camera, ros, sim).

The edge agent runs every frame source's images through the same ONNX detector and keypoint
networks and publishes ``RobotDetections`` on ``smartedge/<site>/edge/<camera>/detections``.
A new camera needs only a *grabber*: ``open()``, ``read() -> Frame`` (an RGB image and its
capture stamp in ns, the time the frame was exposed) and ``close()``. Here the "SDK" hands out
the images of a folder in turn, stamped when they are grabbed; replace
:meth:`VendorGrabber._next_image` with your SDK's call (and its own capture stamp if it has one).

    .venv/bin/python examples/frame_source.py --site simulation/sites/paper_lab.yaml \\
        --camera cam1 --source vendor --vendor-folder runs/frames --vendor-rate 5
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from core.site import Site
from edge_agent.frames import Frame, FrameSourceError, LatestFrameReader
from edge_agent.models import models_for_site
from edge_agent.pipeline import EdgePipeline
from edge_agent.sources import CameraFrameSource, register_source
from protocol.errors import UsageError


class VendorGrabber:
    """A blocking frame input (the edge agent's ``Grabber``): one frame per ``read()``."""

    label = "vendor"

    def __init__(self, folder: Path, rate_hz: float) -> None:
        self.folder = folder
        self.period_s = 1.0 / rate_hz
        self.paths: list[Path] = []
        self.index = 0
        self.seq = 0

    def open(self) -> None:
        """Connect to the camera; a :class:`FrameSourceError` says why it cannot (the agent
        reports it in its status and tries again)."""
        self.paths = sorted(p for p in self.folder.glob("*") if p.suffix in (".png", ".jpg"))
        if not self.paths:
            raise FrameSourceError(f"{self.folder}: no .png or .jpg images")

    def _next_image(self) -> np.ndarray:
        """The SDK's call: the next image, BGR as OpenCV reads it."""
        image = cv2.imread(str(self.paths[self.index % len(self.paths)]))
        self.index += 1
        if image is None:
            raise FrameSourceError(f"{self.paths[(self.index - 1) % len(self.paths)]}: "
                                   "unreadable")
        return image

    def read(self) -> Frame | None:
        time.sleep(self.period_s)  # the camera's frame rate
        image_bgr = self._next_image()
        stamp_ns = time.time_ns()  # the capture time (an SDK's exposure stamp is better)
        self.seq += 1
        return Frame(np.ascontiguousarray(image_bgr[..., ::-1]), stamp_ns, self.seq)

    def close(self) -> None:
        self.paths = []


class VendorSourcePlugin:
    """``--source vendor``: its own options, and the source built from them."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        group = parser.add_argument_group("vendor camera (--source vendor)")
        group.add_argument("--vendor-folder", type=Path, help="the images the SDK hands out")
        group.add_argument("--vendor-rate", type=float, default=5.0, help="frames per second")

    def build(self, args: argparse.Namespace, site: Site | None) -> CameraFrameSource:
        if site is None or args.vendor_folder is None:
            raise UsageError("--source vendor needs --site and --vendor-folder")
        camera = site.camera(args.camera)  # the calibration: image size, intrinsics, pose
        # the site's robot models' networks (--model, --threads as for --source camera)
        models = models_for_site(site, args.model, threads=args.threads)
        pipeline = EdgePipeline(args.camera, models, min_score=args.min_score,
                                expected_size=(camera.width, camera.height))
        grabber = VendorGrabber(args.vendor_folder, args.vendor_rate)
        return CameraFrameSource(LatestFrameReader(grabber).start(), pipeline, grabber.label)


def main(argv: Sequence[str]) -> int:
    """The edge agent (``smartedge edge-agent``) with ``--source vendor`` offered."""
    register_source("vendor", VendorSourcePlugin())
    from edge_agent.service import main as edge_agent_main

    return edge_agent_main(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
