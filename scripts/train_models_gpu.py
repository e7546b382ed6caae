"""Train the shipped detector and keypoint network together on one GPU machine, in a fixed time.

Made for a GPU lent for a few minutes (2026-11-27: one H200 with 16 cores). One render of the
training views serves both networks (the render cache holds the detector's frames and the
keypoint crops of every view), then `smartedge train detector` and `smartedge train keypoints
--mirror` run side by side on the one GPU on that cache. Each writes its checkpoint as it goes,
so a run stopped by its time limit resumes anywhere (`--device cpu` too) with the same command
and the same --out.

    python scripts/train_models_gpu.py [--work DIR] [--render-s 150] [--train-min 4.5]
        [--keypoints-init CKPT] [--site-seeds 3] [--detector-input WxH] [--tiny]

``--detector-input WxH`` trains the detector at another input size: its frames are rendered a
second time at that size (the same views; the render budget covers both), and it trains from
scratch on them. ``--site-seeds N`` spreads the site views over N texture seeds (the site
figure of docs/models.md grows with them).

Then, on any machine: `smartedge evaluate keypoints --model DIR/keypoints --calibrate` (the
confidence -> sigma table of the keypoint card) and copy both into edge_agent/models/.
Needs the train extra and a headless OpenGL (EGL) driver for the renders.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

T0 = time.perf_counter()
SITE_SEEDS = 3  # default: site views spread over the site's textures of seeds 2, 3, 4
SEED = 1  # smartedge train's default --seed: randomized seed 1, held out 1001 and 1002


def _input_size(text: str) -> tuple[int, int]:
    from lab.train import parse_input_size

    return parse_input_size(text)


def say(msg: str) -> None:
    print(f"[{time.perf_counter() - T0:6.1f} s] {msg}", flush=True)


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", default="runs/models_gpu", help="output folder (default "
                   "runs/models_gpu): cache/, detector/, keypoints/, their logs")
    p.add_argument("--render-s", type=float, default=150.0, help="time for the renders, "
                   "held-out sets included (default 150 s)")
    p.add_argument("--max-views", type=int, default=30000, help="at most so many training "
                   "views (default 30000)")
    p.add_argument("--train-min", type=float, default=4.5, help="training time of each "
                   "network (default 4.5 min; both train at once)")
    p.add_argument("--workers", type=int, default=os.cpu_count() or 2,
                   help="render processes (default: every core)")
    p.add_argument("--val-views", type=int, default=200, help="held-out views of each kind")
    p.add_argument("--keypoints-init", metavar="CKPT", help="fine-tune the keypoint network "
                   "from this checkpoint (its --lr is then halved)")
    p.add_argument("--site-seeds", type=int, default=SITE_SEEDS,
                   help=f"texture seeds of the site views (default {SITE_SEEDS})")
    p.add_argument("--detector-input", metavar="WxH", type=_input_size,
                   help="the detector's input size (default 424x240)")
    p.add_argument("--detector-batch", type=int, default=64)
    p.add_argument("--keypoints-batch", type=int, default=128)
    p.add_argument("--tiny", action="store_true", help="tiny images and a few steps: checks "
                   "the whole chain in a minute on a CPU")
    args = p.parse_args(argv)

    from lab.train import set_specs, tiny_geometry
    from lab.training_views import SimulationViews
    from simulation.render_gl import create_context
    from simulation.scenario import PAPER_SCENARIO, load_scenario
    from training.data import Geometry, render_set

    def train_sets(n_rand: int, n_site: int) -> list:
        return list(set_specs(seed=SEED, train_views=n_rand, site_views=n_site,
                              site_seeds=args.site_seeds)[0])

    work = Path(args.work)
    ctx = create_context()
    say(f"GL: {ctx.info.get('GL_RENDERER')} / {ctx.info.get('GL_VERSION')}")
    ctx.release()
    sc = load_scenario(PAPER_SCENARIO)
    views = SimulationViews(str(sc.source_path), sc.site.robot_model(sc.robot_id), None)
    geom = tiny_geometry() if args.tiny else Geometry()
    # the geometries to render: the keypoint network's (and the default detector's), and the
    # detector's own when --detector-input differs (smartedge train then finds both cached)
    geoms = [geom]
    if args.detector_input and args.detector_input != (geom.det_w, geom.det_h):
        geoms.append(dataclasses.replace(geom, det_w=args.detector_input[0],
                                         det_h=args.detector_input[1]))
    cache = work / "cache"
    # held-out sets first, as smartedge train renders them (no jitter, no augmentation)
    val = args.val_views
    for g in geoms:
        eval_geom = dataclasses.replace(g, crop_jitter=False)
        for spec in set_specs(seed=SEED, train_views=0, site_views=0, val_views=val)[1]:
            render_set(views, [spec], eval_geom, cache, workers=args.workers,
                       augment_clean=False, progress=say)
    # a probe round, then as many views as the time allows (2/3 randomized, 1/3 site)
    unit = 48 if args.tiny else 600
    t = time.perf_counter()
    n_rand, n_site = ((2 * unit, unit) if args.tiny else
                      (200 * max(1, 2 * args.workers // 3), unit * max(1, args.workers // 5)))
    for g in geoms:
        render_set(views, train_sets(n_rand, n_site), g, cache, workers=args.workers,
                   progress=say)
    rate = (n_rand + n_site) / (time.perf_counter() - t)  # views of every geometry
    left = args.render_s - (time.perf_counter() - T0)
    total = min(args.max_views, int(n_rand + n_site + max(0.0, left) * rate * 0.9))
    if not args.tiny:
        n_site = max(unit, total // 3 // unit * unit)
        n_rand = max(2 * unit, (total - n_site) // 200 * 200)
    say(f"render rate {rate:.0f} views/s: {n_rand} randomized + {n_site} site views")
    for g in geoms:
        render_set(views, train_sets(n_rand, n_site), g, cache, workers=args.workers,
                   progress=say)
    say("rendering done")
    (work / "counts.json").write_text(json.dumps({"randomized": n_rand, "site": n_site,
                                                  "views_per_s": round(rate, 1)}))
    common = ["--train-views", str(n_rand), "--site-views", str(n_site),
              "--site-seeds", str(args.site_seeds), "--val-views", str(val), "--workers", "1",
              "--threads", str(max(1, args.workers // 4))]
    common += ["--tiny", "--steps", "6"] if args.tiny else ["--minutes", str(args.train_min)]
    runs = {"detector": ["--batch", str(args.detector_batch), "--lr", "2e-3"],
            "keypoints": ["--batch", str(args.keypoints_batch), "--mirror", "--no-calibration",
                          "--lr", "1e-3" if args.keypoints_init else "2e-3"]}
    if args.keypoints_init:
        runs["keypoints"] += ["--init-from", str(Path(args.keypoints_init).resolve())]
    if len(geoms) > 1:
        runs["detector"] += ["--detector-input", f"{geoms[1].det_w}x{geoms[1].det_h}"]
    procs = {}
    for kind, extra in runs.items():
        out = work / kind
        out.mkdir(parents=True, exist_ok=True)
        link = out / "cache"
        if not link.exists():
            link.symlink_to(cache.resolve())
        log = open(work / f"{kind}.log", "a")  # noqa: SIM115 (closed below)
        cmd = [sys.executable, "-m", "smartedge", "train", kind, "--out", str(out), *common,
               *extra]
        procs[kind] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log)
        say(f"started: smartedge train {kind} {' '.join(cmd[5:])}")
    codes = {}
    for kind, (proc, log) in procs.items():
        codes[kind] = proc.wait()
        log.close()
        say(f"{kind} exited {codes[kind]}")
        print((work / f"{kind}.log").read_text()[-2500:], flush=True)
    return 0 if all(c == 0 for c in codes.values()) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
