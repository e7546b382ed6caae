"""``smartedge bench render``: rendered images per second with exact labels.

For each case (the simulated site seen from its own cameras, and domain-randomized scenes; at
848x480 and 256x192) a :class:`simulation.dataset.SampleGenerator` renders samples in this
process: scene assembly, one GL pass (colour, depth, instance and class ids, read back), the
distortion remap and the keypoint/box labels; randomized samples include the image
augmentation. One line per case with ``images/s``. Target: >= 100 images/s at 848x480.
"""

from __future__ import annotations

import argparse
import platform
import time
from collections.abc import Sequence

CASES = (("site", 848, 480), ("site", 256, 192), ("randomized", 848, 480),
         ("randomized", 256, 192))


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench render", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=5.0, help="measured time per case")
    parser.add_argument("--warmup", type=int, default=5, help="unmeasured images per case")
    args = parser.parse_args(list(argv))

    import os

    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}; one process; labels included")
    for mode, w, h in CASES:
        gen = SampleGenerator(scenario, mode, seed=1, width=w, height=h)
        renderer = gen._renderer(w, h)
        for i in range(args.warmup):
            gen(i)
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < args.seconds:
            gen(args.warmup + n)
            n += 1
        rate = n / (time.perf_counter() - t0)
        tris = getattr(renderer, "last_triangles", None)
        extra = f", {tris} triangles" if tris else ""
        print(f"  {mode:<10} {w}x{h}: {rate:7.1f} images/s ({n} images{extra})")
    return 0
