"""The robot model's optional ``head_camera`` in the site file: parsed into
:class:`core.site.HeadCamera`, every mounting form, errors naming file and key."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

from core.site import load_site, parse_site
from protocol.errors import SiteConfigError

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "deploy" / "site.example.yaml"
PAPER_LAB = REPO / "simulation" / "sites" / "paper_lab.yaml"


def _doc() -> dict:
    return yaml.safe_load(EXAMPLE.read_text())


def _with_head(head: object) -> dict:
    doc = _doc()
    doc["robot_models"]["hsr"]["head_camera"] = head
    return doc


def test_the_paper_lab_hsr_has_a_forward_looking_head_camera_tilted_down() -> None:
    head = load_site(PAPER_LAB).robot_model("hsr").head_camera
    assert head is not None
    assert (head.width, head.height) == (640, 480) and head.K[0, 0] == 525.0
    assert head.dist.shape == (5,)
    z_axis, origin = head.T_base_cam[:3, 2], head.T_base_cam[:3, 3]
    assert origin[2] == pytest.approx(1.0)
    tilt_deg = np.degrees(np.arcsin(-z_axis[2]))
    assert 25.0 <= tilt_deg <= 30.0 and z_axis[0] > 0.85  # forward and down
    assert head.T_base_cam[1, 0] == pytest.approx(-1.0)  # image right = robot's right (-y)
    cam = head.camera_model("hsr_head")
    assert np.allclose(cam.T_world_cam, head.T_base_cam)
    T_world_base = np.eye(4)
    T_world_base[:3, 3] = (3.0, 4.0, 0.0)
    placed = head.camera_model("hsr_head", T_world_base)
    assert np.allclose(placed.position_world, origin + np.array([3.0, 4.0, 0.0]))


def test_a_robot_model_without_head_camera_has_none() -> None:
    doc = _doc()
    doc["robot_models"]["hsr"].pop("head_camera", None)
    assert parse_site(doc).robot_model("hsr").head_camera is None


@pytest.mark.parametrize("mount", [
    {"translation_m": [0.1, 0.0, 1.0], "rpy_deg": [-117.0, 0.0, -90.0]},
    [[0, 0, 1, 0.1], [-1, 0, 0, 0], [0, -1, 0, 1.0], [0, 0, 0, 1]],
    {"position_m": [0.1, 0.0, 1.0], "look_at_m": [3.0, 0.0, 1.0]},
])
def test_mounting_forms(mount: object) -> None:
    head = parse_site(_with_head({"resolution": [320, 240], "K": [[300, 0, 160], [0, 300, 120],
                                                                  [0, 0, 1]],
                                  "T_base_cam": mount})).robot_model("hsr").head_camera
    assert head is not None and head.dist.size == 0
    assert head.T_base_cam[:3, 3] == pytest.approx([0.1, 0.0, 1.0])
    assert head.T_base_cam[:3, 2][0] > 0.85  # the optical axis looks forward


GOOD = {"resolution": [640, 480], "intrinsics": {"fx": 525.0, "fy": 525.0, "cx": 319.5,
                                                 "cy": 239.5},
        "T_base_cam": {"position_m": [0.08, 0.0, 1.0], "look_at_m": [2.0, 0.0, 0.0]}}


@pytest.mark.parametrize(("change", "key"), [
    ({"resolution": [640]}, "robot_models.hsr.head_camera.resolution"),
    ({"resolution": [0, 480]}, "robot_models.hsr.head_camera.resolution"),
    ({"intrinsics": None, "K": [[525, 0, 320], [0, -1, 240], [0, 0, 1]]},
     "robot_models.hsr.head_camera.K"),
    ({"intrinsics": None}, "robot_models.hsr.head_camera.K"),
    ({"distortion": [0.1, 0.2, 0.3]}, "robot_models.hsr.head_camera.distortion"),
    ({"T_base_cam": None}, "robot_models.hsr.head_camera.T_base_cam"),
    ({"T_base_cam": {"translation_m": [0, 0, 1]}}, "robot_models.hsr.head_camera.T_base_cam"),
    ({"T_base_cam": {"translation_m": [0, 0, 1], "rpy_deg": [0, 0]}},
     "robot_models.hsr.head_camera.T_base_cam.rpy_deg"),
    ({"T_base_cam": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
     "robot_models.hsr.head_camera.T_base_cam"),
    ({"fov_deg": 60}, "robot_models.hsr.head_camera.fov_deg"),
])
def test_errors_name_file_and_key(tmp_path: Path, change: dict, key: str) -> None:
    head = copy.deepcopy(GOOD)
    for k, v in change.items():
        if v is None:
            head.pop(k, None)
        else:
            head[k] = v
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(_with_head(head)))
    with pytest.raises(SiteConfigError) as info:
        load_site(path)
    assert str(path) in str(info.value) and key in str(info.value), str(info.value)


def test_head_camera_must_be_a_mapping(tmp_path: Path) -> None:
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(_with_head([640, 480])))
    with pytest.raises(SiteConfigError, match=r"robot_models\.hsr\.head_camera"):
        load_site(path)
