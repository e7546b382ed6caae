"""``smartedge train detector|keypoints|segmentation``: train a network on synthetic renders only.

Renders (once, cached in ``OUT/cache``) domain-randomized scenes, views from the site's own
cameras and (``--robot-views``) from the robot's own head camera, trains with a progress line
and checkpoints (run the same command again to resume an
interrupted run, on this or another machine, GPU or CPU), validates on held-out seeds, exports
one ONNX file, checks onnxruntime against torch and writes the model card
(``OUT/<kind>.json`` + ``.md``, with where and how long each leg trained). Needs the
``train`` extra (torch). Uses CUDA when torch sees a GPU (``--device``), with bf16 autocast.

Examples::

    smartedge train detector  --out runs/models --minutes 45
    smartedge train keypoints --out runs/models --minutes 45
    smartedge train segmentation --out runs/seg --minutes 40 --threads 1 --workers 1
    smartedge train keypoints --out runs/tiny --steps 5 --train-views 16 --val-views 8 --tiny
    smartedge train keypoints --out runs/kp --mirror --batch 128 --minutes 4 --workers 16
    smartedge train keypoints --out runs/husky --robot-mesh husky.urdf --keypoints husky_kp.yaml

The shipped detector and keypoint network in ``edge_agent/models/`` were made on a GPU with
``scripts/train_models_gpu.py`` (2026-11-27), the segmentation network with
``scripts/train_shipped_models.sh`` on a CPU.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from protocol.errors import SmartedgeError

#: held-out seeds are the training seeds + this (never equal: checked by TrainConfig)
HELD_OUT_SEED_OFFSET = 1000


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="smartedge train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("kind", choices=("detector", "keypoints", "segmentation"))
    p.add_argument("--out", required=True, help="output folder (model, card, cache, checkpoint)")
    p.add_argument("--scenario", help="scenario file (default: the paper's lab); its site file "
                   "gives the cameras and the robot model")
    p.add_argument("--robot", help="robot id in the site (default: the site's only robot)")
    p.add_argument("--robot-mesh", metavar="FILE", help="your robot's mesh or URDF instead of "
                   "the built-in one (needs --keypoints; see smartedge render)")
    p.add_argument("--keypoints", metavar="FILE", help="your robot's keypoint file")
    p.add_argument("--train-views", type=int, default=3000,
                   help="randomized training views (default 3000)")
    p.add_argument("--site-views", type=int, default=1200,
                   help="training views from the site's cameras (default 1200)")
    p.add_argument("--site-seeds", type=int, default=1,
                   help="spread the site views over this many seeds (seed + 1, + 2, ...), each "
                   "its own textures and obstacle colours of the site (default 1)")
    p.add_argument("--robot-views", type=int, default=0,
                   help="training views from the robot's own head camera at random free poses "
                   "(default 0), spread over the demo site's textures (seed 0) and the site "
                   "views' seeds; a held-out robot-view set (seed + "
                   f"{HELD_OUT_SEED_OFFSET + 2}) is added when > 0")
    p.add_argument("--val-views", type=int, default=200,
                   help="held-out views of each kind (default 200)")
    p.add_argument("--seed", type=int, default=1, help="training seed (default 1); held-out "
                   f"sets use seed + {HELD_OUT_SEED_OFFSET}, + {HELD_OUT_SEED_OFFSET + 1} "
                   f"(and + {HELD_OUT_SEED_OFFSET + 2} for robot views)")
    p.add_argument("--steps", type=int, default=3000, help="optimizer steps (default 3000)")
    p.add_argument("--minutes", type=float, help="time budget instead of --steps (the step count "
                   "is set from the speed measured in the first steps)")
    p.add_argument("--batch", type=int, help="batch size (default 16 detector and "
                   "segmentation, 32 keypoints)")
    p.add_argument("--lr", type=float, default=2e-3, help="AdamW learning rate (default 2e-3)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads (default 2)")
    p.add_argument("--device", default="auto", help="auto (default: CUDA when torch sees a "
                   "GPU, else the CPU), cpu or cuda[:N]; a checkpoint resumes on any of them")
    p.add_argument("--leg-steps", type=int, metavar="N", help="stop after N steps of this "
                   "leg and export what is there; the same command resumes the schedule, here "
                   "or on another machine (e.g. a GPU lent for a few minutes)")
    p.add_argument("--mirror", action="store_true", help="keypoints: also train on mirrored "
                   "crops (left/right keypoints swapped), for flip test-time augmentation")
    p.add_argument("--no-calibration", action="store_true", help="keypoints: skip the "
                   "confidence-to-sigma calibration after training (run it later with "
                   "`smartedge evaluate keypoints --model OUT --calibrate`)")
    p.add_argument("--no-amp", action="store_true", help="train in float32 on a GPU too "
                   "(default: bf16 autocast where the GPU supports it; never on a CPU)")
    p.add_argument("--workers", type=int, default=2, help="render processes (default 2)")
    p.add_argument("--real", metavar="DATASET.json", help="a lab's labelled frames (COCO "
                   "keypoints, smartedge dataset) trained on beside the renders (detector, "
                   "keypoints)")
    p.add_argument("--real-val", metavar="DATASET.json", help="held-out labelled frames, "
                   "validated on as the set 'real' (split by time: smartedge dataset split)")
    p.add_argument("--real-weight", type=int, default=1, metavar="N",
                   help="each labelled frame counts N times among the rendered ones (1)")
    p.add_argument("--init-from", metavar="CKPT|ONNX|shipped", help="fine-tune: start from "
                   "the weights of an earlier run's <kind>.ckpt (same kind and image sizes) or "
                   "of an exported <kind>.onnx with its card (`shipped`: the model smartedge "
                   "ships; keypoint networks are matched by keypoint name, so keypoints can be "
                   "added) with a fresh optimizer and schedule; use a lower --lr")
    p.add_argument("--detector-input", metavar="WxH", type=parse_input_size,
                   help="detector / segmentation: the network's input size (default 424x240, "
                   "half of an 848x480 frame); both divisible by 8. A larger input finds "
                   "smaller (farther) robots at more compute per frame; --init-from a "
                   "checkpoint of another input size works (the networks are fully "
                   "convolutional)")
    p.add_argument("--tiny", action="store_true",
                   help="tiny images (smoke test: checks the whole chain in seconds)")
    return p


def parse_input_size(text: str) -> tuple[int, int]:
    """``WxH`` → (w, h), each a positive multiple of 8 (the networks' coarsest stride)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WxH, e.g. 640x360") from None
    if w <= 0 or h <= 0 or w % 8 or h % 8:
        raise argparse.ArgumentTypeError(f"{text!r}: width and height must be positive "
                                         "multiples of 8")
    return w, h


def tiny_geometry() -> Any:
    """The ``--tiny`` image sizes (smoke tests)."""
    from training.data import Geometry

    return Geometry(det_w=128, det_h=96, crop_w=64, crop_h=96, frame_w=256, frame_h=192)


def set_specs(*, seed: int, train_views: int, site_views: int, site_seeds: int = 1,
              robot_views: int = 0, val_views: int = 200) -> tuple[tuple[Any, ...],
                                                                  tuple[Any, ...]]:
    """The rendered sets of a run, (training, held-out): randomized views of ``seed``, the site
    views spread over ``site_seeds`` texture seeds (``seed`` + 1, + 2, ...), the robot's head
    camera views over the demo site (texture seed 0) and those seeds; held out: the same kinds
    at ``seed`` + :data:`HELD_OUT_SEED_OFFSET` (+ 1, + 2). What another tool renders ahead
    with these sets, ``smartedge train`` finds in its cache."""
    from training.data import SetSpec

    n_site = max(1, site_seeds)
    site_sets = [SetSpec("site", seed + 1 + k, site_views // n_site + (k < site_views % n_site))
                 for k in range(n_site)]
    # the robot's head camera sees the demo site (texture seed 0) too: train on it as well
    robot_seeds = [0, *(s.seed for s in site_sets if s.seed != 0)]
    n_robot = len(robot_seeds)
    robot_sets = [SetSpec("robot", rseed, robot_views // n_robot + (k < robot_views % n_robot))
                  for k, rseed in enumerate(robot_seeds)]
    train_sets = tuple(s for s in (SetSpec("randomized", seed, train_views), *site_sets,
                                   *robot_sets) if s.count > 0)
    val_sets = (SetSpec("randomized", seed + HELD_OUT_SEED_OFFSET, val_views),
                SetSpec("site", seed + HELD_OUT_SEED_OFFSET + 1, val_views))
    if robot_views > 0:
        val_sets += (SetSpec("robot", seed + HELD_OUT_SEED_OFFSET + 2, val_views),)
    return train_sets, val_sets


def main(argv: Sequence[str]) -> int:
    args = build_parser().parse_args(list(argv))
    try:
        try:
            from lab.training_views import SimulationViews
            from training.data import Geometry
            from training.train import TrainConfig, train
        except ModuleNotFoundError as exc:
            raise SmartedgeError(f"missing {exc.name!r}: smartedge train needs the train extra "
                                 "(pip install 'smartedge[train]')") from None
        from lab.render import load_user_robot
        from simulation.scenario import PAPER_SCENARIO, load_scenario

        scenario = load_scenario(Path(args.scenario) if args.scenario else PAPER_SCENARIO)
        mesh, model = load_user_robot(args.robot_mesh, args.keypoints)
        if model is None:
            model = scenario.site.robot_model(args.robot or scenario.robot_id)
        geometry = tiny_geometry() if args.tiny else Geometry()
        if args.detector_input:
            if args.kind == "keypoints":
                raise SmartedgeError("--detector-input is for the detector and the "
                                     "segmentation network (the keypoint network sees crops)")
            geometry = dataclasses.replace(geometry, det_w=args.detector_input[0],
                                           det_h=args.detector_input[1])
        if args.kind == "segmentation":  # whole frames + label images at the output size
            from training.nets import SemanticSegNet

            stride = SemanticSegNet.output_stride
            geometry = dataclasses.replace(geometry, crops_per_robot=0,
                                           seg_w=geometry.det_w // stride,
                                           seg_h=geometry.det_h // stride)
        train_sets, val_sets = set_specs(
            seed=args.seed, train_views=args.train_views, site_views=args.site_views,
            site_seeds=args.site_seeds, robot_views=args.robot_views, val_views=args.val_views)
        batch = args.batch or (32 if args.kind == "keypoints" else 16)
        init_from = args.init_from
        if init_from == "shipped":
            from edge_agent.model_cards import default_model_dir

            init_from = str(default_model_dir() / f"{args.kind}.onnx")
        cfg = TrainConfig(args.kind, train_sets, val_sets, geometry, steps=args.steps,
                          minutes=args.minutes, batch=batch, lr=args.lr, threads=args.threads,
                          workers=args.workers, init_from=init_from,
                          device=args.device, amp=False if args.no_amp else None,
                          leg_steps=args.leg_steps, mirror=args.mirror,
                          real_train=Path(args.real) if args.real else None,
                          real_val=Path(args.real_val) if args.real_val else None,
                          real_weight=args.real_weight)
        mesh_name = (Path(args.robot_mesh).name if args.robot_mesh else
                     "built-in box base" if model.name == "box_base" else
                     "built-in HSR-like mesh")  # simulation.robot_mesh.builtin_robot_mesh
        views = SimulationViews(str(scenario.source_path), model, mesh)
        path = train(cfg, views, Path(args.out), robot_mesh_name=mesh_name,
                     say=lambda line: print(line, flush=True))
        if (args.kind == "keypoints" and not args.tiny and args.robot_mesh is None
                and not args.no_calibration):
            from lab.evaluation.keypoints import calibrate_keypoints

            calibrate_keypoints(Path(args.out), count=args.val_views,
                                scenario_path=scenario.source_path, threads=args.threads,
                                progress=lambda line: print(line, flush=True))
    except SmartedgeError as exc:
        print(f"smartedge train: {exc}", file=sys.stderr)
        return 1
    print(f"model: {path}")
    return 0
