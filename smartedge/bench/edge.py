"""``smartedge bench edge``: per-stage latency of the edge pipeline with onnxruntime.

Renders a few 848x480 views of the simulated site with the robot in view, then times on each:
the detector (resize to its input + network + peak decoding), the keypoint network (crop +
network + decoding, one robot) and the whole detector + keypoints pipeline. Prints median and
95th percentile per stage and the pipeline's frames/s, with the execution provider and thread
count. Target (issue 11): detector + keypoints >= 60 frames/s on 2 x86 cores.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Sequence

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

    from edge_agent.models import ModelError, RobotKeypointPipeline
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
    frames = []
    i = 0
    while len(frames) < args.views and i < 50 * args.views:
        s = gen(i)
        i += 1
        if s.robots[0].bbox_xyxy is not None:
            frames.append(s.image_rgb)
    if not frames:
        print("smartedge bench edge: no rendered view shows the robot")
        return 1
    h, w = frames[0].shape[:2]
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}; onnxruntime {pipe.providers[0]}, "
          f"{args.threads} thread(s); frames {w}x{h}, one robot in view")
    print(f"models: {pipe.folder} (detector input {pipe.detector.card.input_w}x"
          f"{pipe.detector.card.input_h}, keypoints {pipe.keypoints.card.input_w}x"
          f"{pipe.keypoints.card.input_h})")
    peer = RobotKeypointPipeline.from_folder(args.model, threads=args.threads, spinning=True)
    medians = {}
    for name, p in (("smartedge (idle threads sleep)", pipe),
                    ("peer: onnxruntime default (spinning threads)", peer)):
        for f in frames:  # warm-up
            p(f)
        det_ms, kp_ms, total_ms = [], [], []
        robots = 0
        for k in range(args.frames):
            t0 = time.perf_counter()
            found = p(frames[k % len(frames)])
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
    ours, theirs = medians.values()
    print(f"ratio: smartedge takes {ours / theirs:.2f}x the time of the peer per frame")
    return 0
