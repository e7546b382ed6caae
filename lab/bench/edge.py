"""``smartedge bench edge``: per-stage latency of the edge pipeline with onnxruntime.

Renders a few 848x480 views of the simulated site with the robot in view, then times on each:
the detector (resize to its input + network + peak decoding), the keypoint network (crop +
network + decoding, one robot) and the whole detector + keypoints pipeline. Prints median and
95th percentile per stage and the pipeline's frames/s, with the execution provider and thread
count, as the edge agent runs them on the CPU (test-time flips on, far band off). Three peers
in the same run: with the camera's far band (``--far-band on``, edge_agent/far_band.py: what the
band costs), onnxruntime's default spinning threads, and the same models without their
test-time flips (what the flips cost). Target: detector + keypoints >= 60 frames/s on 2 x86
cores. Then the whole per-frame
path of an edge agent on a camera streaming JPEG (decode, networks, message, msgpack, a real
Zenoh put), per stage; target >= 30 frames/s per camera.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Sequence
from typing import Any

import numpy as np


def _stats(ms: list[float]) -> str:
    a = np.asarray(ms)
    return f"median {np.median(a):6.2f} ms  p95 {np.percentile(a, 95):6.2f} ms"


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench edge", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", help="model folder (default: the shipped models)")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    parser.add_argument("--frames", type=int, default=500, help="timed frames (default 500)")
    parser.add_argument("--views", type=int, default=8, help="distinct rendered views")
    args = parser.parse_args(list(argv))

    from edge_agent.far_band import far_band_for_camera
    from edge_agent.model_cards import ModelError
    from edge_agent.models import RobotKeypointPipeline
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    try:
        pipe = RobotKeypointPipeline.from_folder(args.model,
                                     threads=args.threads)
    except ModelError as exc:
        print(f"smartedge bench edge: {exc}")
        return 1
    scenario = load_scenario()
    gen = SampleGenerator(scenario, "site", seed=77)
    frames, bands = [], []
    height_m = scenario.site.robot_model(scenario.robot_id).height_m
    i = 0
    while len(frames) < args.views and i < 50 * args.views:
        s = gen(i)
        i += 1
        if s.robots[0].bbox_xyxy is not None:
            frames.append(s.image_rgb)
            bands.append(far_band_for_camera(s.camera, height_m, pipe.detector.card.input_w))
    if not frames:
        print("smartedge bench edge: no rendered view shows the robot")
        return 1
    h, w = frames[0].shape[:2]
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}; onnxruntime {pipe.providers[0]}, "
          f"{args.threads} thread(s); frames {w}x{h}, one robot in view")
    print(f"models: {pipe.folder} (detector input {pipe.detector.card.input_w}x"
          f"{pipe.detector.card.input_h}, keypoints {pipe.keypoints.card.input_w}x"
          f"{pipe.keypoints.card.input_h}; test-time flip: detector "
          f"{'on' if pipe.detector.flip else 'off'}, keypoints "
          f"{'on' if pipe.keypoints.flip else 'off'}; far band "
          f"{bands[0].describe() if bands[0] else 'none'})")
    peer = RobotKeypointPipeline.from_folder(args.model, threads=args.threads, spinning=True)
    no_flip = RobotKeypointPipeline.from_folder(args.model, threads=args.threads, flip=False,
                                                detector_flip=False)
    medians = {}
    none = [None] * len(frames)
    for name, p, far in (("smartedge (idle threads sleep)", pipe, none),
                         ("peer: with the far band (--far-band on)", pipe, bands),
                         ("peer: onnxruntime default (spinning threads)", peer, none),
                         ("peer: no test-time flip (detector, keypoints)", no_flip, none)):
        for f, band in zip(frames, far, strict=True):  # warm-up
            p(f, far_band=band)
        det_ms, kp_ms, total_ms = [], [], []
        robots = 0
        for k in range(args.frames):
            t0 = time.perf_counter()
            found = p(frames[k % len(frames)], far_band=far[k % len(frames)])
            total_ms.append((time.perf_counter() - t0) * 1e3)
            det_ms.append(p.times.detector_ms)
            kp_ms.append(p.times.keypoints_ms)
            robots += len(found)
        medians[name] = float(np.median(total_ms))
        print(f"{name}:")
        print(f"  detector            {_stats(det_ms)}")
        print(f"  keypoints (1 robot) {_stats(kp_ms)}")
        print(f"  detector+keypoints  {_stats(total_ms)}  → "
              f"{1e3 / np.median(total_ms):.0f} frames/s (target >= 60)")
        print(f"  robots found per frame: {robots / args.frames:.2f}")
    ours, band, spinning, plain = medians.values()
    print(f"ratio: smartedge takes {ours / spinning:.2f}x the time of onnxruntime's default "
          f"per frame, {ours / plain:.2f}x the time without the test-time flips; the far band "
          f"takes {band / ours:.2f}x the time without it")
    _whole_pipeline(pipe, frames, None, args.frames)
    return 0


def _whole_pipeline(models: Any, frames: list[np.ndarray], far_band: Any, count: int) -> None:
    """The edge agent's whole per-frame path as on a camera streaming MJPEG: decode the JPEG
    (the grab), detector + keypoints into a RobotDetections, msgpack encode, put on a real
    Zenoh session (peer on loopback)."""
    import cv2
    import zenoh

    from core.session import loopback_config
    from edge_agent.frames import Frame
    from edge_agent.pipeline import EdgePipeline
    from protocol import codec

    jpegs = [cv2.imencode(".jpg", f[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
             for f in frames]
    pipeline = EdgePipeline("cam1", models, expected_size=frames[0].shape[1::-1],
                            far_band=far_band)
    stages: dict[str, list[float]] = {"decode": [], "detector": [], "keypoints": [],
                                      "encode+publish": [], "whole": []}
    with zenoh.open(loopback_config(listen=["tcp/127.0.0.1:0"])) as session:
        pub = session.declare_publisher("lab/bench/edge/cam1/detections")
        for k in range(count):
            t0 = time.perf_counter()
            bgr = cv2.imdecode(np.frombuffer(jpegs[k % len(jpegs)], np.uint8), cv2.IMREAD_COLOR)
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            t1 = time.perf_counter()
            msg, lat = pipeline.process(Frame(rgb, time.time_ns(), k + 1))
            t2 = time.perf_counter()
            pub.put(codec.encode(msg))
            t3 = time.perf_counter()
            stages["decode"].append((t1 - t0) * 1e3)
            stages["detector"].append(lat.detector_s * 1e3)
            stages["keypoints"].append(lat.keypoints_s * 1e3)
            stages["encode+publish"].append((t3 - t2) * 1e3)
            stages["whole"].append((t3 - t0) * 1e3)
        pub.undeclare()
    print("whole edge pipeline (JPEG decode → networks → RobotDetections → msgpack → Zenoh put):")
    for name, ms in stages.items():
        print(f"  {name:<19} {_stats(ms)}")
    print(f"  → {1e3 / np.median(stages['whole']):.0f} frames/s per camera (target >= 30)")
