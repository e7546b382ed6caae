"""Robot meshes: primitives, the built-in HSR-like robot against the site's keypoints, loading
mesh files, URDFs and keypoint files (with their errors), and a real robot (pybullet's Husky)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core.site import RobotModel, load_site
from protocol.errors import SmartedgeError
from simulation.mesh import Mesh
from simulation.robot_files import RobotMeshError, load_keypoint_file, load_robot_mesh, load_urdf
from simulation.robot_mesh import (
    box,
    capsule,
    cylinder,
    grid_panel,
    hsr_like_mesh,
    hsr_like_parts,
    lathe,
    robot_model_from_mesh,
    sphere,
    surface_distance,
    text_cells,
)

try:
    import trimesh
except ImportError:  # the sim extra is not installed: loaders cannot be tested
    trimesh = None

needs_trimesh = pytest.mark.skipif(trimesh is None, reason="trimesh not installed")
REPO = Path(__file__).resolve().parents[2]
SITES = [REPO / "simulation" / "sites" / "paper_lab.yaml", REPO / "deploy" / "site.example.yaml"]


def signed_volume(m: Mesh) -> float:
    """Enclosed volume (m^3), positive when the faces wind counter-clockwise seen from outside."""
    t = m.vertices.astype(np.float64)[m.faces.astype(np.int64)]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def face_area_normals(m: Mesh) -> np.ndarray:
    t = m.vertices.astype(np.float64)[m.faces.astype(np.int64)]
    return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]) / 2.0


# ---- primitives


def test_box_is_closed_outward_with_face_colours() -> None:
    b = box((1.0, 2.0, 3.0), (1.0, 0.0, 0.5), (0.5, 0.5, 0.5), face_colors={"+x": (1, 0, 0)})
    assert b.num_triangles == 12
    assert signed_volume(b) == pytest.approx(6.0)
    lo, hi = b.bounds()
    np.testing.assert_allclose(lo, [0.5, -1.0, -1.0])
    np.testing.assert_allclose(hi, [1.5, 1.0, 2.0])
    red = np.all(b.colors == np.float32([1, 0, 0]), axis=1)
    assert red.sum() == 4 and np.all(b.vertices[red, 0] == 1.5)
    np.testing.assert_allclose(np.linalg.norm(b.normals, axis=1), 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="unknown faces"):
        box((1, 1, 1), face_colors={"front": (1, 0, 0)})
    with pytest.raises(ValueError, match="outside"):
        box((1, 1, 1), color=(255, 0, 0))


def test_cylinder_sphere_capsule_volumes() -> None:
    c = cylinder(0.5, 0.0, 2.0, segments=64)
    assert c.num_triangles == 4 * 64
    assert signed_volume(c) == pytest.approx(math.pi * 0.25 * 2.0, rel=2e-3)
    assert cylinder(0.5, 0.0, 1.0, segments=16, caps=False).num_triangles == 32
    s = sphere(1.0, (0.0, 0.0, 2.0), segments=64, rings=32)
    assert signed_volume(s) == pytest.approx(4.0 / 3.0 * math.pi, rel=5e-3)
    assert s.bounds()[0][2] == pytest.approx(1.0, abs=1e-6)
    p0, p1, r = np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, 0.0]), 0.2
    k = capsule(p0, p1, r, segments=64, rings=16)
    expected = math.pi * r * r * math.sqrt(2.0) + 4.0 / 3.0 * math.pi * r**3
    assert signed_volume(k) == pytest.approx(expected, rel=5e-3)
    # every vertex is at distance r from the segment
    t = np.clip((k.vertices - p0) @ (p1 - p0) / 2.0, 0.0, 1.0)
    dist = np.linalg.norm(k.vertices - (p0 + t[:, None] * (p1 - p0)), axis=1)
    np.testing.assert_allclose(dist, r, atol=1e-6)


def test_partial_lathe_is_closed() -> None:
    prof = [(1.0, 0.0), (1.2, 0.0), (1.2, 0.0), (1.2, 0.5), (1.2, 0.5), (1.0, 0.5), (1.0, 0.5),
            (1.0, 0.0)]
    shell = lathe(np.array(prof), (0.1, 0.2, 0.3), segments=256, angle0_rad=-0.5,
                  angle1_rad=0.5)
    expected = 0.5 * (1.2**2 - 1.0**2) * 0.5  # (angle / 2) (ro^2 - ri^2) h
    assert signed_volume(shell) == pytest.approx(expected, rel=1e-3)
    # closed: the area-weighted normals sum to zero
    np.testing.assert_allclose(face_area_normals(shell).sum(axis=0), 0.0, atol=1e-6)


def test_grid_panel_paints_cells() -> None:
    cells = text_cells("HSR", ink=(0, 0, 0), paper=(1, 1, 1))
    assert cells.shape == (7, 13, 3)
    p = grid_panel(cells, 1.3, 0.7)
    assert p.num_triangles == 2 * 7 * 13
    np.testing.assert_allclose(p.normals, np.tile([1.0, 0.0, 0.0], (len(p.vertices), 1)))
    # the top-left cell seen from +x (at -y, +z) is paper, the H's top-left stroke is ink
    centers = p.vertices.reshape(-1, 4, 3).mean(axis=1)
    cols = p.colors.reshape(-1, 4, 3)[:, 0]
    assert centers[0, 1] < 0 and centers[0, 2] > 0 and np.all(cols[0] == 1.0)
    assert np.all(cols[13 + 1] == 0.0)


def test_surface_distance_regions() -> None:
    tri = Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], (0.5, 0.5, 0.5))
    pts = np.array([[0.2, 0.2, 0.3],    # above the face
                    [-1.0, -1.0, 0.0],  # beyond vertex a
                    [2.0, -0.5, 0.0],   # beyond vertex b
                    [0.5, -1.0, 0.0],   # beyond edge ab
                    [1.0, 1.0, 0.0],    # beyond edge bc
                    [-0.5, 0.5, 1.0]])  # beyond edge ca, above
    expected = [0.3, math.sqrt(2.0), math.sqrt(1.25), 1.0, math.sqrt(0.5), math.sqrt(1.25)]
    np.testing.assert_allclose(surface_distance(tri, pts), expected, atol=1e-12)


def test_modules_import_no_trimesh() -> None:
    code = ("import sys, simulation.robot_mesh, simulation.robot_files; "
            "assert 'trimesh' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True)


# ---- the HSR-like robot


@pytest.fixture(scope="module", params=SITES, ids=lambda p: p.name)
def hsr_model(request) -> RobotModel:
    return load_site(request.param).robot_models["hsr"]


def test_hsr_keypoints_lie_on_the_surface(hsr_model: RobotModel) -> None:
    mesh = hsr_like_mesh(hsr_model)
    assert 2_000 <= mesh.num_triangles <= 20_000
    d = surface_distance(mesh, hsr_model.keypoints_base_m)
    far = {n: round(float(x), 4) for n, x in zip(hsr_model.keypoint_names, d, strict=True)
           if x > 0.02}
    assert not far, f"keypoints more than 2 cm from the surface: {far}"
    assert d.max() < 0.002  # in fact all lie on the base's rim, side or bumper


def test_hsr_size_and_validity(hsr_model: RobotModel) -> None:
    mesh = hsr_like_mesh(hsr_model)
    lo, hi = mesh.bounds()
    v = mesh.vertices.astype(np.float64)
    assert np.hypot(v[:, 0], v[:, 1]).max() <= hsr_model.footprint_radius_m + 0.015
    assert hi[2] == pytest.approx(hsr_model.height_m, abs=1e-6)
    assert lo[2] >= 0.0
    assert np.all((mesh.colors >= 0) & (mesh.colors <= 1))
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-5)
    for name, part in hsr_like_parts(hsr_model).items():
        if name not in ("logo", "neck"):  # open surfaces
            assert signed_volume(part) > 0.0, name


def test_hsr_parts_are_asymmetric(hsr_model: RobotModel) -> None:
    parts = hsr_like_parts(hsr_model)

    def centre(name: str) -> np.ndarray:
        lo, hi = parts[name].bounds()
        return (lo + hi) / 2.0

    assert centre("torso_upper")[0] < -0.05  # set back
    assert centre("face")[0] > centre("head")[0]  # face on the front
    assert centre("logo")[0] < centre("torso_upper")[0]  # logo on the back
    assert centre("bumper")[0] > 0.1
    for arm in ("upper_arm", "forearm", "hand", "finger_left", "finger_right"):
        c = centre(arm)
        assert c[0] > 0.0 and c[1] < -0.05, arm  # front right


def test_hsr_appearance_tells_front_back_left_right(hsr_model: RobotModel) -> None:
    """The surface area per colour differs between the front and back halves (x > 0, x < 0)
    and between the left and right halves: the mesh is no mirror image of itself."""
    mesh = hsr_like_mesh(hsr_model)
    t = mesh.vertices.astype(np.float64)[mesh.faces.astype(np.int64)]
    area = np.linalg.norm(face_area_normals(mesh), axis=1)
    centre = t.mean(axis=1)
    keys = [tuple(c) for c in mesh.colors[mesh.faces].mean(axis=1).round(2)]
    palette = sorted(set(keys))
    index = np.array([palette.index(k) for k in keys])

    def area_per_colour(sel: np.ndarray) -> np.ndarray:
        return np.bincount(index[sel], weights=area[sel], minlength=len(palette))

    for axis, at_least in ((0, 0.2), (1, 0.05)):
        pos = area_per_colour(centre[:, axis] > 1e-6)
        neg = area_per_colour(centre[:, axis] < -1e-6)
        assert np.abs(pos - neg).sum() / (pos + neg).sum() > at_least, "xy"[axis]


def test_hsr_scales_with_the_model() -> None:
    kp = np.array([[0.3, 0.0, 0.4], [0.0, 0.3, 0.4], [-0.3, 0.0, 0.05]])
    model = RobotModel("big", ("a", "b", "c"), kp, 0.3, 1.4)
    mesh = hsr_like_mesh(model)
    assert mesh.bounds()[1][2] == pytest.approx(1.4, abs=1e-6)
    assert surface_distance(mesh, kp).max() < 0.02


# ---- mesh files



def _colored_box(extents, color_rgba=(200, 30, 30, 255), at=(0.0, 0.0, 0.0)):
    tm = trimesh.creation.box(extents=extents)
    tm.apply_translation(at)
    tm.visual.vertex_colors = np.tile(color_rgba, (len(tm.vertices), 1))
    return tm


@needs_trimesh
@pytest.mark.parametrize("ext", ["obj", "stl", "ply", "glb"])
def test_load_mesh_formats(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"robot.{ext}"
    _colored_box((0.4, 0.3, 0.8), at=(0.0, 0.0, 0.4)).export(path)
    mesh = load_robot_mesh(path)
    lo, hi = mesh.bounds()
    np.testing.assert_allclose(lo, [-0.2, -0.15, 0.0], atol=1e-6)
    np.testing.assert_allclose(hi, [0.2, 0.15, 0.8], atol=1e-6)
    assert mesh.num_triangles == 12
    if ext in ("ply", "glb"):  # formats with colours
        np.testing.assert_allclose(mesh.colors.mean(axis=0), [200 / 255, 30 / 255, 30 / 255],
                                   atol=0.01)
    elif ext == "stl":
        np.testing.assert_allclose(mesh.colors, 0.6)
    # millimetre files
    mm = tmp_path / f"robot_mm.{ext}"
    _colored_box((400.0, 300.0, 800.0)).export(mm)
    np.testing.assert_allclose(load_robot_mesh(mm, scale=0.001).bounds()[1], [0.2, 0.15, 0.4],
                               atol=1e-6)


@needs_trimesh
def test_load_mesh_flattens_scene_transforms(tmp_path: Path) -> None:
    scene = trimesh.Scene()
    T = np.eye(4)
    T[:3, 3] = [1.0, 0.0, 0.5]
    scene.add_geometry(_colored_box((0.2, 0.2, 0.2)), node_name="a")
    scene.add_geometry(_colored_box((0.2, 0.2, 0.2), (10, 200, 10, 255)), node_name="b",
                       transform=T)
    path = tmp_path / "two.glb"
    scene.export(path)
    mesh = load_robot_mesh(path)
    assert mesh.num_triangles == 24
    np.testing.assert_allclose(mesh.bounds()[0], [-0.1, -0.1, -0.1], atol=1e-6)
    np.testing.assert_allclose(mesh.bounds()[1], [1.1, 0.1, 0.6], atol=1e-6)
    green = mesh.colors[:, 1] > 0.5
    assert np.all(mesh.vertices[green, 0] > 0.85)


@needs_trimesh
def test_load_textured_mesh_keeps_texture(tmp_path: Path) -> None:
    image_mod = pytest.importorskip("PIL.Image")
    tm = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    img = np.zeros((8, 8, 3), np.uint8)
    img[:, :4] = (255, 0, 0)
    uv = (tm.vertices[:, :2] + 0.5).clip(0, 1)
    tm.visual = trimesh.visual.TextureVisuals(uv=uv, image=image_mod.fromarray(img))
    path = tmp_path / "tex.glb"
    tm.export(path)
    mesh = load_robot_mesh(path)
    assert mesh.texture is not None and mesh.uv is not None
    assert mesh.texture.shape == (8, 8, 3) and mesh.uv.shape == (len(mesh.vertices), 2)


@needs_trimesh
def test_load_mesh_errors(tmp_path: Path) -> None:
    with pytest.raises(RobotMeshError, match=r"missing\.obj: mesh file not found"):
        load_robot_mesh(tmp_path / "missing.obj")
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(np.random.default_rng(0).bytes(3000))
    with pytest.raises(RobotMeshError, match=r"garbage\.stl: .*no triangles") as exc:
        load_robot_mesh(garbage)
    assert isinstance(exc.value, SmartedgeError)
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    with pytest.raises(RobotMeshError, match=r"empty\.ply"):
        load_robot_mesh(empty)
    with pytest.raises(RobotMeshError, match="not a regular file"):
        load_robot_mesh(tmp_path)


# ---- URDF + keypoint files


URDF = """<?xml version="1.0"?>
<robot name="toy">
  <material name="Red"><color rgba="0.8 0.1 0.1 1"/></material>
  <link name="base_footprint"/>
  <link name="chassis">
    <visual>
      <origin xyz="0 0 0.1"/>
      <geometry><box size="0.6 0.4 0.2"/></geometry>
      <material name="Red"/>
    </visual>
  </link>
  <link name="wheel_left">
    <visual>
      <origin rpy="1.5707963267948966 0 0"/>
      <geometry><cylinder radius="0.1" length="0.05"/></geometry>
      <material name="tyre"><color rgba="0.1 0.1 0.1 1"/></material>
    </visual>
  </link>
  <link name="mast">
    <visual>
      <geometry>
        <mesh filename="package://toy_description/meshes/mast.stl" scale="0.001 0.001 0.001"/>
      </geometry>
      <material name="Red"/>
    </visual>
    <visual>
      <origin xyz="0 0 0.35"/>
      <geometry><sphere radius="0.05"/></geometry>
    </visual>
  </link>
  <joint name="chassis_joint" type="fixed">
    <parent link="base_footprint"/><child link="chassis"/>
    <origin xyz="0 0 0.05" rpy="$(optenv TOY_RPY 0 0 0)"/>
  </joint>
  <joint name="wheel_left_joint" type="continuous">
    <parent link="chassis"/><child link="wheel_left"/>
    <origin xyz="0 0.25 0.05"/>
    <axis xyz="0 1 0"/>
  </joint>
  <joint name="mast_joint" type="fixed">
    <parent link="chassis"/><child link="mast"/>
    <origin xyz="-0.2 0 0.2" rpy="0 0 1.5707963267948966"/>
  </joint>
</robot>
"""


@pytest.fixture
def toy_urdf(tmp_path: Path) -> Path:
    pkg = tmp_path / "src" / "toy_description"
    (pkg / "meshes").mkdir(parents=True)
    (pkg / "urdf").mkdir()
    mast = trimesh.creation.box(extents=(40.0, 20.0, 300.0))  # millimetres
    mast.apply_translation((0.0, 0.0, 150.0))
    mast.export(pkg / "meshes" / "mast.stl")
    path = pkg / "urdf" / "toy.urdf"
    path.write_text(URDF)
    return path


@needs_trimesh
def test_load_urdf(toy_urdf: Path) -> None:
    mesh, links = load_urdf(toy_urdf)
    assert set(links) == {"base_footprint", "chassis", "wheel_left", "mast"}
    np.testing.assert_allclose(links["base_footprint"], np.eye(4))
    np.testing.assert_allclose(links["wheel_left"][:3, 3], [0.0, 0.25, 0.1])
    np.testing.assert_allclose(links["mast"][:3, 3], [-0.2, 0.0, 0.25])
    np.testing.assert_allclose(links["mast"][:3, 0], [0.0, 1.0, 0.0], atol=1e-12)
    lo, hi = mesh.bounds()
    # chassis 0.05..0.35 (x +-0.3), wheel to y 0.275 and z 0.0, mast (rotated: 20 mm along x)
    # up to 0.55 and its sphere to 0.65
    np.testing.assert_allclose(lo, [-0.3, -0.2, 0.0], atol=1e-4)
    np.testing.assert_allclose(hi, [0.3, 0.275, 0.65], atol=1e-4)
    mast = (mesh.vertices[:, 2] > 0.4) & (mesh.colors[:, 0] > 0.7)  # red, above the chassis
    assert mast.sum() >= 4
    np.testing.assert_allclose(np.ptp(mesh.vertices[mast, :2], axis=0), [0.02, 0.04], atol=1e-5)
    wheel = mesh.vertices[:, 1] > 0.21
    np.testing.assert_allclose(mesh.colors[wheel], 0.1, atol=1e-6)
    # another frame as base
    mesh2, links2 = load_urdf(toy_urdf, base_link="chassis")
    np.testing.assert_allclose(links2["chassis"], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(mesh2.bounds()[0][2], -0.05, atol=1e-4)


@needs_trimesh
def test_urdf_package_dirs(toy_urdf: Path, tmp_path: Path) -> None:
    moved = tmp_path / "elsewhere.urdf"
    moved.write_text(toy_urdf.read_text())
    with pytest.raises(RobotMeshError, match=r"elsewhere\.urdf: link\[mast\]\.visual\[0\]"
                       r"\.geometry\.mesh\.filename: mesh file 'package://toy_description/"
                       r"meshes/mast\.stl' not found"):
        load_urdf(moved)
    for dirs in ([tmp_path / "src"], [tmp_path / "src" / "toy_description"],
                 {"toy_description": tmp_path / "src" / "toy_description"}):
        mesh, _ = load_urdf(moved, package_dirs=dirs)
        assert mesh.bounds()[1][2] == pytest.approx(0.65, abs=1e-4)


@needs_trimesh
@pytest.mark.parametrize(("edit", "message"), [
    (("package://toy_description/meshes/mast.stl", "meshes/nothere.stl"),
     r"mesh file 'meshes/nothere\.stl' not found"),
    (('<child link="mast"/>', '<child link="mastt"/>'),
     r"joint\[mast_joint\]\.child: unknown link 'mastt'"),
    (('<box size="0.6 0.4 0.2"/>', '<box size="0.6 0.4"/>'),
     r"link\[chassis\]\.visual\[0\]\.geometry\.box\.size: expected 3"),
    (('xyz="0 0.25 0.05"', 'xyz="0 zero 0.05"'),
     r"joint\[wheel_left_joint\]\.origin\.xyz: expected 3 numbers"),
    (("</robot>", "<link name='floating'/></robot>"), r"2 trees"),
    (("</robot>", "<joint"), r"not valid XML"),
    (('<sphere radius="0.05"/>', "<capsule radius='0.05' length='1'/>"),
     r"geometry\.capsule: unsupported geometry"),
])
def test_urdf_errors(toy_urdf: Path, edit: tuple[str, str], message: str) -> None:
    text = toy_urdf.read_text()
    assert edit[0] in text
    toy_urdf.write_text(text.replace(edit[0], edit[1]))
    with pytest.raises(RobotMeshError, match=r"toy\.urdf: .*" + message):
        load_urdf(toy_urdf)


@needs_trimesh
def test_urdf_broken_mesh_file(toy_urdf: Path) -> None:
    (toy_urdf.parents[1] / "meshes" / "mast.stl").write_bytes(b"\x00\x01garbage" * 50)
    with pytest.raises(RobotMeshError, match=r"mast\.stl: no triangles"):
        load_urdf(toy_urdf)


def test_urdf_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RobotMeshError, match=r"nope\.urdf: URDF file not found"):
        load_urdf(tmp_path / "nope.urdf")


KEYPOINTS = """\
keypoints:
  - {name: wheel_hub, link: wheel_left, xyz_m: [0.0, 0.025, 0.0]}
  - {name: mast_top, link: mast, xyz_m: [0.01, 0.0, 0.3]}
  - {name: chassis_front, xyz_m: [0.3, 0.0, 0.2]}
"""


@needs_trimesh
def test_load_keypoint_file(toy_urdf: Path, tmp_path: Path) -> None:
    _, links = load_urdf(toy_urdf)
    path = tmp_path / "kp.yaml"
    path.write_text(KEYPOINTS)
    names, xyz = load_keypoint_file(path, links)
    assert names == ("wheel_hub", "mast_top", "chassis_front")
    # the wheel link is not rotated (only its visual is); the mast link is turned 90 deg
    np.testing.assert_allclose(xyz, [[0.0, 0.275, 0.1], [-0.2, 0.01, 0.55], [0.3, 0.0, 0.2]],
                               atol=1e-12)
    mesh, _ = load_urdf(toy_urdf)
    model = robot_model_from_mesh("toy", mesh, names, xyz)
    assert model.num_keypoints == 3
    assert model.height_m == pytest.approx(0.65, abs=1e-4)
    assert model.footprint_radius_m == pytest.approx(math.hypot(0.3, 0.2), abs=1e-4)


TOY_LINKS = {"base_footprint": np.eye(4), "chassis": np.eye(4), "wheel_left": np.eye(4),
             "mast": np.eye(4)}


@pytest.mark.parametrize(("text", "message"), [
    (KEYPOINTS.replace("link: mast,", "link: nope,"),
     r"keypoints\[1\]\.link: unknown link 'nope'; links: \['base_footprint'"),
    ("keypoints: [ {name: a, xyz_m: [0, 0, 0]", r"not valid YAML"),
    ("- just a list", r"expected a mapping"),
    ("points: []", r"points: unknown key"),
    ("keypoints: [{name: a, xyz_m: [0, 0, 0]}]", r"keypoints: expected a list of at least 3"),
    (KEYPOINTS.replace("chassis_front", "mast_top"), r"keypoints\[2\]\.name: duplicate"),
    (KEYPOINTS.replace("[0.3, 0.0, 0.2]", "[0.3, 0.0]"), r"keypoints\[2\]\.xyz_m: expected"),
    (KEYPOINTS.replace("xyz_m: [0.3", "xyz: [0.3"), r"keypoints\[2\]\.xyz: unknown key"),
])
def test_keypoint_file_errors(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "kp.yaml"
    path.write_text(text)
    with pytest.raises(RobotMeshError, match=r"kp\.yaml: .*" + message):
        load_keypoint_file(path, TOY_LINKS)


def test_keypoint_file_without_links(tmp_path: Path) -> None:
    path = tmp_path / "kp.yaml"
    path.write_text(KEYPOINTS)
    with pytest.raises(RobotMeshError, match="no link transforms given"):
        load_keypoint_file(path)
    with pytest.raises(RobotMeshError, match=r"absent\.yaml: keypoint file not found"):
        load_keypoint_file(tmp_path / "absent.yaml")


# ---- a real robot description: Clearpath Husky from pybullet_data (BSD)


# the example of docs/simulation.md
HUSKY_KEYPOINTS = """\
keypoints:
  - {name: front_bumper, link: front_bumper_link, xyz_m: [0.013, 0.0, 0.0]}
  - {name: rear_bumper, link: rear_bumper_link, xyz_m: [0.013, 0.0, 0.0]}
  - {name: front_left_tyre, link: front_left_wheel_link, xyz_m: [0.0, 0.0, 0.1777]}
  - {name: rail_left, link: user_rail_link, xyz_m: [0.0, 0.2, 0.0]}
  - {name: rail_centre, xyz_m: [0.272, 0.0, 0.39]}       # no link: the base frame
"""


@needs_trimesh
def test_husky_from_pybullet_data(tmp_path: Path) -> None:
    pybullet_data = pytest.importorskip("pybullet_data")
    urdf = Path(pybullet_data.getDataPath()) / "husky" / "husky.urdf"
    mesh, links = load_urdf(urdf)
    lo, hi = mesh.bounds()
    size = hi - lo
    assert 0.9 < size[0] < 1.1 and 0.6 < size[1] < 0.8 and 0.3 < size[2] < 0.5  # ~1 x 0.7 m
    assert lo[2] == pytest.approx(0.0, abs=0.01)  # base_footprint: wheels on the floor
    assert 20_000 < mesh.num_triangles < 60_000
    for side, y in (("left", 1.0), ("right", -1.0)):
        for end, x in (("front", 1.0), ("rear", -1.0)):
            T = links[f"{end}_{side}_wheel_link"]
            assert np.sign(T[0, 3]) == x and np.sign(T[1, 3]) == y
            assert T[2, 3] == pytest.approx(0.1778, abs=1e-3)  # wheel radius above the floor
    kp = tmp_path / "husky_keypoints.yaml"
    kp.write_text(HUSKY_KEYPOINTS)
    names, xyz = load_keypoint_file(kp, links)
    assert names == ("front_bumper", "rear_bumper", "front_left_tyre", "rail_left",
                     "rail_centre")
    np.testing.assert_allclose(xyz[0], [0.48 + 0.013, 0.0, 0.14493 + 0.091], atol=1e-6)
    np.testing.assert_allclose(xyz[1], [-0.48 - 0.013, 0.0, 0.14493 + 0.091], atol=1e-5)
    assert surface_distance(mesh, xyz).max() < 0.005  # they were picked on its surface
    model = robot_model_from_mesh("husky", mesh, names, xyz)
    assert 0.5 < model.footprint_radius_m < 0.7
