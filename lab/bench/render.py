"""``smartedge bench render``: rendered images per second with exact labels, where the time
goes, and how far that is from what the GL itself can do.

For each case (the simulated site seen from its own cameras, and domain-randomized training
scenes; at 848x480 and 256x192) a :class:`simulation.dataset.SampleGenerator` renders samples:
scene assembly, one GL pass (colour, depth, instance and class ids, read back), the distortion
remap and the keypoint/box labels; randomized samples include the image augmentation. Per case,
in the same run and in alternating rounds (so a shared machine's load hits all alike):

- ``one view at a time``: ``generator(index)`` in this process: the previous configuration
  and the reference of the ratios;
- ``batched``: ``generator.samples(indices)``, ``--batch`` views per call
  (:meth:`simulation.render_gl.Renderer.render_many`: one context switch, uploads together);
- ``pool``: a :class:`simulation.dataset.SamplePool` of ``--workers`` processes, each with
  its own EGL context, returning only the labels;

then the per-stage breakdown (GL synchronized per stage, so stages do not overlap) and the
GL floor: every draw call of a view (triangles, textures, shaders, framebuffer size) replayed
from pre-computed uniforms with the clears and read-back and no other per-frame work, untiled
and with ``--tiles`` views tiled into one framebuffer; for site views also the floor of what
the renderer really draws (the kept render of the site's static objects copied back, the robot
and people drawn on top). ``cpu-ms/image`` counts every thread of the
rendering processes, so it stays comparable on a loaded machine where images/s does not.
Targets: >= 100 site images/s and >= 50 randomized images/s at 848x480.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable, Sequence
from typing import Any

CASES = (("site", 848, 480), ("randomized", 848, 480), ("site", 256, 192),
         ("randomized", 256, 192))
#: stage names as printed
STAGE_LABELS = {"scene": "scene", "lens_map": "lens map", "upload": "upload", "draw": "draw",
                "read_back": "read-back", "remap": "remap", "labels": "labels",
                "augment": "augment"}


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WIDTHxHEIGHT") from None
    return w, h


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench render", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=4.0,
                        help="measured time per configuration and case (split into rounds)")
    parser.add_argument("--rounds", type=int, default=4,
                        help="alternating rounds the configurations' time is split into")
    parser.add_argument("--batch", type=int, default=8, help="views per batched call")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="pool processes (0: no pool); default: one per core")
    parser.add_argument("--gl-threads", type=int, default=1,
                        help="llvmpipe rasterizer threads per pool worker (LP_NUM_THREADS)")
    parser.add_argument("--tiles", type=int, default=4,
                        help="views tiled into one framebuffer for the tiled GL floor (0: skip)")
    parser.add_argument("--modes", default="site,randomized", help="comma-separated modes")
    parser.add_argument("--sizes", default="848x480,256x192", type=str,
                        help="comma-separated WIDTHxHEIGHT")
    args = parser.parse_args(list(argv))
    modes = [m for m in args.modes.split(",") if m]
    sizes = [_size(s) for s in args.sizes.split(",") if s]

    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}; load average {load:.2f} at start (on a shared machine "
          "compare the ratios within this run); labels included")
    first = True
    for mode, w, h in [(m, w, h) for (w, h) in sizes for m in modes]:
        gen = SampleGenerator(scenario, mode, seed=1, width=w, height=h)
        renderer = gen.renderer(w, h)
        if first:
            print(f"GL: {renderer.gl_renderer}")
            first = False
        _case(gen, w, h, args)
    return 0


def _case(gen: Any, w: int, h: int, args: argparse.Namespace) -> None:
    from simulation.dataset import SamplePool, sample_summary
    from simulation.render_stages import StageTimes

    warm = list(range(2 * args.batch))
    gen.samples(warm)  # GL context, shaders, static meshes, textures, lens maps
    probe = [gen.view(i) for i in range(args.batch)]
    renderer = gen.renderer(w, h)
    internal = renderer.lens_map(probe[0].camera).render_size
    triangles = sum(sum(len(o.mesh.faces) for o in v.scene.objects) for v in probe) / len(probe)
    print(f"{gen.mode} {w}x{h} (internal render {internal[0]}x{internal[1]}, "
          f"{triangles:.0f} triangles per view)")

    next_index = [10_000]

    def indices(n: int) -> list[int]:
        start = next_index[0]
        next_index[0] += n
        return list(range(start, start + n))

    def one_at_a_time(n: int) -> None:
        for i in indices(n):
            gen(i)

    def batched(n: int) -> None:
        gen.samples(indices(n))

    configs: dict[str, Callable[[int], None]] = {"one view at a time (previous)": one_at_a_time,
                                                 f"batched ({args.batch} views per call)": batched}
    pool = None
    if args.workers > 0:
        pool = SamplePool(gen, args.workers, chunk=args.batch, gl_threads=args.gl_threads)
        pool.warm_up()

        def pooled(n: int) -> None:
            assert pool is not None
            for _ in pool.map(sample_summary, indices(n)):
                pass

        configs[f"pool, {args.workers} workers"] = pooled
    try:
        results = _measure(configs, args, pool)
    finally:
        if pool is not None:
            pool.close()
    base = results["one view at a time (previous)"][0]
    for name, (rate, cpu_ms) in results.items():
        print(f"  {name:<32} {rate:7.1f} images/s  {cpu_ms:6.1f} cpu-ms/image  "
              f"x{rate / base:.2f}")

    gen.times = StageTimes()
    t0, n = time.perf_counter(), 0
    while time.perf_counter() - t0 < args.seconds / 2:
        gen.samples(indices(args.batch))
        n += args.batch
    per_image = gen.times.per_image_ms()
    gen.times = None
    wall_ms = 1000.0 * (time.perf_counter() - t0) / n
    stages = " | ".join(f"{STAGE_LABELS[k]} {v:.2f}" for k, v in per_image.items())
    print(f"  stages, ms/image (batched, GL synchronized; {wall_ms:.2f} in all): {stages}")

    views = [(v.scene, v.camera) for v in probe]
    floor_s = renderer.gl_floor(views, args.seconds / 2)
    line = (f"  GL floor, every draw of a view, no per-frame work: {1.0 / floor_s:7.1f} "
            f"images/s (one view at a time: x{base * floor_s:.2f} of it)")
    if args.tiles > 1:
        tiled_s = renderer.gl_floor(views, args.seconds / 2, tiles=args.tiles)
        line += (f"; {args.tiles} views tiled in one framebuffer: {1.0 / tiled_s:.1f} "
                 f"images/s per view (x{floor_s / tiled_s:.2f})")
    print(line)
    if any(v.scene.static_objects for v in probe):
        static_s = renderer.gl_floor(views, args.seconds / 2, static=True)
        print(f"  GL floor as rendered (kept render of the site's static objects + the robot "
              f"and people on top): {1.0 / static_s:7.1f} images/s (one view at a time: "
              f"x{base * static_s:.2f} of it)")


def _measure(configs: dict[str, Callable[[int], None]], args: argparse.Namespace,
             pool: Any) -> dict[str, tuple[float, float]]:
    """(images/s, CPU ms per image) per configuration, measured in ``args.rounds`` alternating
    rounds of about ``args.seconds / args.rounds`` each."""
    count = dict.fromkeys(configs, 0)
    wall = dict.fromkeys(configs, 0.0)
    cpu = dict.fromkeys(configs, 0.0)
    slot = args.seconds / max(args.rounds, 1)
    for _ in range(max(args.rounds, 1)):
        for name, run in configs.items():
            t0, c0 = time.perf_counter(), time.process_time()
            p0 = pool.cpu_seconds if pool is not None else 0.0
            n = 0
            while n == 0 or time.perf_counter() - t0 < slot:
                run(args.batch)
                n += args.batch
            wall[name] += time.perf_counter() - t0
            cpu[name] += time.process_time() - c0
            if name.startswith("pool"):
                cpu[name] += pool.cpu_seconds - p0
            count[name] += n
    return {name: (count[name] / wall[name], 1000.0 * cpu[name] / count[name])
            for name in configs}
