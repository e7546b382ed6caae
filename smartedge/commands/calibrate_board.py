"""``smartedge calibrate board | intrinsics | extrinsics``: print a ChArUco board, calibrate one
camera's intrinsics from views of it, and every camera's pose from sightings of it, solved
jointly (docs/calibration.md)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Final

import numpy as np
import yaml

from protocol.errors import SmartedgeError

#: image file suffixes read from folders
IMAGE_SUFFIXES: Final = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def _squares(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected COLSxROWS such as 7x5, got {text!r}") from None
    return x, y


# ---------------------------------------------------------------------------------- board


def board_main(argv: Sequence[str]) -> int:
    from calibration.board import (
        CharucoBoardSpec,
        board_image_for_dpi,
        write_board_pdf,
        write_board_png,
    )

    p = argparse.ArgumentParser(
        prog="smartedge calibrate board",
        description="Draw a ChArUco board as a PNG (with its print resolution) or a PDF (1:1 "
                    "page) and write its spec beside it (same name, .yaml). Print at actual "
                    "size, then measure a square and correct the spec if the printer scaled.")
    p.add_argument("--out", required=True, help="board.png or board.pdf")
    p.add_argument("--squares", type=_squares, default=(7, 5), help="COLSxROWS (default 7x5)")
    p.add_argument("--square-m", type=float, default=0.04, help="square side, m (0.04)")
    p.add_argument("--marker-m", type=float, default=0.03, help="marker side, m (0.03)")
    p.add_argument("--dictionary", default="DICT_5X5_100", help="ArUco dictionary (DICT_5X5_100)")
    p.add_argument("--dpi", type=float, default=300.0, help="print resolution (300)")
    p.add_argument("--margin-squares", type=float, default=0.5,
                   help="white margin around the squares, in squares (0.5)")
    args = p.parse_args(list(argv))
    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".pdf"):
        print(f"error: --out must end in .png or .pdf, got {out.name}", file=sys.stderr)
        return 2
    try:
        spec = CharucoBoardSpec(args.squares[0], args.squares[1], args.square_m, args.marker_m,
                                args.dictionary)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    board = board_image_for_dpi(spec, args.dpi, args.margin_squares)
    out.parent.mkdir(parents=True, exist_ok=True)
    (write_board_pdf if out.suffix.lower() == ".pdf" else write_board_png)(board, out)
    spec_path = spec.write(out.with_suffix(".yaml"))
    h, w = board.image.shape
    print(f"board: {spec.describe()}")
    print(f"wrote {out} ({w}x{h} px, {board.dpi:.0f} dpi, "
          f"{w / board.px_per_m * 1e3:.0f} x {h / board.px_per_m * 1e3:.0f} mm with the margin)")
    print(f"wrote {spec_path} (pass it as --board)")
    return 0


# ---------------------------------------------------------------------------------- sources


def _folder_images(folder: Path) -> list[Path]:
    return sorted(f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in
                  IMAGE_SUFFIXES)


def _read_images(files: Sequence[Path], skipped: dict[str, str]
                 ) -> Iterator[tuple[str, np.ndarray]]:
    import cv2

    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if img is None:
            skipped[f.name] = "cannot read the image file"
            continue
        yield f.name, img


def _video_frames(source: str | int, every: int, max_frames: int
                  ) -> Iterator[tuple[str, np.ndarray]]:
    import cv2

    cap = cv2.VideoCapture(source)
    if not cap.isOpened():
        raise SmartedgeError(f"cannot open video source {source!r}")
    try:
        index = taken = 0
        while taken < max_frames:
            ok, frame = cap.read()
            if not ok:
                break
            if index % every == 0:
                taken += 1
                yield f"frame{index:06d}", frame
            index += 1
    finally:
        cap.release()


# ---------------------------------------------------------------------------------- intrinsics


def intrinsics_main(argv: Sequence[str]) -> int:
    import cv2

    from calibration.board import (
        MIN_SHARPNESS,
        BoardDetector,
        draw_detection,
        load_board_spec,
    )
    from calibration.intrinsics import (
        MIN_VIEWS,
        calibrate_intrinsics,
        coverage_image,
        write_camera_info_yaml,
        write_opencv_yaml,
    )

    p = argparse.ArgumentParser(
        prog="smartedge calibrate intrinsics",
        description="One camera's intrinsics from views of a ChArUco board: detects the board, "
                    "keeps views that add coverage, calibrates (OpenCV, radial-tangential), "
                    "writes <camera>.yaml (ROS camera_info), <camera>_opencv.yaml (FileStorage)"
                    " and <camera>_coverage.png into --out.")
    p.add_argument("--camera", required=True, help="camera id (names the files)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", type=Path, help="folder of board images")
    src.add_argument("--video", help="video file")
    src.add_argument("--device", help="camera device (index such as 0, or a URI)")
    p.add_argument("--board", required=True, type=Path, help="board spec YAML")
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--every", type=int, default=10, help="video/device: every Nth frame (10)")
    p.add_argument("--max-frames", type=int, default=200, help="video/device: frames read (200)")
    p.add_argument("--min-views", type=int, default=MIN_VIEWS)
    p.add_argument("--min-sharpness", type=float, default=MIN_SHARPNESS,
                   help=f"variance of the Laplacian a view needs ({MIN_SHARPNESS:g})")
    p.add_argument("--rational", action="store_true",
                   help="8-coefficient rational model (wide-angle lenses)")
    p.add_argument("--overlays", action="store_true",
                   help="also write every image with its detected corners into --out/overlays")
    args = p.parse_args(list(argv))
    t0 = time.perf_counter()
    try:
        spec = load_board_spec(args.board)
        detector = BoardDetector(spec, min_sharpness=args.min_sharpness)
        skipped: dict[str, str] = {}
        if args.images is not None:
            if not args.images.is_dir():
                raise SmartedgeError(f"--images {args.images}: not a folder")
            frames: Iterator[tuple[str, np.ndarray]] = _read_images(
                _folder_images(args.images), skipped)
        else:
            source: str | int = args.video if args.video is not None else (
                int(args.device) if args.device.isdigit() else args.device)
            frames = _video_frames(source, max(1, args.every), max(1, args.max_frames))
        args.out.mkdir(parents=True, exist_ok=True)
        detections = []
        for name, img in frames:
            det = detector.detect(img)
            detections.append((name, det))
            if args.overlays:
                (args.out / "overlays").mkdir(exist_ok=True)
                cv2.imwrite(str(args.out / "overlays" / f"{Path(name).stem}.png"),
                            draw_detection(img, det))
            print(f"  {name}: " + (f"{det.num_corners} corners" if det.usable
                                   else f"skipped: {det.reason}"), flush=True)
        result = calibrate_intrinsics(detections, spec, args.camera, rational_model=args.rational,
                                      min_views=args.min_views, skipped=skipped)
    except SmartedgeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    info = write_camera_info_yaml(result, args.out / f"{args.camera}.yaml")
    ocv = write_opencv_yaml(result, args.out / f"{args.camera}_opencv.yaml")
    cov = args.out / f"{args.camera}_coverage.png"
    cv2.imwrite(str(cov), coverage_image(result))
    print(result.summary())
    print("per-view reprojection RMS (px):")
    for v in sorted(result.views, key=lambda v: -v.rms_px):
        print(f"  {v.name}: {v.rms_px:.3f} ({v.num_corners} corners)")
    if result.skipped:
        print(f"skipped {len(result.skipped)} images:")
        for name, why in sorted(result.skipped.items()):
            print(f"  {name}: {why}")
    uncovered = int((~result.coverage).sum())
    if uncovered:
        print(f"{uncovered} of {result.coverage.size} image cells have no corner (red in {cov}); "
              "add views with the board there")
    print(f"wrote {info} (ROS camera_info), {ocv} (OpenCV), {cov} "
          f"in {time.perf_counter() - t0:.1f} s; check with: smartedge site calib {info}")
    return 0


# ---------------------------------------------------------------------------------- extrinsics


def extrinsics_main(argv: Sequence[str]) -> int:
    from calibration.board import BoardDetector, load_board_spec
    from calibration.board_extrinsics import (
        BoardSighting,
        load_board_poses,
        pose_from_xyz_rpy,
        report_yaml,
        site_header,
        solve_board_extrinsics,
    )
    from calibration.site_file import write_site_with_cameras
    from core.site import load_camera_calibration, load_site

    p = argparse.ArgumentParser(
        prog="smartedge calibrate extrinsics",
        description="Every camera's T_world_cam from board sightings, solved jointly (bundle "
                    "adjustment over every corner). --images holds one folder per camera id; "
                    "files with the same name (stamp or index) saw the same board pose.")
    p.add_argument("--board", required=True, type=Path, help="board spec YAML")
    p.add_argument("--site", required=True, type=Path, help="site file (intrinsics, camera ids)")
    p.add_argument("--images", required=True, type=Path, help="folder of per-camera folders")
    anchor = p.add_mutually_exclusive_group(required=True)
    anchor.add_argument("--fixed-board", metavar="'x y z roll pitch yaw'",
                        help="the board's pose in the map frame at --fixed-stamp (m, deg)")
    anchor.add_argument("--board-poses", type=Path,
                        help="YAML board_poses: {stamp: {translation_m, rpy_deg}} (e.g. the "
                             "robot's localization with the board on the robot)")
    p.add_argument("--fixed-stamp", help="stamp of --fixed-board (default: the first stamp)")
    p.add_argument("--intrinsics", type=Path,
                   help="folder of `calibrate intrinsics` results: <camera>.yaml replaces that "
                        "camera's intrinsics, in the solve and as calibration_file: in --out")
    p.add_argument("--out", required=True, type=Path, help="site file to write")
    p.add_argument("--report", type=Path, help="report YAML (default: OUT.report.yaml)")
    args = p.parse_args(list(argv))
    t0 = time.perf_counter()
    try:
        site = load_site(args.site)
        spec = load_board_spec(args.board)
        cameras = dict(site.cameras)
        calibration_files: dict[str, Path] = {}
        if args.intrinsics is not None:
            for cid, cam in site.cameras.items():
                path = args.intrinsics / f"{cid}.yaml"
                if not path.is_file():
                    print(f"  {cid}: no {path.name} in --intrinsics, the site's intrinsics kept")
                    continue
                calib = load_camera_calibration(path)
                cameras[cid] = dataclasses.replace(cam, width=calib.width, height=calib.height,
                                                   K=calib.K, dist=calib.dist)
                calibration_files[cid] = path
        if not args.images.is_dir():
            raise SmartedgeError(f"--images {args.images}: not a folder")
        detector = BoardDetector(spec)
        sightings: list[BoardSighting] = []
        stamps: set[str] = set()
        for folder in sorted(f for f in args.images.iterdir() if f.is_dir()):
            if folder.name not in site.cameras:
                print(f"  {folder.name}/: not a camera of site {site.name!r}, ignored")
                continue
            cam_skipped: dict[str, str] = {}
            used = 0
            cam = cameras[folder.name]
            for name, img in _read_images(_folder_images(folder), cam_skipped):
                stamp = Path(name).stem
                stamps.add(stamp)
                det = detector.detect(img)
                if det.image_size != (cam.width, cam.height):
                    cam_skipped[name] = (f"image is {det.image_size[0]}x{det.image_size[1]}, "
                                         f"the site's {folder.name} {cam.width}x{cam.height}")
                elif det.usable:
                    sightings.append(BoardSighting.from_detection(folder.name, stamp, det))
                    used += 1
                else:
                    cam_skipped[name] = str(det.reason)
            print(f"  {folder.name}: {used} sightings")
            for name, why in sorted(cam_skipped.items()):
                print(f"    {name}: skipped: {why}")
        if not stamps:
            raise SmartedgeError(f"--images {args.images}: no camera folder with images "
                                 f"(folders are named by camera id: {sorted(site.cameras)})")
        if args.board_poses is not None:
            fixed = load_board_poses(args.board_poses)
        else:
            stamp = args.fixed_stamp or min(stamps)
            if stamp not in stamps:
                raise SmartedgeError(f"--fixed-stamp {stamp!r}: no image has that name")
            try:
                fixed = {stamp: pose_from_xyz_rpy(args.fixed_board)}
            except ValueError as exc:
                raise SmartedgeError(f"--fixed-board: {exc}") from None
        result = solve_board_extrinsics(cameras, sightings, spec, fixed)
        unsolved = sorted(set(site.cameras) - set(result.cameras))
        # the written file is loaded back and checked by the writer
        write_site_with_cameras(
            args.site, args.out, {c: r.T_world_cam for c, r in result.cameras.items()},
            site_header(result, args.site, unsolved), calibration_files)
        out = args.out
    except SmartedgeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    report = args.report or args.out.with_suffix(".report.yaml")
    report.write_text(yaml.safe_dump(report_yaml(result), sort_keys=False), encoding="utf-8")
    print(result.report())
    missing = sorted(set(site.cameras) - set(result.cameras))
    if missing:
        print(f"not solved (no sighting ties them to the fixed board): {', '.join(missing)}; "
              "their poses are unchanged")
    print(f"wrote {out} and {report} in {time.perf_counter() - t0:.1f} s")
    return 0 if not missing else 3
