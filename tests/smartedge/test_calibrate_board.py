"""``smartedge calibrate board | intrinsics | extrinsics`` end to end on a tmp dir: a printable
board, intrinsics from rendered images of it, extrinsics of the paper lab from rendered
sightings."""

from __future__ import annotations

import math
import shutil
import zlib

import cv2
import numpy as np
import pytest
import yaml

from calibration.board import board_image, load_board_spec
from core.geometry import rpy_from_rotation
from core.site import load_camera_calibration, load_site
from simulation.board_views import BoardRenderer, BoardTexture, calibration_sweep
from simulation.detections import true_cameras
from simulation.scenario import load_scenario
from smartedge.commands.calibrate import main as calibrate_main
from smartedge.commands.site import main as site_main
from tests.calibration.rendered import (
    EXTRINSICS_BOARD,
    PAPER_LAB,
    paper_lab_board_poses,
    paper_lab_camera,
    render_sightings,
)


def test_board_writes_png_pdf_and_the_spec(tmp_path, capsys) -> None:
    assert calibrate_main(["board", "--out", str(tmp_path / "b.png"), "--squares", "9x7",
                           "--square-m", "0.06", "--marker-m", "0.045", "--dpi", "150"]) == 0
    assert calibrate_main(["board", "--out", str(tmp_path / "b.pdf"), "--squares", "9x7",
                           "--square-m", "0.06", "--marker-m", "0.045"]) == 0
    spec = load_board_spec(tmp_path / "b.yaml")
    assert (spec.squares_x, spec.squares_y, spec.square_length_m) == (9, 7, 0.06)
    png = cv2.imread(str(tmp_path / "b.png"), cv2.IMREAD_GRAYSCALE)
    px_per_square = round(0.06 / 0.0254 * 150)
    assert png.shape == (8 * px_per_square, 10 * px_per_square)  # 9x7 + half a square around
    assert b"pHYs" in (tmp_path / "b.png").read_bytes()[:64]
    pdf = (tmp_path / "b.pdf").read_bytes()
    assert pdf.startswith(b"%PDF-1.4") and pdf.rstrip().endswith(b"%%EOF")
    # the page is the board at 1:1: (9 + 1) squares of 60 mm wide (margins rounded to whole
    # pixels at 300 dpi), in points
    width_pt = float(pdf.split(b"/MediaBox [0 0 ")[1].split()[0])
    assert abs(width_pt - 0.6 / 0.0254 * 72) < 72 / 300
    # a well-formed file: every xref offset points at its object, the image stream holds the
    # board's pixels
    xref_at = int(pdf.rsplit(b"startxref", 1)[1].split()[0])
    rows = pdf[xref_at:].split(b"trailer")[0].splitlines()[3:]
    for number, row in enumerate(rows, start=1):
        assert pdf[int(row.split()[0]):].startswith(f"{number} 0 obj".encode())
    stream = pdf.split(b"/Subtype /Image")[1].split(b"stream\n", 1)[1].split(b"\nendstream")[0]
    pixels = np.frombuffer(zlib.decompress(stream), np.uint8)
    page = board_image(spec, round(0.06 / 0.0254 * 300)).image
    np.testing.assert_array_equal(pixels, page.ravel())
    assert "DICT_5X5_100" in capsys.readouterr().out
    assert calibrate_main(["board", "--out", str(tmp_path / "b.pdf"), "--marker-m", "0.05"]) == 2


def test_intrinsics_from_a_folder_of_rendered_images(tmp_path, capsys) -> None:
    assert calibrate_main(["board", "--out", str(tmp_path / "board.png"), "--squares", "9x7",
                           "--square-m", "0.06", "--marker-m", "0.045"]) == 0
    spec = load_board_spec(tmp_path / "board.yaml")
    cam = paper_lab_camera()
    img = board_image(spec, 60)
    images = tmp_path / "images"
    images.mkdir()
    with BoardRenderer(BoardTexture(img.image, img.extent_board_m), cam.width,
                       cam.height) as br:
        for i, c in enumerate(calibration_sweep(cam, spec.size_m, 16, seed=5)):
            rgb = br.render(c, np.eye(4)).image_rgb
            cv2.imwrite(str(images / f"view{i:02d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(images / "wall.png"), np.full((cam.height, cam.width, 3), 120, np.uint8))
    (images / "broken.png").write_bytes(b"not a png")
    out = tmp_path / "calib"
    assert calibrate_main(["intrinsics", "--camera", "cam1", "--images", str(images),
                           "--board", str(tmp_path / "board.yaml"), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "RMS" in text and "per-view reprojection RMS" in text
    assert "wall.png: no board found" in text and "broken.png: cannot read" in text
    calib = load_camera_calibration(out / "cam1.yaml")
    assert abs(calib.K[0, 0] / cam.K[0, 0] - 1) < 0.005
    assert abs(calib.K[1, 2] / cam.K[1, 2] - 1) < 0.005
    assert site_main(["calib", str(out / "cam1_opencv.yaml")]) == 0
    assert cv2.imread(str(out / "cam1_coverage.png")).shape == (cam.height, cam.width, 3)
    # a folder without enough views: a clear error, exit 1
    for f in sorted(images.glob("view*.png"))[4:]:
        f.unlink()
    assert calibrate_main(["intrinsics", "--camera", "cam1", "--images", str(images),
                           "--board", str(tmp_path / "board.yaml"), "--out", str(out)]) == 1
    assert "usable views of 6 images (need at least 8)" in capsys.readouterr().err


@pytest.fixture(scope="module")
def lab_sightings(tmp_path_factory):
    """(true cameras, folder of per-camera sighting images, board spec file, --fixed-board)."""
    root = tmp_path_factory.mktemp("lab")
    cameras = true_cameras(load_scenario())
    poses = paper_lab_board_poses(cameras, rounds=4)
    for cid, by_stamp in render_sightings(cameras, poses).items():
        (root / "img" / cid).mkdir(parents=True)
        for stamp, rgb in by_stamp.items():
            cv2.imwrite(str(root / "img" / cid / f"{stamp}.png"),
                        cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    EXTRINSICS_BOARD.write(root / "board.yaml")
    T0 = poses["000"]
    rpy = [math.degrees(a) for a in rpy_from_rotation(T0[:3, :3])]
    fixed = " ".join(f"{v:.9f}" for v in [*T0[:3, 3], *rpy])
    return cameras, root / "img", root / "board.yaml", fixed


def test_extrinsics_of_the_paper_lab_from_camera_folders(lab_sightings, tmp_path,
                                                         capsys) -> None:
    cameras, images, board, fixed = lab_sightings
    # intrinsics from `calibrate intrinsics` (camera_info YAML) for three of the cameras
    (tmp_path / "intr").mkdir()
    for cid in ("cam1", "cam2", "cam3"):
        cam = cameras[cid]
        (tmp_path / "intr" / f"{cid}.yaml").write_text(yaml.safe_dump({
            "image_width": cam.width, "image_height": cam.height,
            "camera_matrix": {"rows": 3, "cols": 3, "data": cam.K.ravel().tolist()},
            "distortion_model": "plumb_bob",
            "distortion_coefficients": {"rows": 1, "cols": 5, "data": cam.dist.tolist()}}))
    out = tmp_path / "out" / "site.yaml"
    out.parent.mkdir()
    rc = calibrate_main(["extrinsics", "--board", str(board), "--site", str(PAPER_LAB),
                         "--images", str(images), "--fixed-board", fixed, "--intrinsics",
                         str(tmp_path / "intr"), "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "joint adjustment" in text and "cam4: no cam4.yaml in --intrinsics" in text
    site = load_site(out)
    for cid, cam in cameras.items():
        assert np.linalg.norm(site.cameras[cid].position_world - cam.position_world) < 0.04
        np.testing.assert_allclose(site.cameras[cid].K, cam.K)
    written = yaml.safe_load(out.read_text())["cameras"]
    assert written[0]["calibration_file"] == "../intr/cam1.yaml" and "intrinsics" not in written[0]
    assert "calibration_file" not in written[3] and "intrinsics" in written[3]
    report = yaml.safe_load(out.with_suffix(".report.yaml").read_text())
    assert set(report["cameras"]) == set(cameras)
    assert len(report["cameras"]["cam1"]["covariance_position_m_rotation_rad"]) == 6


def test_extrinsics_names_what_it_could_not_use(lab_sightings, tmp_path, capsys) -> None:
    _, images, board, fixed = lab_sightings
    # cam4 left out, a stranger's folder, and one image of the wrong size
    shutil.copytree(images, tmp_path / "img", ignore=shutil.ignore_patterns("cam4"))
    (tmp_path / "img" / "cam9").mkdir()
    small = cv2.imread(str(tmp_path / "img" / "cam1" / "001.png"))
    cv2.imwrite(str(tmp_path / "img" / "cam1" / "001.png"), cv2.resize(small, (424, 240)))
    out = tmp_path / "site.yaml"
    rc = calibrate_main(["extrinsics", "--board", str(board), "--site", str(PAPER_LAB),
                         "--images", str(tmp_path / "img"), "--fixed-board", fixed, "--out",
                         str(out)])
    text = capsys.readouterr().out
    assert rc == 3, text
    assert "cam9/: not a camera of site 'paper_lab', ignored" in text
    assert "001.png: skipped: image is 424x240, the site's cam1 848x480" in text
    assert "not solved (no sighting ties them to the fixed board): cam4" in text
    site, nominal = load_site(out), load_site(PAPER_LAB)
    np.testing.assert_array_equal(site.cameras["cam4"].T_cam_world,
                                  nominal.cameras["cam4"].T_cam_world)
    bad = ["extrinsics", "--board", str(board), "--site", str(PAPER_LAB), "--images",
           str(images), "--out", str(out)]
    assert calibrate_main([*bad, "--fixed-board", "1 2 3"]) == 1
    assert "--fixed-board: expected 'x y z roll pitch yaw'" in capsys.readouterr().err
    assert calibrate_main([*bad, "--fixed-board", fixed, "--fixed-stamp", "777"]) == 1
    assert "--fixed-stamp '777': no image has that name" in capsys.readouterr().err


def test_intrinsics_from_a_video_file(tmp_path, capsys) -> None:
    from tests.calibration.rendered import INTRINSICS_BOARD, sweep_views

    cam, views = sweep_views()
    video = tmp_path / "wave.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0,
                             (cam.width, cam.height))
    assert writer.isOpened()
    for v in views[:14]:
        for _ in range(2):  # every other frame is read (--every 2)
            writer.write(cv2.cvtColor(v.image_rgb, cv2.COLOR_RGB2BGR))
    writer.release()
    INTRINSICS_BOARD.write(tmp_path / "board.yaml")
    assert calibrate_main(["intrinsics", "--camera", "cam9", "--video", str(video), "--every",
                           "2", "--board", str(tmp_path / "board.yaml"), "--out",
                           str(tmp_path / "out")]) == 0
    assert "frame000000: " in capsys.readouterr().out
    calib = load_camera_calibration(tmp_path / "out" / "cam9.yaml")
    assert abs(calib.K[0, 0] / cam.K[0, 0] - 1) < 0.005
