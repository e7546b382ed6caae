"""The OpenGL renderer and the labels computed from its images.

Skipped only when moderngl is not installed; a missing EGL/Mesa makes these tests fail with
:class:`RendererUnavailable`'s message (CI installs the packages).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import cv2
import numpy as np
import pytest

from core.camera import CameraModel
from core.geometry import invert_transform, rotation_from_rpy
from core.site import look_at_T_world_cam
from protocol.errors import SmartedgeError
from simulation.labels import instance_bbox, keypoint_labels
from simulation.mesh import (
    CLASS_ID,
    Mesh,
    Scene,
    SceneObject,
    closed_outward_faces,
    concatenate,
)
from simulation.render_gl import Renderer, RendererUnavailable, RenderOutput, create_context

pytest.importorskip("moderngl")

W, H = 640, 480
DIST = np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
BOX_ID, PLATE_ID, OCCLUDER_ID = 7, 9, 11
BACKGROUND = (0.1, 0.2, 0.3)


def quad_mesh(corners: np.ndarray, color=(0.7, 0.7, 0.7), uv=None, texture=None) -> Mesh:
    return Mesh(np.asarray(corners, float), np.array([[0, 1, 2], [0, 2, 3]]),
                np.asarray(color, np.float32), None, uv, texture)


def box_mesh(size_m, color=(0.8, 0.5, 0.2)) -> Mesh:
    """Flat-shaded axis-aligned box centred on its origin."""
    half = 0.5 * np.asarray(size_m, float)
    verts, faces = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            u = np.zeros(3)
            u[(axis + 1) % 3] = 1.0
            v = np.cross(n, u)
            c, du, dv = n * half, u * half, v * half
            base = len(verts)
            verts += [c - du - dv, c + du - dv, c + du + dv, c - du + dv]
            faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return Mesh(np.array(verts), np.array(faces), np.asarray(color, np.float32))


def box_corners(size_m, T_world_box) -> np.ndarray:
    half = 0.5 * np.asarray(size_m, float)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return signs * half @ T_world_box[:3, :3].T + T_world_box[:3, 3]


def make_camera(position, target, dist=DIST, hfov_deg: float = 75.0) -> CameraModel:
    f = 0.5 * W / math.tan(math.radians(hfov_deg) / 2)
    K = np.array([[f, 0.0, (W - 1) / 2 + 3.0], [0.0, f * 1.01, (H - 1) / 2 - 2.0], [0, 0, 1.0]])
    T_world_cam = look_at_T_world_cam(np.asarray(position, float), np.asarray(target, float))
    return CameraModel("cam", W, H, K, np.asarray(dist, float), invert_transform(T_world_cam))


def pose(x, y, z, roll=0.0, pitch=0.0, yaw=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotation_from_rpy(roll, pitch, yaw)
    T[:3, 3] = (x, y, z)
    return T


def facing_disc(center_world: np.ndarray, camera: CameraModel, radius_m: float) -> Mesh:
    """A 48-gon disc centred on ``center_world``, perpendicular to the optical axis (a disc's
    pixel centroid, unlike a square's, is not stuck to half-pixel steps)."""
    R_world_cam = camera.T_world_cam[:3, :3]
    ang = np.linspace(0.0, 2 * np.pi, 48, endpoint=False)
    rim = radius_m * (np.outer(np.cos(ang), R_world_cam[:, 0]) +
                      np.outer(np.sin(ang), R_world_cam[:, 1]))
    verts = np.vstack([center_world, center_world + rim])
    faces = np.column_stack([np.zeros(48), 1 + np.arange(48), 1 + (np.arange(48) + 1) % 48])
    return Mesh(verts, faces.astype(np.uint32), np.array([0.7, 0.7, 0.7], np.float32))


@pytest.fixture(scope="module")
def renderer() -> Iterator[Renderer]:
    with Renderer(W, H) as r:  # EGL missing: RendererUnavailable fails every test using it
        yield r


@pytest.fixture
def camera() -> CameraModel:
    return make_camera([3.0, -1.2, 1.7], [0.0, 0.0, 0.4])


BOX_SIZE = (0.6, 0.4, 0.5)
BOX_POSE = pose(0.1, 0.05, 0.25, yaw=0.4)


def box_scene(*extra: SceneObject) -> Scene:
    floor = quad_mesh([[-4, -4, 0], [4, -4, 0], [4, 4, 0], [-4, 4, 0]], (0.5, 0.5, 0.5))
    objs = (
        SceneObject(floor, np.eye(4), 0, CLASS_ID["floor"]),
        SceneObject(box_mesh(BOX_SIZE), BOX_POSE, BOX_ID, CLASS_ID["box"]),
        *extra,
    )
    return Scene(objs, background_rgb=BACKGROUND)


# ----------------------------------------------------------------------------------------------
# (a) geometry: rendered positions and depths agree with cv2.projectPoints
# ----------------------------------------------------------------------------------------------


def test_markers_land_where_projectpoints_puts_them(renderer, camera) -> None:
    # Markers spread over the whole image, corners included (strongest distortion there).
    R_world_cam, t_world_cam = camera.T_world_cam[:3, :3], camera.T_world_cam[:3, 3]
    f = camera.K[0, 0]
    pix = [(u, v) for u in (25, 180, 320, 470, 610) for v in (22, 130, 240, 350, 455)]
    ray = cv2.undistortPoints(np.array(pix, float).reshape(-1, 1, 2), camera.K, camera.dist,
                              criteria=(3, 100, 1e-12)).reshape(-1, 2)
    depths = np.linspace(2.0, 5.0, len(pix))
    centers = (np.column_stack([ray, np.ones(len(pix))]) * depths[:, None]) @ R_world_cam.T
    centers += t_world_cam
    objs = tuple(
        SceneObject(facing_disc(c, camera, 9.0 * z / f), np.eye(4), 100 + i, CLASS_ID["box"])
        for i, (c, z) in enumerate(zip(centers, depths, strict=True))
    )
    out = renderer.render(Scene(objs, background_rgb=BACKGROUND), camera)

    labels = keypoint_labels(out, camera, centers)
    expected = cv2.projectPoints(centers, cv2.Rodrigues(camera.T_cam_world[:3, :3])[0],
                                 camera.T_cam_world[:3, 3], camera.K, camera.dist)[0]
    np.testing.assert_allclose(labels.pixels_px, expected.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(labels.pixels_px, camera.project(centers)[0], atol=1e-6)
    np.testing.assert_allclose(labels.depth_m, depths, atol=1e-9)
    assert labels.in_image.all() and labels.visible.all()

    errors = []
    for i, uv in enumerate(labels.pixels_px):
        rows, cols = np.nonzero(out.instance_id == 100 + i)
        assert len(rows) > 100, f"marker {i} at {uv} has {len(rows)} pixels"
        errors.append(np.hypot(cols.mean() - uv[0], rows.mean() - uv[1]))
        iu, iv = np.rint(uv).astype(int)
        assert abs(out.depth_m[iv, iu] - depths[i]) < 0.01
    assert max(errors) < 0.5, f"marker centroids off by {np.round(errors, 3)} px"


def test_box_corner_and_face_labels(renderer, camera) -> None:
    out = renderer.render(box_scene(), camera)
    corners = box_corners(BOX_SIZE, BOX_POSE)
    labels = keypoint_labels(out, camera, corners)
    np.testing.assert_allclose(labels.pixels_px, camera.project(corners)[0], atol=1e-6)
    assert labels.in_image.all()
    # The camera is above and in front of the box: the bottom corner on its far side is hidden.
    cam_in_box = invert_transform(BOX_POSE) @ np.append(camera.position_world, 1.0)
    toward = np.sign(cam_in_box[:3])
    signs = np.sign((corners - BOX_POSE[:3, 3]) @ BOX_POSE[:3, :3])
    hidden = np.all(signs == -toward, axis=1)
    assert hidden.sum() == 1
    np.testing.assert_array_equal(labels.visible, ~hidden)
    for (u, v), vis in zip(np.rint(labels.pixels_px).astype(int), labels.visible, strict=True):
        if vis:  # a visible corner touches the box's silhouette or lies on it
            assert (out.instance_id[v - 1:v + 2, u - 1:u + 2] == BOX_ID).any()

    # Face centres the camera sees: their pixel shows the box at the keypoint's depth (within
    # 1 cm on faces seen within 60 deg of head-on; grazing faces change depth fast per pixel).
    half = 0.5 * np.asarray(BOX_SIZE)
    faces = np.diag(half * toward) @ BOX_POSE[:3, :3].T + BOX_POSE[:3, 3]
    normals = np.diag(toward) @ BOX_POSE[:3, :3].T
    view = faces - camera.position_world
    cos_view = -np.sum(normals * view, axis=1) / np.linalg.norm(view, axis=1)
    face_labels = keypoint_labels(out, camera, faces)
    assert face_labels.visible.all() and (cos_view > 0.5).any()
    for (u, v), z, c in zip(np.rint(face_labels.pixels_px).astype(int), face_labels.depth_m,
                            cos_view, strict=True):
        assert out.instance_id[v, u] == BOX_ID
        around = out.depth_m[v - 1:v + 2, u - 1:u + 2]
        assert around.min() - 0.01 < z < around.max() + 0.01
        if c > 0.5:
            assert abs(out.depth_m[v, u] - z) < 0.01

    box = instance_bbox(out, BOX_ID)
    assert box is not None
    uv = labels.pixels_px
    np.testing.assert_allclose(box, [uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(),
                                     uv[:, 1].max()], atol=1.0)
    assert instance_bbox(out, 12345) is None


# ----------------------------------------------------------------------------------------------
# (b) label images: exact ids inside, depth of a tilted plane, distortion over the whole image
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dist", [DIST, [0.12, 0.01, 0.0005, 0.0005, 0.0], np.zeros(5)],
                         ids=["barrel", "pincushion", "pinhole"])
def test_instance_class_and_depth_images_match_ray_casting(renderer, dist) -> None:
    camera = make_camera([3.0, -1.2, 1.7], [0.0, 0.0, 0.4], dist=dist)
    # A plate 2.5 m in front of the camera, tilted 35 deg and 20 deg about the image axes.
    side = 3.0
    T_cam_plate = pose(0.2, 0.1, 2.5, roll=math.pi + 0.6, pitch=0.35)
    T_plate = camera.T_world_cam @ T_cam_plate
    plate = quad_mesh(np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]]) * side / 2)
    scene = Scene((SceneObject(plate, T_plate, PLATE_ID, CLASS_ID["table"]),),
                  background_rgb=BACKGROUND)
    out = renderer.render(scene, camera)

    # Cast the ray of every pixel (through the inverse lens model) onto the plate's plane.
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = cv2.undistortPoints(np.stack([u, v], -1).reshape(-1, 1, 2), camera.K, camera.dist,
                               criteria=(3, 100, 1e-12)).reshape(H, W, 2)
    rays = np.concatenate([rays, np.ones((H, W, 1))], axis=-1)  # camera frame, z = 1
    n, p0 = T_cam_plate[:3, 2], T_cam_plate[:3, 3]
    z = (n @ p0) / (rays @ n)  # ray parameter = camera z since rays have z = 1
    hit_plate = (rays * z[..., None] - p0) @ T_cam_plate[:3, :2]
    # Pixels clearly inside / outside: by 1.5 px (nearest sampling of the distorted image moves
    # edges by up to half a pixel), by 0.05 px without distortion (GL samples pixel centres
    # exactly), at the hit's depth, measured in the plate's plane (foreshortened by the tilt).
    margin_px = 1.5 if np.any(dist) else 0.05
    cos_tilt = np.abs(rays @ n) / np.linalg.norm(rays, axis=-1)
    margin_m = margin_px * z / camera.K[0, 0] / np.maximum(cos_tilt, 1e-6)
    dist_in = side / 2 - np.abs(hit_plate).max(axis=-1)
    interior = (z > 0) & (dist_in > margin_m)
    exterior = (z <= 0) | (dist_in < -margin_m)
    assert interior.sum() > 0.3 * W * H and exterior.sum() > 0.1 * W * H

    assert (out.instance_id[interior] == PLATE_ID).all()
    assert (out.class_id[interior] == CLASS_ID["table"]).all()
    assert (out.instance_id[exterior] == 0).all() and (out.class_id[exterior] == 0).all()
    assert np.isinf(out.depth_m[exterior]).all()
    bg = np.round(np.array(BACKGROUND) * 255).astype(np.uint8)
    assert (np.abs(out.color_rgb[exterior].astype(int) - bg) <= 1).all()
    depth_tol_m = 0.01 if np.any(dist) else 1e-4
    assert np.abs(out.depth_m[interior] - z[interior]).max() < depth_tol_m
    assert set(np.unique(out.instance_id)) == {0, PLATE_ID}


# ----------------------------------------------------------------------------------------------
# (c) occlusion
# ----------------------------------------------------------------------------------------------


def test_occluder_flips_visibility_of_the_keypoints_it_covers(renderer, camera) -> None:
    corners = box_corners(BOX_SIZE, BOX_POSE)
    before = keypoint_labels(renderer.render(box_scene(), camera), camera, corners)

    # A plate perpendicular to the optical axis, halfway to the box, covering the image's left
    # part up to a vertical edge through the box's middle.
    R_world_cam = camera.T_world_cam[:3, :3]
    centre_cam = camera.world_to_cam(BOX_POSE[:3, 3][None])[0]
    z_occ = 0.5 * centre_cam[2]
    x_edge = centre_cam[0] * z_occ / centre_cam[2]
    occ_cam = np.array([[x_edge - 3, -2, z_occ], [x_edge, -2, z_occ], [x_edge, 2, z_occ],
                        [x_edge - 3, 2, z_occ]])
    occluder = quad_mesh(occ_cam @ R_world_cam.T + camera.T_world_cam[:3, 3])
    after_out = renderer.render(
        box_scene(SceneObject(occluder, np.eye(4), OCCLUDER_ID, CLASS_ID["person"])), camera
    )
    after = keypoint_labels(after_out, camera, corners)

    # The straight ray to a keypoint crosses the occluder's plane at x = x_kp * z_occ / z_kp.
    kp_cam = camera.world_to_cam(corners)
    x_cross = kp_cam[:, 0] * z_occ / kp_cam[:, 2]
    covered = x_cross < x_edge - 0.02
    clear = x_cross > x_edge + 0.02
    assert covered.any() and (covered & before.visible).any() and (clear & before.visible).any()
    assert not after.visible[covered].any()
    np.testing.assert_array_equal(after.visible[clear], before.visible[clear])
    np.testing.assert_array_equal(after.pixels_px, before.pixels_px)
    assert (after_out.instance_id == OCCLUDER_ID).any()


def test_keypoints_slightly_inside_the_surface_stay_visible(renderer, camera) -> None:
    out = renderer.render(box_scene(), camera)
    cam_in_box = invert_transform(BOX_POSE) @ np.append(camera.position_world, 1.0)
    toward = np.sign(cam_in_box[:3])
    half = 0.5 * np.asarray(BOX_SIZE)
    faces = np.diag(half * toward) @ BOX_POSE[:3, :3].T + BOX_POSE[:3, 3]
    view = faces - camera.position_world
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    # Pushed along the line of sight, so the camera depth grows by (nearly) that much. (On the
    # grazing top face a 3x3 neighbour is ~2 cm deeper, so "hidden" needs clearly > 4 cm.)
    for behind_m, visible in ((0.02, True), (0.035, True), (0.1, False), (0.2, False)):
        labels = keypoint_labels(out, camera, faces + behind_m * view)
        assert (labels.visible == visible).all(), behind_m


# ----------------------------------------------------------------------------------------------
# (d) determinism and caching, (e) nothing in view
# ----------------------------------------------------------------------------------------------


def test_same_scene_twice_gives_identical_arrays_and_uploads_once(renderer, camera) -> None:
    scene = box_scene()
    a = renderer.render(scene, camera)
    uploaded = renderer.num_uploaded_meshes
    b = renderer.render(scene, camera)
    c = RenderOutput.empty(W, H)
    assert renderer.render(scene, camera, out=c) is c
    assert renderer.num_uploaded_meshes == uploaded
    for name in ("color_rgb", "depth_m", "instance_id", "class_id"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert np.array_equal(getattr(a, name), getattr(c, name)), name
        assert getattr(a, name) is not getattr(b, name)
    assert a.color_rgb.dtype == np.uint8 and a.color_rgb.shape == (H, W, 3)
    assert a.depth_m.dtype == np.float32 and a.instance_id.dtype == np.int32
    assert a.class_id.dtype == np.int32 and a.depth_m.shape == (H, W)
    assert set(np.unique(a.class_id)) == {CLASS_ID["floor"], CLASS_ID["box"], 0}


def test_back_face_culling_only_where_it_cannot_change_the_image(renderer) -> None:
    box = box_mesh((4.0, 4.0, 3.0))
    inward = Mesh(box.vertices, box.faces[:, ::-1], box.colors)
    panel = quad_mesh([[3, 0, 0], [4, 0, 0], [4, 1, 0], [3, 1, 0]])
    assert closed_outward_faces(box).all()
    assert not closed_outward_faces(inward).any()
    assert not closed_outward_faces(panel).any()
    moved = inward.transformed(pose(10.0, 0.0, 0.0))
    np.testing.assert_array_equal(closed_outward_faces(concatenate([box, panel, moved])),
                                  [True] * 12 + [False] * 14)
    # A camera inside a closed box (a room shell) sees its walls all around: no culling there.
    inside = make_camera([0.3, -0.2, 0.1], [1.0, 0.5, -0.2])
    for mesh in (box, inward):
        out = renderer.render(Scene((SceneObject(mesh, np.eye(4), BOX_ID, 2),)), inside)
        assert (out.instance_id == BOX_ID).all()
        assert np.isfinite(out.depth_m).all() and out.depth_m.max() < 4.0


def test_meshes_of_a_static_scene_are_uploaded_once_and_freed_after_use(renderer,
                                                                         camera) -> None:
    import gc

    gc.collect()
    renderer.render(Scene(()), camera)  # frees what earlier tests left behind
    start = renderer.num_uploaded_meshes
    scene = box_scene()
    renderer.render(scene, camera)
    assert renderer.num_uploaded_meshes == start + 2  # floor and box
    renderer.render(scene, camera)
    assert renderer.num_uploaded_meshes == start + 2
    extra = SceneObject(box_mesh((0.2, 0.2, 0.2)), pose(1.0, 1.0, 0.1), 5, 3)
    renderer.render(Scene((*scene.objects, extra)), camera)
    assert renderer.num_uploaded_meshes == start + 3
    del extra
    gc.collect()
    renderer.render(scene, camera)
    assert renderer.num_uploaded_meshes == start + 2


def test_renderers_of_other_sizes_in_the_same_process_do_not_interfere(renderer,
                                                                        camera) -> None:
    scene = box_scene()
    first = renderer.render(scene, camera)
    K_small = camera.K * 0.5
    K_small[2, 2] = 1.0
    small = CameraModel("small", 320, 200, K_small, camera.dist, camera.T_cam_world)
    with Renderer(320, 200) as other:
        other.render(box_scene(), small)
        again = renderer.render(scene, camera)
        assert (other.render(scene, small).instance_id == BOX_ID).any()
    after = renderer.render(scene, camera)
    for name in ("color_rgb", "depth_m", "instance_id", "class_id"):
        assert np.array_equal(getattr(first, name), getattr(again, name)), name
        assert np.array_equal(getattr(first, name), getattr(after, name)), name


def test_camera_looking_away_sees_nothing(renderer) -> None:
    away = make_camera([3.0, -1.2, 1.7], [6.0, -3.0, 2.5])
    out = renderer.render(box_scene(), away)
    assert not out.instance_id.any() and not out.class_id.any()
    assert np.isinf(out.depth_m).all()
    bg = np.round(np.array(BACKGROUND) * 255).astype(np.uint8)
    assert (out.color_rgb == bg).all()
    labels = keypoint_labels(out, away, box_corners(BOX_SIZE, BOX_POSE))
    assert not labels.in_image.any() and not labels.visible.any()
    assert np.isnan(labels.pixels_px).all()  # behind the camera


# ----------------------------------------------------------------------------------------------
# shading, textures, the undistorted path
# ----------------------------------------------------------------------------------------------


def test_pinhole_path_lambert_shading_and_texture_orientation(renderer) -> None:
    # Camera frame = world frame: the camera looks along world +z.
    f = 500.0
    cam = CameraModel("pinhole", W, H, np.array([[f, 0, 319.5], [0, f, 239.5], [0, 0, 1.0]]),
                      np.zeros(5), np.eye(4))
    tex = np.zeros((64, 64, 3), np.uint8)
    tex[:32, :32] = (255, 0, 0)      # top-left: red
    tex[:32, 32:] = (0, 255, 0)      # top-right: green
    tex[32:, :32] = (0, 0, 255)      # bottom-left: blue
    tex[32:, 32:] = (255, 255, 255)  # bottom-right: white
    # Image-left-bottom corner (x = -1, y = +1 is down) carries uv (0, 0).
    corners = np.array([[-1, 1, 4], [1, 1, 4], [1, -1, 4], [-1, -1, 4]], float)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    textured = quad_mesh(corners, (1.0, 1.0, 1.0), uv, tex)
    scene = Scene((SceneObject(textured, np.eye(4), 1, 1),), light_dir_world=(0.0, 0.0, -1.0),
                  ambient=0.3)
    out = renderer.render(scene, cam)
    q = int(f * 0.5 / 4)  # quadrant centres sit half a side off the image centre
    cu, cv = 320, 240
    assert tuple(out.color_rgb[cv - q, cu - q]) == (255, 0, 0)
    assert tuple(out.color_rgb[cv - q, cu + q]) == (0, 255, 0)
    assert tuple(out.color_rgb[cv + q, cu - q]) == (0, 0, 255)
    assert tuple(out.color_rgb[cv + q, cu + q]) == (255, 255, 255)
    # The quad spans u in 319.5 +- 125 exactly: pixel centres inside are covered.
    row = out.instance_id[cv]
    assert np.flatnonzero(row).min() == 195 and np.flatnonzero(row).max() == 444

    grey = quad_mesh(corners, (0.5, 0.5, 0.5))
    lit = renderer.render(Scene((SceneObject(grey, np.eye(4)),), (0.0, 0.0, -1.0), 0.3), cam)
    side = renderer.render(Scene((SceneObject(grey, np.eye(4)),), (1.0, 0.0, 0.0), 0.3), cam)
    assert abs(int(lit.color_rgb[cv, cu, 0]) - 128) <= 1   # 0.5 * (0.3 + 0.7 * 1)
    assert abs(int(side.color_rgb[cv, cu, 0]) - 38) <= 1   # 0.5 * 0.3 (ambient only)


def test_lens_fold_ghosts_are_not_in_the_image(renderer) -> None:
    # k1 = -0.25 at 100 deg: the polynomial folds back; a point far outside the field of view
    # projects into the image with projectPoints but the lens never images it.
    cam = make_camera([0.0, 0.0, 1.0], [5.0, 0.0, 1.0], dist=[-0.25, 0, 0, 0, 0], hfov_deg=100)
    x_n = 2.2  # beyond the fold: r_d = 2.2 * (1 - 0.25 * 4.84) = -0.46, mirrored into the image
    ghost_cam = np.array([[x_n * 2.0, 0.0, 2.0], [0.3, 0.1, 2.0]])
    ghost_world = ghost_cam @ cam.T_world_cam[:3, :3].T + cam.T_world_cam[:3, 3]
    out = renderer.render(Scene((), background_rgb=BACKGROUND), cam)
    labels = keypoint_labels(out, cam, ghost_world)
    assert cam.in_image(labels.pixels_px)[0]  # projectPoints says: in the image
    np.testing.assert_array_equal(labels.in_image, [False, True])
    assert renderer.lens_map(cam).num_without_preimage > 0


def test_camera_size_must_match_the_renderer(renderer) -> None:
    small = CameraModel("small", 32, 24, np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]]),
                        np.zeros(5), np.eye(4))
    with pytest.raises(ValueError, match="32x24"):
        renderer.render(Scene(()), small)
    with pytest.raises(ValueError, match=r"out\.depth_m"):
        bad = RenderOutput.empty(W, H)
        renderer.render(Scene(()), make_camera([0, 0, 1], [1, 0, 1]),
                        out=RenderOutput(bad.color_rgb, bad.depth_m.astype(np.float64),
                                         bad.instance_id, bad.class_id))


# ----------------------------------------------------------------------------------------------
# (f) errors
# ----------------------------------------------------------------------------------------------


def test_renderer_unavailable_is_a_smartedge_error() -> None:
    assert issubclass(RendererUnavailable, SmartedgeError)


def test_missing_egl_names_the_debian_packages(monkeypatch) -> None:
    monkeypatch.setenv("GLCONTEXT_LINUX_LIBEGL", "libEGL_missing_for_test.so.1")
    with pytest.raises(RendererUnavailable, match="libegl1 libegl-mesa0 libgl1-mesa-dri") as e:
        create_context()
    assert "EGL library" in str(e.value)
