"""``smartedge render``: rendered camera images of the simulated site with exact labels.

Writes a dataset a person can open (PNG images, depth, class and instance images, one JSON line
of labels per image; see :mod:`simulation.dataset`) and, with ``--preview K``, the first K
images with the robot's box and keypoints drawn on them (green: visible, red: occluded or
outside), so you can look at what the cameras see. Deterministic: the same ``--seed`` gives the
same images.

Examples::

    smartedge render --out runs/render --count 200                  # views of the site's cameras
    smartedge render --out runs/random --count 5000 --randomize --workers 2
    smartedge render --out runs/preview --count 8 --preview 8 --size 848x480
    smartedge render --out runs/husky --randomize --robot husky.urdf --keypoints husky_kp.yaml
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from protocol.errors import SmartedgeError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="smartedge render", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenario", help="scenario file (default: the paper's lab); its "
                        "site file gives the cameras and the robot model")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--count", type=int, default=100, help="number of images (default 100)")
    parser.add_argument("--randomize", action="store_true",
                        help="domain-randomized scenes instead of the site's own cameras")
    parser.add_argument("--size", help="WxH (default: each camera's own; 848x480 randomized)")
    parser.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    parser.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    parser.add_argument("--robot", metavar="FILE",
                        help="your robot instead of the built-in one: a mesh (OBJ, STL, PLY, "
                        "GLB) or a URDF, in the robot base frame; needs --keypoints")
    parser.add_argument("--keypoints", metavar="FILE",
                        help="the robot's keypoints (YAML: keypoints: [{name, link, xyz_m}])")
    parser.add_argument("--preview", type=int, default=0, metavar="K",
                        help="also write the first K images with labels drawn (preview/)")
    return parser


def parse_size(text: str | None) -> tuple[int | None, int | None]:
    if not text:
        return None, None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SmartedgeError(f"--size {text!r}: expected WxH, e.g. 848x480") from None
    if min(w, h) < 8 or max(w, h) > 8192:
        raise SmartedgeError(f"--size {text!r}: 8..8192 pixels per side")
    return w, h


def load_user_robot(robot: str | None, keypoints: str | None) -> tuple[object, object]:
    """(mesh, robot model) of ``--robot`` + ``--keypoints``, or (None, None) for the built-in."""
    if robot is None and keypoints is None:
        return None, None
    if robot is None or keypoints is None:
        raise SmartedgeError("--robot and --keypoints go together")
    from simulation.robot_files import load_keypoint_file, load_robot_mesh, load_urdf
    from simulation.robot_mesh import robot_model_from_mesh

    if Path(robot).suffix.lower() == ".urdf":
        mesh, links = load_urdf(robot)
    else:
        mesh, links = load_robot_mesh(robot), None
    names, kp = load_keypoint_file(keypoints, links)
    return mesh, robot_model_from_mesh(Path(robot).stem, mesh, names, kp)


def draw_labels(sample: object) -> np.ndarray:
    """The sample's image (RGB) with each robot's box and keypoints drawn."""
    import cv2

    img = np.ascontiguousarray(sample.image_rgb[..., ::-1])  # type: ignore[attr-defined]
    for robot in sample.robots:  # type: ignore[attr-defined]
        if robot.bbox_xyxy is not None:
            x0, y0, x1, y1 = (round(float(v)) for v in robot.bbox_xyxy)
            cv2.rectangle(img, (x0, y0), (x1, y1), (255, 200, 0), 1, cv2.LINE_AA)
        for (u, v), vis, inside in zip(robot.keypoints_px, robot.visible, robot.in_image,
                                       strict=True):
            if not inside:
                continue
            color = (0, 220, 0) if vis else (0, 0, 255)
            cv2.circle(img, (round(float(u)), round(float(v))), 3, color, -1, cv2.LINE_AA)
    return img[..., ::-1]


def main(argv: Sequence[str]) -> int:
    args = build_parser().parse_args(list(argv))
    try:
        import cv2

        from simulation.dataset import SampleGenerator, write_dataset
        from simulation.scenario import PAPER_SCENARIO, load_scenario

        width, height = parse_size(args.size)
        scenario = load_scenario(Path(args.scenario) if args.scenario else PAPER_SCENARIO)
        mesh, model = load_user_robot(args.robot, args.keypoints)
        gen = SampleGenerator(scenario, "randomized" if args.randomize else "site",
                              seed=args.seed, width=width, height=height, robot_mesh=mesh,
                              robot_model=model)
        print(f"smartedge render: {args.count} {gen.mode} images of robot {gen.robot_id!r} "
              f"({scenario.name}), seed {args.seed}, {args.workers} worker(s) → {args.out}")
        labels = write_dataset(gen, args.out, args.count, workers=args.workers, progress=print)
        if args.preview:
            prev = Path(args.out) / "preview"
            prev.mkdir(parents=True, exist_ok=True)
            for i in range(min(args.preview, args.count)):
                cv2.imwrite(str(prev / f"{i:06d}.png"), draw_labels(gen(i))[..., ::-1])
            print(f"preview images: {prev}")
    except SmartedgeError as exc:
        print(f"smartedge render: {exc}", file=sys.stderr)
        return 1
    print(f"labels: {labels}")
    return 0
