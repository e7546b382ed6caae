"""Site file: the example loads; each kind of mistake names the key and the file."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from core.site import SiteConfigError, load_camera_calibration, load_site
from tests.conftest import EXAMPLE_SITE


def _doc() -> dict:
    return yaml.safe_load(EXAMPLE_SITE.read_text())


def _write(tmp_path: Path, doc: dict, name: str = "site.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(doc))
    return path


def test_example_site_loads(example_site) -> None:
    assert example_site.name == "lab"
    assert sorted(example_site.cameras) == ["cam_ne", "cam_nw", "cam_se", "cam_sw"]
    model = example_site.robot_model("hsr")
    assert model.keypoints_base_m.shape == (12, 3)
    assert example_site.thresholds.single_camera_max_ddepth_m == pytest.approx(0.15)
    for cam in example_site.cameras.values():
        # every camera is 2.5 m high and looks down at the room centre
        assert cam.position_world[2] == pytest.approx(2.5)
        uv, depth = cam.project(np.array([[10.0, 6.0, 0.0]]))
        assert depth[0] > 0 and cam.in_image(uv)[0]


def test_quaternion_and_look_at_give_the_same_extrinsics(example_site) -> None:
    # cam_nw is written with a quaternion; it equals the look-at it was derived from
    from core.site import look_at_T_world_cam

    T = look_at_T_world_cam(np.array([7.0, 9.0, 2.5]), np.array([10.5, 5.5, 0.0]))
    assert np.allclose(example_site.camera("cam_nw").T_world_cam, T, atol=1e-6)


def test_projection_matches_opencv(example_site) -> None:
    cv2 = pytest.importorskip("cv2")
    cam = example_site.camera("cam_se")
    pts = np.random.default_rng(0).uniform([8, 4, 0], [12, 8, 1], size=(50, 3))
    uv, _ = cam.project(pts)
    rvec, _ = cv2.Rodrigues(cam.T_cam_world[:3, :3])
    uv_cv, _ = cv2.projectPoints(pts, rvec, cam.T_cam_world[:3, 3], cam.K, cam.dist)
    assert np.allclose(uv, uv_cv.reshape(-1, 2), atol=1e-6)


MISTAKES = [
    # (mutation, expected key in the message, expected reason fragment)
    (lambda d: d.pop("site"), "site", "required key is missing"),
    (lambda d: d.update(sitee="x"), "sitee", "unknown key"),
    (lambda d: d["cameras"][1].pop("resolution"), "cameras[1].resolution", "missing"),
    (lambda d: d["cameras"][1].update(K=[[1, 0], [0, 1]]), "cameras[1].K", "3x3"),
    (lambda d: d["cameras"][0].update(K=np.eye(3).tolist()), "cameras[0].K", "not both"),
    (
        lambda d: d["cameras"][0]["intrinsics"].update(fx="wide"),
        "cameras[0].intrinsics.fx",
        "expected a number",
    ),
    (
        lambda d: d["cameras"][2].update(distortion=[0.1, 0.2, 0.3]),
        "cameras[2].distortion",
        "length 3",
    ),
    (lambda d: d["cameras"][0].pop("T_world_cam"), "cameras[0].T_world_cam", "missing"),
    (lambda d: d["cameras"][0].update(T_cam_world=np.eye(4).tolist()), "cameras[0]", "not both"),
    (
        lambda d: d["cameras"][3]["T_world_cam"].update(quaternion_xyzw=[0, 0, 0, 0]),
        "cameras[3].T_world_cam.quaternion_xyzw",
        "not all zero",
    ),
    (
        lambda d: d["cameras"][0].update(T_world_cam=(2 * np.eye(4)).tolist()),
        "cameras[0].T_world_cam",
        "rotation",
    ),
    (lambda d: d["cameras"][1].update(id="cam_sw"), "cameras[1].id", "duplicate"),
    (lambda d: d["cameras"][1].update(id="cam/1"), "cameras[1].id", "invalid id"),
    (
        lambda d: d["robot_models"]["hsr"]["keypoints"][2].update(xyz_m=[0, 1]),
        "robot_models.hsr.keypoints[2].xyz_m",
        "3 numbers",
    ),
    (
        lambda d: d["robot_models"]["hsr"].pop("footprint_radius_m"),
        "robot_models.hsr.footprint_radius_m",
        "missing",
    ),
    (lambda d: d["robots"][0].update(model="pepper"), "robots[0].model", "unknown robot model"),
    (lambda d: d["thresholds"].update(sync_windw_ms=3), "thresholds.sync_windw_ms", "unknown key"),
    (
        lambda d: d["thresholds"].update(multi_frame_count=2.5),
        "thresholds.multi_frame_count",
        "integer",
    ),
    (lambda d: d["thresholds"].update(sync_window_ms=-1), "thresholds.sync_window_ms", "outside"),
    (lambda d: d.update(cameras=[]), "cameras", "non-empty"),
]


@pytest.mark.parametrize(("mutate", "key", "reason"), MISTAKES, ids=[m[1] for m in MISTAKES])
def test_each_mistake_names_key_and_file(tmp_path: Path, mutate, key: str, reason: str) -> None:
    doc = copy.deepcopy(_doc())
    mutate(doc)
    path = _write(tmp_path, doc, "broken_site.yaml")
    with pytest.raises(SiteConfigError) as info:
        load_site(path)
    text = str(info.value)
    assert str(path) in text and info.value.path == str(path)
    assert info.value.key == key, text
    assert reason in text


def test_unreadable_and_invalid_yaml(tmp_path: Path) -> None:
    with pytest.raises(SiteConfigError, match="cannot read"):
        load_site(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("site: [unclosed\n")
    with pytest.raises(SiteConfigError, match="not valid YAML"):
        load_site(bad)


OPENCV_CALIB = """%YAML:1.0
---
image_width: 848
image_height: 480
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 430.5, 0., 421.25, 0., 431.0, 238.75, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.05, 0.06, 0.001, -0.0005, -0.02 ]
"""

ROS_CALIB = """image_width: 640
image_height: 480
camera_name: cam
camera_matrix: {rows: 3, cols: 3, data: [500, 0, 320, 0, 500, 240, 0, 0, 1]}
distortion_model: plumb_bob
distortion_coefficients: {rows: 1, cols: 5, data: [0.1, -0.2, 0, 0, 0]}
"""


def test_opencv_and_ros_calibration_files(tmp_path: Path) -> None:
    cv_file = tmp_path / "cam_cv.yaml"
    cv_file.write_text(OPENCV_CALIB)
    calib = load_camera_calibration(cv_file)
    assert (calib.width, calib.height) == (848, 480)
    assert calib.K[0, 0] == 430.5 and calib.K[1, 2] == 238.75
    assert np.allclose(calib.dist, [-0.05, 0.06, 0.001, -0.0005, -0.02])
    ros_file = tmp_path / "cam_ros.yaml"
    ros_file.write_text(ROS_CALIB)
    assert load_camera_calibration(ros_file).K[0, 2] == 320


def test_site_camera_from_calibration_file(tmp_path: Path) -> None:
    (tmp_path / "cam_cv.yaml").write_text(OPENCV_CALIB)
    doc = _doc()
    cam = doc["cameras"][0]
    for key in ("resolution", "intrinsics", "distortion"):
        cam.pop(key)
    cam["calibration_file"] = "cam_cv.yaml"
    site = load_site(_write(tmp_path, doc))
    assert site.camera("cam_sw").K[0, 0] == 430.5
    cam["K"] = np.eye(3).tolist()
    with pytest.raises(SiteConfigError) as info:
        load_site(_write(tmp_path, doc))
    assert info.value.key == "cameras[0].K" and "calibration_file" in str(info.value)


def test_bad_calibration_file_names_file_and_key(tmp_path: Path) -> None:
    path = tmp_path / "broken_calib.yaml"
    path.write_text(OPENCV_CALIB.replace("rows: 3\n   cols: 3", "rows: 2\n   cols: 3", 1))
    with pytest.raises(SiteConfigError) as info:
        load_camera_calibration(path)
    assert info.value.path == str(path) and info.value.key.startswith("camera_matrix")


def test_unknown_camera_and_robot_lookups_name_the_known_ids(example_site) -> None:
    with pytest.raises(KeyError, match="cam_sw"):
        example_site.camera("cam_x")
    with pytest.raises(KeyError, match="hsr"):
        example_site.robot_model("r2d2")


def test_robot_model_names_its_models_relative_to_the_site_file(tmp_path: Path) -> None:
    """``robot_models.<name>.models`` gives the edge's ONNX files, relative to the site file;
    without it the shipped models are used (None)."""
    doc = _doc()
    name = next(iter(doc["robot_models"]))
    assert load_site(_write(tmp_path, doc)).robot_models[name].detector_onnx is None
    doc["robot_models"][name]["models"] = {"detector": "m/det.onnx",
                                           "keypoints": "/abs/kp.onnx"}
    model = load_site(_write(tmp_path, doc)).robot_models[name]
    assert model.detector_onnx == tmp_path / "m" / "det.onnx"
    assert model.keypoints_onnx == Path("/abs/kp.onnx")


@pytest.mark.parametrize("models, key", [
    ({"detector": "d.onnx"}, "models.keypoints"),
    ({"detector": "d.onnx", "keypoints": 3}, "models.keypoints"),
    ({"detector": "d.onnx", "keypoints": "k.onnx", "seg": "s.onnx"}, "models"),
    ("d.onnx", "models"),
])
def test_bad_robot_models_entry_names_the_key(tmp_path: Path, models: object, key: str) -> None:
    doc = _doc()
    name = next(iter(doc["robot_models"]))
    doc["robot_models"][name]["models"] = models
    with pytest.raises(SiteConfigError) as info:
        load_site(_write(tmp_path, doc, "bad_models.yaml"))
    assert f"robot_models.{name}.{key}" in str(info.value)
    assert "bad_models.yaml" in str(info.value)


@pytest.mark.parametrize(("change", "key", "reason"), [
    (("data: [500, 0, 320, 0, 500, 240, 0, 0, 1]", "data: [500, 0, 320, 0, -500, 240, 0, 0, 1]"),
     "camera_matrix", "not a camera matrix"),
    (("data: [500, 0, 320, 0, 500, 240, 0, 0, 1]", "data: [500, 0, 320, 0, 500, 240, 0, 1, 1]"),
     "camera_matrix", "not a camera matrix"),
    (("distortion_model: plumb_bob", "distortion_model: equidistant"),
     "distortion_model", "fisheye"),
], ids=["negative focal length", "last row not 0 0 1", "fisheye"])
def test_calibration_files_get_the_inline_checks_and_no_fisheye(
        tmp_path: Path, change: tuple[str, str], key: str, reason: str) -> None:
    """A camera matrix from a calibration file is checked like an inline K; a ROS fisheye
    (equidistant) calibration is refused instead of being read as plumb_bob."""
    path = tmp_path / "cam_ros.yaml"
    assert change[0] in ROS_CALIB
    path.write_text(ROS_CALIB.replace(*change))
    with pytest.raises(SiteConfigError, match=reason) as info:
        load_camera_calibration(path)
    assert info.value.path == str(path) and info.value.key == key
    rational = tmp_path / "rational.yaml"
    rational.write_text(ROS_CALIB.replace("plumb_bob", "rational_polynomial").replace(
        "cols: 5, data: [0.1, -0.2, 0, 0, 0]", "cols: 8, data: [0.1, -0.2, 0, 0, 0, 0, 0, 0]"))
    assert load_camera_calibration(rational).dist.size == 8


# --------------------------------------------------------------------------------------------
# the one clock policy
# --------------------------------------------------------------------------------------------


def test_clock_section_and_its_defaults(tmp_path: Path, example_site) -> None:
    from core.site import ClockPolicy

    assert example_site.clock == ClockPolicy() == ClockPolicy(100.0, 1000.0)
    policy = ClockPolicy(max_future_ms=50.0, max_age_ms=500.0)
    assert (policy.max_future_ns, policy.max_age_ns) == (50_000_000, 500_000_000)
    assert not policy.too_far_ahead(1_050_000_000, 1_000_000_000)
    assert policy.too_far_ahead(1_050_000_001, 1_000_000_000)
    assert not policy.too_old(500_000_000, 1_000_000_000)
    assert policy.too_old(499_999_999, 1_000_000_000)
    doc = _doc()
    doc["clock"] = {"max_future_ms": 20, "max_age_ms": 250.5}
    assert load_site(_write(tmp_path, doc)).clock == ClockPolicy(20.0, 250.5)
    doc.pop("clock")
    assert load_site(_write(tmp_path, doc)).clock == ClockPolicy()


@pytest.mark.parametrize(("clock", "key", "reason"), [
    ({"max_futur_ms": 1.0}, "clock.max_futur_ms", "unknown key"),
    ({"max_future_ms": -1.0}, "clock.max_future_ms", "outside"),
    ({"max_age_ms": "1 s"}, "clock.max_age_ms", "expected a number"),
    ({"max_age_ms": 0}, "clock", "max_age_ms must be"),
    ([100.0], "clock", "expected a mapping"),
])
def test_clock_mistakes_name_key_and_file(tmp_path: Path, clock: object, key: str,
                                          reason: str) -> None:
    doc = _doc()
    doc["clock"] = clock
    path = _write(tmp_path, doc)
    with pytest.raises(SiteConfigError) as info:
        load_site(path)
    assert info.value.key == key and reason in str(info.value) and str(path) in str(info.value)


def test_old_thresholds_max_future_ms_is_read_as_the_clock_key_with_a_warning(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    doc = _doc()
    doc.pop("clock", None)
    doc["thresholds"]["max_future_ms"] = 40.0
    path = _write(tmp_path, doc)
    with caplog.at_level("WARNING", logger="core.site"):
        site = load_site(path)
    assert site.clock.max_future_ms == 40.0 and site.clock.max_age_ms == 1000.0
    assert "thresholds.max_future_ms is deprecated" in caplog.text
    assert "clock.max_future_ms" in caplog.text and str(path) in caplog.text
    doc["clock"] = {"max_future_ms": 30.0}  # both: which one is meant?
    with pytest.raises(SiteConfigError) as info:
        load_site(_write(tmp_path, doc))
    assert info.value.key == "thresholds.max_future_ms" and "clock.max_future_ms" in str(info.value)
    doc.pop("clock")
    doc["thresholds"]["max_future_ms"] = -5
    with pytest.raises(SiteConfigError, match=r"thresholds\.max_future_ms"):
        load_site(_write(tmp_path, doc))


@pytest.mark.parametrize(("section", "key", "new"), [
    ("bridge", "clock_tolerance_ms", "clock.max_future_ms"),
    ("map", "max_future_s", "clock.max_future_ms"),
    ("fusion", "max_future_s", "clock.max_age_ms"),
    ("map", "max_age_s", "clock.max_age_ms"),
    ("pose", "prior_max_age_s", "clock.max_age_ms"),
    ("pose", "publish_max_age_s", "clock.max_age_ms"),
    ("pose_output", "max_age_s", "clock.max_age_ms"),
])
def test_per_service_clock_settings_are_gone_and_name_the_clock_key(
        tmp_path: Path, section: str, key: str, new: str) -> None:
    doc = _doc()
    doc.setdefault(section, {})[key] = 0.5
    path = _write(tmp_path, doc)
    with pytest.raises(SiteConfigError) as info:
        load_site(path)
    assert info.value.key == f"{section}.{key}" and new in str(info.value)
