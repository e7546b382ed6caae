"""The one writer of calibrated camera poses into a site file
(calibration.site_file): poses replaced, everything else kept, relative paths
rebased onto the written file's folder, bad input named."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from calibration.site_file import (
    COMMENTS_NOTE,
    pose_node,
    write_site_with_cameras,
)
from core.geometry import pose_error, rotation_from_rotvec
from core.site import SiteConfigError, load_site
from tests.calibration.rendered import PAPER_LAB


def _moved(T: np.ndarray) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = rotation_from_rotvec(np.array([0.01, -0.02, 0.03])) @ out[:3, :3]
    out[:3, 3] += [0.05, -0.02, 0.01]
    return out


def test_only_the_named_poses_change_and_the_file_reads_back(tmp_path) -> None:
    nominal = load_site(PAPER_LAB)
    new = {"cam2": _moved(nominal.cameras["cam2"].T_world_cam)}
    out = tmp_path / "sub" / "site.yaml"
    site = write_site_with_cameras(PAPER_LAB, out, new, "line one\nline two")
    text = out.read_text().splitlines()
    assert text[:3] == ["# line one", "# line two", f"# {COMMENTS_NOTE}"]
    again = load_site(out)
    for cid, cam in nominal.cameras.items():
        want = new.get(cid, cam.T_world_cam)
        assert max(pose_error(again.cameras[cid].T_world_cam, want)) < 1e-5
        assert max(pose_error(site.cameras[cid].T_world_cam, want)) < 1e-5
        np.testing.assert_array_equal(again.cameras[cid].K, cam.K)
        assert again.cameras[cid].clock_offset_ns == cam.clock_offset_ns
    doc = yaml.safe_load(out.read_text())
    cam2 = next(c for c in doc["cameras"] if c["id"] == "cam2")
    assert cam2["T_world_cam"] == pose_node(new["cam2"]) and "T_cam_world" not in cam2
    assert doc["robot_models"] == yaml.safe_load(PAPER_LAB.read_text())["robot_models"]


def test_relative_paths_are_rebased_onto_the_written_files_folder(tmp_path) -> None:
    nominal = load_site(PAPER_LAB)
    cam = nominal.cameras["cam1"]
    src = tmp_path / "lab"
    src.mkdir()
    calib = {"image_width": cam.width, "image_height": cam.height,
             "camera_matrix": {"rows": 3, "cols": 3, "data": cam.K.ravel().tolist()},
             "distortion_model": "plumb_bob",
             "distortion_coefficients": {"rows": 1, "cols": 5, "data": cam.dist.tolist()}}
    (src / "calib").mkdir()
    (src / "calib" / "cam1.yaml").write_text(yaml.safe_dump(calib))
    doc = yaml.safe_load(PAPER_LAB.read_text())
    for c in doc["cameras"]:
        if c["id"] == "cam1":
            for key in ("K", "intrinsics", "distortion", "resolution"):
                c.pop(key, None)
            c["calibration_file"] = "calib/cam1.yaml"
    (src / "site.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    out = tmp_path / "elsewhere" / "deeper" / "site.yaml"
    site = write_site_with_cameras(src / "site.yaml", out, {"cam1": cam.T_world_cam})
    written = yaml.safe_load(out.read_text())
    assert written["cameras"][0]["calibration_file"] == "../../lab/calib/cam1.yaml"
    np.testing.assert_allclose(site.cameras["cam1"].K, cam.K)
    # a new intrinsics file replaces the inline intrinsics, relative to the written file
    (tmp_path / "elsewhere" / "cam2.yaml").write_text(yaml.safe_dump(calib))
    site = write_site_with_cameras(src / "site.yaml", out, {},
                                   calibration_files={"cam2": tmp_path / "elsewhere" /
                                                      "cam2.yaml"})
    cam2 = next(c for c in yaml.safe_load(out.read_text())["cameras"] if c["id"] == "cam2")
    assert cam2["calibration_file"] == "../cam2.yaml" and "K" not in cam2


def test_unknown_camera_and_bad_files_are_named(tmp_path) -> None:
    with pytest.raises(SiteConfigError, match=r"cameras.*no camera with id \['cam9'\]"):
        write_site_with_cameras(PAPER_LAB, tmp_path / "s.yaml", {"cam9": np.eye(4)})
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: lab\ncameras: {cam1: 1}\n")
    with pytest.raises(SiteConfigError, match=r"bad\.yaml.*cameras"):
        write_site_with_cameras(bad, tmp_path / "s.yaml", {"cam1": np.eye(4)})
    assert not (tmp_path / "s.yaml").exists()
