"""Headless OpenGL rendering of a :class:`~simulation.mesh.Scene` through a calibrated camera.

The only module of the project that imports moderngl (imported lazily, so importing this module
never needs it). One draw pass with three render targets (RGBA8 colour; R32UI
``instance_id << 8 | class_id``, exact integers; R32F 1 / z, perspective-exact) yields, for
every pixel of the image *as the real, distorted lens sees it*:

- ``color_rgb`` (H, W, 3) uint8: albedo (× texture) × (ambient + (1 - ambient) · max(0, n·l)),
  lit per vertex and two-sided (a face seen from behind is lit with its normal flipped);
- ``depth_m`` (H, W) float32: z of the surface point in the camera optical frame, metres,
  ``np.inf`` where nothing was drawn;
- ``instance_id`` / ``class_id`` (H, W) int32: exact (never interpolated), 0 where nothing (or
  an object with id 0) was drawn. :class:`~simulation.mesh.SceneObject` keeps instance ids
  below 2**24 and class ids below 256, which the packing relies on.

Camera model: the OpenGL projection is built from the intrinsics in the OpenCV convention (x
right, y down, z forward; integer pixel coordinates are pixel *centres*), so a vertex lands
exactly where ``cv2.projectPoints`` puts it and a pixel is covered when its centre lies inside
the projected triangle. The GL window's first row is the image's top row, so targets are read
back without flipping. With lens distortion the scene is rendered undistorted through an internal
pinhole camera whose field of view covers the undistorted footprint of every image pixel, then
warped to the distorted image with a per-camera map and ``cv2.remap`` (colour: bilinear; depth
and ids: nearest, so label edges sit within half a pixel of the exact ones; exact near the
image centre). Pixels of a lens model that have no undistorted preimage (a polynomial that folds
back, e.g. a strong negative k1 at a wide field of view, see
:func:`simulation.labels.lens_fold_radius`) stay empty.

Closed, outward-oriented parts of meshes are drawn with back faces culled while the camera is
outside their bounding box (same image, half the rasterization work on llvmpipe). The static
part of a scene (``Scene.static_objects``: the site's floor, walls and furniture) is drawn once
per camera and kept; later frames copy it back, draw the other objects on top and read back and
remap only the image regions those can reach (same image; see :class:`Renderer`).

Texture coordinates follow OpenGL/OBJ: (0, 0) is the *bottom*-left corner of the texture
image, v grows upwards, and textures repeat outside [0, 1].
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import time
import weakref
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any, Final

import cv2
import numpy as np

from protocol.camera import CameraModel
from protocol.errors import SmartedgeError
from protocol.geometry import distort_normalized, lens_fold_radius
from simulation.mesh import Mesh, Scene

if TYPE_CHECKING:
    import moderngl

log = logging.getLogger(__name__)

#: Debian packages that provide headless EGL on Mesa (software llvmpipe or a GPU driver).
EGL_DEBIAN_PACKAGES: Final = "libegl1 libegl-mesa0 libgl1-mesa-dri libgl1"
#: Default near / far clipping distances along the optical axis, metres.
DEFAULT_NEAR_M: Final = 0.05
DEFAULT_FAR_M: Final = 200.0
#: Lens maps kept per renderer (randomized training cameras would otherwise pile up).
LENS_MAP_CACHE_SIZE: Final = 16
#: Memory for kept renders of scenes' static objects per renderer, bytes (16 bytes per pixel of
#: the internal render: ~7 MB per 848x480 camera, so the paper lab's four cameras fit many times)
STATIC_CACHE_BYTES: Final = 128 * 2**20
#: Spacing of the exact undistortion samples a lens map is interpolated from, pixels. The map
#: is smooth, so bilinear interpolation over 8 px is off by ~0.01 px for k1 = -0.2.
_LENS_GRID_STEP_PX: Final = 8
#: Margin of the internal render around the undistorted footprint, pixels (bilinear needs 1).
_LENS_PAD_PX: Final = 2
#: A pixel whose undistortion does not re-distort to within this many pixels has no preimage.
_LENS_MAX_RESIDUAL_PX: Final = 1e-3
#: Image regions where the lens squeezes more undistorted pixels than this into one image pixel
#: (only next to the fold of a lens polynomial that folds back) are left empty.
_LENS_MAX_STRETCH: Final = 3.0
#: Largest internal render relative to the image, per axis (caps degenerate lens models).
_MAX_INTERNAL_SCALE: Final = 3.0
_UNDISTORT_CRITERIA: Final = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)

# Lambert shading is evaluated per vertex (Gouraud): on llvmpipe small triangles cost whole
# 4x4 pixel blocks of fragment shading, so a lean fragment shader is most of the speed. Meshes
# without a texture use a variant without the uv varying and the texture fetch.
_VERTEX_SHADER: Final = """
#version 330
uniform mat4 u_proj;
uniform mat4 u_cam_obj;
uniform mat3 u_normal_cam_obj;
uniform vec3 u_light_cam;
uniform float u_ambient;
in vec3 in_position;
in vec3 in_normal;
in vec3 in_color;
out vec3 v_color;
#ifdef TEXTURED
in vec2 in_uv;
out vec2 v_uv;
#endif
void main() {
    vec4 p = u_cam_obj * vec4(in_position, 1.0);
    vec3 n = u_normal_cam_obj * in_normal;
    float len_n = length(n);
    n = len_n > 1e-12 ? n / len_n : -normalize(p.xyz);
    if (dot(n, p.xyz) > 0.0) n = -n;  // two-sided: light the side facing the camera
    v_color = in_color * (u_ambient + (1.0 - u_ambient) * max(dot(n, u_light_cam), 0.0));
#ifdef TEXTURED
    v_uv = in_uv;
#endif
    gl_Position = u_proj * p;
}
"""

_FRAGMENT_SHADER: Final = """
#version 330
uniform int u_instance_id;
uniform int u_class_id;
in vec3 v_color;
#ifdef TEXTURED
uniform sampler2D u_texture;
in vec2 v_uv;
#endif
layout(location = 0) out vec4 out_color;
layout(location = 1) out uint out_ids;
layout(location = 2) out float out_inv_depth;
void main() {
#ifdef TEXTURED
    out_color = vec4(v_color * texture(u_texture, v_uv).rgb, 1.0);
#else
    out_color = vec4(v_color, 1.0);
#endif
    out_ids = (uint(u_instance_id) << 8) | uint(u_class_id);  // exact, 0 (cleared) = nothing
    out_inv_depth = gl_FragCoord.w;  // 1 / z_cam, perspective-exact; 0 (cleared) = nothing
}
"""


def _shader_variant(source: str, textured: bool) -> str:
    return source.replace("#version 330\n", "#version 330\n#define TEXTURED\n") if textured \
        else source


class RendererUnavailable(SmartedgeError):
    """Headless OpenGL cannot be used here (moderngl, EGL or the Mesa drivers are missing)."""


@dataclasses.dataclass(frozen=True, eq=False)
class RenderOutput:
    """One rendered image as the distorted lens sees it (pixel centres at integer coordinates).

    ``color_rgb`` (H, W, 3) uint8; ``depth_m`` (H, W) float32 camera-frame z in metres,
    ``np.inf`` where nothing was drawn; ``instance_id`` and ``class_id`` (H, W) int32, 0 where
    nothing was drawn.
    """

    color_rgb: np.ndarray
    depth_m: np.ndarray
    instance_id: np.ndarray
    class_id: np.ndarray

    @classmethod
    def empty(cls, width: int, height: int) -> RenderOutput:
        """Freshly allocated arrays for a ``width`` x ``height`` image (for ``render(out=)``)."""
        return cls(
            np.zeros((height, width, 3), np.uint8),
            np.full((height, width), np.inf, np.float32),
            np.zeros((height, width), np.int32),
            np.zeros((height, width), np.int32),
        )

    @property
    def width(self) -> int:
        return int(self.color_rgb.shape[1])

    @property
    def height(self) -> int:
        return int(self.color_rgb.shape[0])


def create_context() -> moderngl.Context:
    """A standalone headless OpenGL (>= 3.3 core) context on EGL.

    Raises :class:`RendererUnavailable` naming what is missing (moderngl, libEGL, libGL, an EGL
    device or the Mesa drivers) and the Debian packages that provide it.
    """
    try:
        import moderngl
    except ImportError as exc:
        raise RendererUnavailable(
            f"moderngl is not installed ({exc}); install it with pip install 'moderngl>=5.8'"
        ) from exc
    try:
        ctx = moderngl.create_context(standalone=True, backend="egl")  # type: ignore[arg-type]
    except Exception as exc:  # glcontext raises bare Exception for every failure
        raise RendererUnavailable(_diagnose_egl_failure(str(exc))) from exc
    if ctx.version_code < 330:
        version = ctx.info.get("GL_VERSION", ctx.version_code)
        ctx.release()
        raise RendererUnavailable(
            f"headless OpenGL {version} is too old (3.3 core needed); install Mesa: "
            f"apt-get install {EGL_DEBIAN_PACKAGES}"
        )
    return ctx


def _diagnose_egl_failure(message: str) -> str:
    low = message.lower()
    if "egl" in low and "not loaded" in low:
        missing = "the EGL library (libEGL.so.1)"
    elif "not loaded" in low:
        missing = "the OpenGL library (libGL.so.1)"
    elif "0 devices" in low or "eglinitialize" in low or "display" in low:
        missing = "an EGL device: Mesa's EGL vendor library or its DRI drivers (llvmpipe)"
    else:
        missing = "a working EGL/OpenGL driver"
    return (
        f"headless OpenGL (EGL) is unavailable: {missing} is missing ({message}); install the "
        f"Debian packages: apt-get install {EGL_DEBIAN_PACKAGES}"
    )


# --------------------------------------------------------------------------------------------
# camera model → OpenGL
# --------------------------------------------------------------------------------------------


def projection_matrix(K: np.ndarray, width: int, height: int, near_m: float = DEFAULT_NEAR_M,
                      far_m: float = DEFAULT_FAR_M) -> np.ndarray:
    """(4, 4) OpenGL projection of the OpenCV-convention intrinsics ``K`` (3, 3, skew allowed).

    Takes camera optical-frame points (z forward) to clip space such that the GL window
    coordinate of a point is (u + 0.5, v + 0.5) for its OpenCV pixel (u, v): GL pixel centres
    sit at half-integers, OpenCV's at integers. Window row 0 is image row 0 (the top), so the
    image is read back unflipped (and triangle winding on screen is mirrored: faces
    counter-clockwise seen from outside are clockwise on screen). Depth maps [near_m, far_m] to
    [-1, 1].
    """
    fx, s, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    P = np.zeros((4, 4))
    P[0, :3] = (2.0 * fx / width, 2.0 * s / width, 2.0 * (cx + 0.5) / width - 1.0)
    P[1, 1:3] = (2.0 * fy / height, 2.0 * (cy + 0.5) / height - 1.0)
    P[2, 2:] = ((far_m + near_m) / (far_m - near_m), -2.0 * far_m * near_m / (far_m - near_m))
    P[3, 2] = 1.0
    return P


@dataclasses.dataclass(frozen=True, eq=False)
class LensMap:
    """How the internal undistorted render becomes the distorted image of one camera.

    ``K_render`` (3, 3) and ``render_size`` (width, height): the internal pinhole camera.
    ``color_maps``: OpenCV fixed-point maps (CV_16SC2 + CV_16UC1) for a bilinear ``cv2.remap``
    of the colour; ``nearest_map`` (H, W, 2) int16 (CV_16SC2): the internal pixel nearest to
    each image pixel's preimage, for ``cv2.remap`` with ``INTER_NEAREST`` of the label images.
    Pixels without preimage map outside the render (they get the border value: nothing).
    ``identity``: no distortion, the render is the image.
    """

    K_render: np.ndarray
    render_size: tuple[int, int]
    identity: bool
    color_maps: tuple[np.ndarray, np.ndarray] | None = None
    nearest_map: np.ndarray | None = None
    num_without_preimage: int = 0
    #: the camera's intrinsics (3, 3), distortion coefficients and the lens's fold radius
    #: (:func:`protocol.geometry.lens_fold_radius`): to map internal pixels to image pixels
    K: np.ndarray | None = None
    dist: np.ndarray | None = None
    fold_radius: float = math.inf


def lens_map(camera: CameraModel) -> LensMap:
    """The :class:`LensMap` of ``camera`` (numpy + OpenCV; 10-30 ms at 848x480).

    The exact undistortion (iterative, checked by re-distorting with
    :func:`protocol.geometry.distort_normalized`) is computed on a grid every
    ``_LENS_GRID_STEP_PX`` pixels and interpolated bilinearly in float. The internal focal
    length is the camera's, enlarged where the lens magnifies (pincushion) so the render is never
    coarser than the image.
    """
    W, H = camera.width, camera.height
    K, dist = camera.K, camera.dist
    if not np.any(dist) or dist.size == 0:
        return LensMap(K.copy(), (W, H), identity=True, K=K.copy(), dist=dist.copy())

    step = _LENS_GRID_STEP_PX
    # Coarse samples at the centres of step x step cells, plus one ring outside, so cv2.resize
    # (cell-centred, float weights) interpolates every image pixel between exact samples.
    gx = (np.arange(-1, math.ceil(W / step) + 1) * step + (step - 1) / 2.0)
    gy = (np.arange(-1, math.ceil(H / step) + 1) * step + (step - 1) / 2.0)
    gu, gv = np.meshgrid(gx, gy)
    xy_d = np.stack([gu, gv, np.ones_like(gu)], axis=-1) @ np.linalg.inv(K).T
    xy_d = xy_d[..., :2] / xy_d[..., 2:]
    xy_u = cv2.undistortPoints(
        xy_d.reshape(-1, 1, 2), np.eye(3), dist, criteria=_UNDISTORT_CRITERIA
    ).reshape(xy_d.shape)
    f_px = float(max(K[0, 0], K[1, 1]))
    with np.errstate(invalid="ignore", over="ignore"):
        residual_px = np.linalg.norm(distort_normalized(xy_u, dist) - xy_d, axis=-1) * f_px
    bad = ~(residual_px < _LENS_MAX_RESIDUAL_PX)  # NaN counts as bad
    bad |= np.hypot(xy_u[..., 0], xy_u[..., 1]) >= lens_fold_radius(dist)  # other branches
    # Next to a fold the lens squeezes many undistorted pixels into one image pixel: bilinear
    # interpolation is poor there and the footprint explodes, so such cells count as empty.
    with np.errstate(invalid="ignore"):
        sx = np.abs(np.diff(xy_u[..., 0], axis=1)) * (K[0, 0] / step) > _LENS_MAX_STRETCH
        sy = np.abs(np.diff(xy_u[..., 1], axis=0)) * (K[1, 1] / step) > _LENS_MAX_STRETCH
    bad[:, 1:] |= sx
    bad[:, :-1] |= sx
    bad[1:] |= sy
    bad[:-1] |= sy
    xy_u[bad] = 0.0

    def upsample(a: np.ndarray) -> np.ndarray:
        big = cv2.resize(a.astype(np.float32), (len(gx) * step, len(gy) * step),
                         interpolation=cv2.INTER_LINEAR)
        return big[step:step + H, step:step + W]

    x_u, y_u = upsample(xy_u[..., 0]), upsample(xy_u[..., 1])
    if bad.any():
        invalid = upsample(bad.astype(np.float32)) > 0.0  # any bad sample in the cell: empty
        num_invalid = int(np.count_nonzero(invalid))
    else:
        invalid = np.zeros(x_u.shape, bool)
        num_invalid = 0
    if num_invalid == invalid.size:
        raise ValueError(f"camera {camera.camera_id}: no pixel of its lens model is invertible")

    # Internal focal: as fine as the image everywhere (pincushion lenses magnify the edges):
    # the smallest step between neighbouring exact samples, in internal pixels per image pixel.
    fx, fy = float(K[0, 0]), float(K[1, 1])
    step_x = np.abs(np.diff(xy_u[..., 0], axis=1))[~(bad[:, 1:] | bad[:, :-1])] * fx / step
    step_y = np.abs(np.diff(xy_u[..., 1], axis=0))[~(bad[1:] | bad[:-1])] * fy / step
    min_step = min(float(step_x.min(initial=1.0)), float(step_y.min(initial=1.0)))
    scale = min(max(1.0, 1.0 / max(min_step, 1e-6)), 2.0)
    if num_invalid:
        xs, ys = x_u[~invalid], y_u[~invalid]
    else:
        xs, ys = x_u, y_u
    x_lo, x_hi, y_lo, y_hi = float(xs.min()), float(xs.max()), float(ys.min()), float(ys.max())
    pad = _LENS_PAD_PX
    max_w, max_h = min(16384, _MAX_INTERNAL_SCALE * W), min(16384, _MAX_INTERNAL_SCALE * H)
    scale = min(scale, (max_w - 2 * pad - 2) / (fx * (x_hi - x_lo)),
                (max_h - 2 * pad - 2) / (fy * (y_hi - y_lo)))
    fxr, fyr = scale * fx, scale * fy
    # The internal principal point sits a whole number of pixels from the image's: around the
    # image centre (where the lens barely warps) nearest sampling then picks exactly the pixel
    # under each image pixel instead of one shifted by a constant fraction.
    cxr = K[0, 2] + math.ceil(pad - fxr * x_lo - K[0, 2])
    cyr = K[1, 2] + math.ceil(pad - fyr * y_lo - K[1, 2])
    rw = math.ceil(cxr + fxr * x_hi + pad) + 1
    rh = math.ceil(cyr + fyr * y_hi + pad) + 1
    K_render = np.array([[fxr, 0.0, cxr], [0.0, fyr, cyr], [0.0, 0.0, 1.0]])

    map_x = x_u * np.float32(fxr)
    map_x += np.float32(cxr)
    map_y = y_u * np.float32(fyr)
    map_y += np.float32(cyr)
    if num_invalid:
        map_x[invalid] = -100.0  # outside: cv2.remap fills the border (background) colour
        map_y[invalid] = -100.0
    color_maps = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
    nearest_map, _ = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2, nninterpolation=True)
    return LensMap(K_render, (rw, rh), identity=False, color_maps=color_maps,
                   nearest_map=nearest_map, num_without_preimage=num_invalid, K=K.copy(),
                   dist=dist.copy(), fold_radius=lens_fold_radius(dist))


# --------------------------------------------------------------------------------------------
# GPU resources
# --------------------------------------------------------------------------------------------


def closed_outward_faces(mesh: Mesh, weld_m: float = 1e-6) -> np.ndarray:
    """(M,) bool: the faces of ``mesh`` that belong to a closed surface whose faces are all
    counter-clockwise seen from outside.

    Vertices closer than ``weld_m`` are merged first (flat-shaded meshes repeat them per face)
    and faces that collapse are left out (False). Per connected part, every directed edge must
    occur exactly once and its reverse exactly once, and the enclosed signed volume must be
    positive. Seen from outside its bounding box, such a part shows only front faces, so its
    back faces may be culled without changing the image; open parts (single-sided panels) and
    inside-out parts are drawn two-sided.
    """
    return closed_outward_faces_many([mesh], weld_m)[0]


def closed_outward_faces_many(meshes: Sequence[Mesh], weld_m: float = 1e-6
                              ) -> list[np.ndarray]:
    """:func:`closed_outward_faces` of each mesh, computed in one pass over all of them (the
    small meshes of a randomized scene cost numpy call overhead, not arithmetic). Vertices of
    different meshes are never welded together, so each result is the single-mesh one."""
    results = [np.zeros(len(m.faces), bool) for m in meshes]
    todo = [k for k, m in enumerate(meshes) if len(m.faces) >= 4]
    if not todo:
        return results
    verts = [meshes[k].vertices.astype(np.float64) for k in todo]
    counts = np.array([len(v) for v in verts])
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]])
    face_counts = np.array([len(meshes[k].faces) for k in todo])
    v = np.concatenate(verts)
    faces = np.concatenate([meshes[k].faces.astype(np.int64) + o
                            for k, o in zip(todo, offsets, strict=True)])
    face_mesh = np.repeat(np.arange(len(todo)), face_counts)
    # weld within each mesh only: the mesh index is part of the key
    keys = np.empty((len(v), 4), np.int64)
    keys[:, :3] = np.round(v / weld_m)
    keys[:, 3] = np.repeat(np.arange(len(todo)), counts)
    _, welded = np.unique(keys, axis=0, return_inverse=True)
    f = welded.reshape(-1)[faces]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    # a mesh with fewer than 4 faces left cannot enclose anything (and was all-open before)
    kept_per_mesh = np.bincount(face_mesh[keep], minlength=len(todo))
    keep &= kept_per_mesh[face_mesh] >= 4
    keep = np.flatnonzero(keep)
    if len(keep) == 0:
        return results
    f = f[keep]
    n = int(f.max()) + 1
    a, b = f.ravel(), f[:, [1, 2, 0]].ravel()  # directed edges, three per face in face order

    # Connected parts: hook each root onto the smallest root it shares an edge with, then
    # compress paths fully; a few rounds suffice.
    parent = np.arange(n)
    while True:
        ra, rb = parent[a], parent[b]
        differ = ra != rb
        if not differ.any():
            break
        np.minimum.at(parent, np.maximum(ra, rb)[differ], np.minimum(ra, rb)[differ])
        while True:
            jumped = parent[parent]
            if np.array_equal(jumped, parent):
                break
            parent = jumped
    _, part = np.unique(parent[f[:, 0]], return_inverse=True)

    # An edge is paired when it occurs once and its reverse occurs exactly once.
    directed = a * n + b
    order = np.argsort(directed)
    ds = directed[order]
    same_next = ds[1:] == ds[:-1]
    repeated = np.zeros(len(ds), bool)
    repeated[1:] |= same_next
    repeated[:-1] |= same_next
    pos = np.minimum(np.searchsorted(ds, b * n + a), len(ds) - 1)
    paired = (ds[pos] == b * n + a) & ~repeated[pos]
    paired[order] &= ~repeated
    open_faces = ~paired.reshape(-1, 3).all(axis=1)
    num_parts = int(part.max()) + 1
    part_open = np.bincount(part, weights=open_faces, minlength=num_parts) > 0
    fv = faces[keep]
    volume6 = np.einsum("ij,ij->i", v[fv[:, 0]], np.cross(v[fv[:, 1]], v[fv[:, 2]]))
    part_volume = np.bincount(part, weights=volume6, minlength=num_parts)
    closed = np.zeros(len(faces), bool)
    closed[keep] = (~part_open & (part_volume > 0.0))[part]
    for k, piece in zip(todo, np.split(closed, np.cumsum(face_counts)[:-1]), strict=True):
        results[k] = piece
    return results


class _Program:
    """One shader variant and its uniforms."""

    def __init__(self, ctx: moderngl.Context, textured: bool) -> None:
        self.textured = textured
        self.program = ctx.program(vertex_shader=_shader_variant(_VERTEX_SHADER, textured),
                                   fragment_shader=_shader_variant(_FRAGMENT_SHADER, textured))
        if textured:
            self.program["u_texture"].value = 0  # type: ignore[union-attr]
        u: Any = self.program  # moderngl types members as a union of uniform kinds
        self.proj, self.cam_obj, self.normal = u["u_proj"], u["u_cam_obj"], u["u_normal_cam_obj"]
        self.light, self.ambient = u["u_light_cam"], u["u_ambient"]
        self.instance_id, self.class_id = u["u_instance_id"], u["u_class_id"]
        self.attributes = ("in_position", "in_normal", "in_color") + (("in_uv",) if textured
                                                                      else ())

    def release(self) -> None:
        self.program.release()


@dataclasses.dataclass
class _GpuMesh:
    ref: weakref.ref[Mesh]
    program: _Program
    vbo: Any
    ibo: Any
    vao: Any
    texture: Any | None
    #: the first ``num_closed`` faces belong to closed, outward-oriented parts: their back faces
    #: may be culled while the camera is outside their bounding box (``box_lo``, ``box_hi``)
    num_closed: int
    num_faces: int
    box_lo: np.ndarray
    box_hi: np.ndarray
    #: bounds (3,) of all vertices in the mesh frame, metres
    mesh_lo: np.ndarray
    mesh_hi: np.ndarray

    def release(self) -> None:
        for obj in (self.vao, self.vbo, self.ibo, self.texture):
            if obj is not None:
                obj.release()


@dataclasses.dataclass(frozen=True)
class _Draw:
    """One object's draw calls in one view: uniform bytes and whether its closed parts may be
    drawn with back faces culled."""

    gm: _GpuMesh
    cam_obj: bytes
    normal: bytes
    instance_id: int
    class_id: int
    cull_closed: bool


@dataclasses.dataclass(frozen=True)
class _Frame:
    """Everything the draw calls of one view need."""

    proj: bytes
    light_cam: tuple[float, ...]
    ambient: float
    background: tuple[float, float, float]
    draws: list[_Draw]
    #: the first ``num_static`` draws are the scene's static objects
    num_static: int = 0
    #: per other (non-static) object, the internal-render pixels (x0, y0, x1, y1), inclusive,
    #: its draws can touch (a box around its projected bounds; empty boxes left out);
    #: ``None``: not known (an object reaches behind the near plane), the whole render
    dynamic_rects: list[tuple[int, int, int, int]] | None = None


class _Targets:
    """The framebuffer of the internal render and its host-side read-back buffers.

    Allocated at a *capacity* (width, height) and drawn in its lower-left ``render_size``
    corner (viewport at the origin, so every pixel lands where a framebuffer of exactly that size
    puts it): randomized cameras, whose internal render size changes with every lens, re-use one
    framebuffer instead of allocating four render buffers per image.
    """

    def __init__(self, ctx: moderngl.Context, capacity: tuple[int, int], *,
                 host: bool = True) -> None:
        self.capacity = capacity
        self.color = ctx.renderbuffer(capacity, 4, dtype="f1")
        self.ids = ctx.renderbuffer(capacity, 1, dtype="u4")
        self.inv_depth = ctx.renderbuffer(capacity, 1, dtype="f4")
        self.depth = ctx.depth_renderbuffer(capacity)
        self.fbo = ctx.framebuffer([self.color, self.ids, self.inv_depth], self.depth)
        # glClear writes one float value into every attachment (bit-cast for integer ones), so
        # the background colour and the zeroed labels are cleared through separate framebuffers.
        # Whole-framebuffer clears: llvmpipe clears a scissored region by drawing a quad.
        self.fbo_color = ctx.framebuffer([self.color])
        self.fbo_labels = ctx.framebuffer([self.ids, self.inv_depth], self.depth)
        n = capacity[0] * capacity[1] if host else 0
        # RGBA reads back ~10x faster than RGB on Mesa; cv2 drops the alpha (numpy's strided
        # copy would cost more than the whole read-back). Flat, viewed at each render size.
        self._rgba = np.zeros(4 * n, np.uint8)
        self._rgb = np.zeros(3 * n, np.uint8)
        # Packed ids as int32 (cv2.remap has no unsigned 32-bit type; nearest copies bits).
        self._ids = np.zeros(n, np.int32)
        self._inv_depth = np.zeros(n, np.float32)

    def fits(self, width: int, height: int) -> bool:
        return width <= self.capacity[0] and height <= self.capacity[1]

    def host(self, width: int, height: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """C-contiguous (H, W, 4) RGBA, (H, W, 3) RGB, (H, W) ids and (H, W) 1 / z views of
        the host buffers for a ``width`` x ``height`` render."""
        n = width * height
        return (self._rgba[:4 * n].reshape(height, width, 4),
                self._rgb[:3 * n].reshape(height, width, 3),
                self._ids[:n].reshape(height, width),
                self._inv_depth[:n].reshape(height, width))

    def release(self) -> None:
        for obj in (self.fbo, self.fbo_color, self.fbo_labels, self.color, self.ids,
                    self.inv_depth, self.depth):
            obj.release()


@dataclasses.dataclass
class _KeptStatic:
    """The render of a scene's static objects through one camera: the framebuffer state
    (``targets``, copied back before the other objects are drawn), the image it gives
    (``out``) and the static objects themselves (referenced so that the ids in the cache key
    are not re-used by other objects)."""

    targets: _Targets
    out: RenderOutput
    objects: tuple[Any, ...]


#: The 12 edges of a box as pairs of corner indices (corner i has bit k set: max along axis k).
_BOX_EDGES: Final = np.array([(i, i | 1 << k) for i in range(8) for k in range(3)
                              if not i & 1 << k])

#: Render stages timed by :class:`StageTimes` (seconds summed over the images rendered).
STAGES: Final = ("scene", "lens_map", "upload", "draw", "read_back", "remap", "labels",
                 "augment")


class StageTimes:
    """Wall-clock seconds per stage, summed over images (a profiling aid for benchmarks).

    Stages (:data:`STAGES`): ``scene`` building the scene and camera (caller), ``lens_map``
    computing a new camera's lens map, ``upload`` meshes and textures new to the renderer,
    ``draw`` issuing the draw calls and rasterizing them (the renderer waits for the GL to
    finish while timed, which costs a little overlap), ``read_back`` the framebuffer reads,
    ``remap`` the lens warp and label unpacking, ``labels`` keypoint/box labels and
    ``augment`` the image augmentation (callers). ``images`` counts rendered images.
    """

    def __init__(self) -> None:
        self.seconds: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        self.images = 0

    def add(self, stage: str, seconds: float) -> None:
        self.seconds[stage] = self.seconds.get(stage, 0.0) + seconds

    def per_image_ms(self) -> dict[str, float]:
        """Milliseconds per image and stage."""
        n = max(self.images, 1)
        return {k: 1000.0 * v / n for k, v in self.seconds.items()}

    def reset(self) -> None:
        self.seconds = dict.fromkeys(STAGES, 0.0)
        self.images = 0


class StageClock:
    """Adds the time since the last :meth:`lap` to a stage of ``times`` (no-op without)."""

    __slots__ = ("t", "times")

    def __init__(self, times: StageTimes | None) -> None:
        self.times = times
        self.t = time.perf_counter() if times is not None else 0.0

    def restart(self) -> None:
        """Start the next lap now (time since the last lap counts for no stage)."""
        if self.times is not None:
            self.t = time.perf_counter()

    def lap(self, stage: str) -> None:
        if self.times is not None:
            now = time.perf_counter()
            self.times.add(stage, now - self.t)
            self.t = now


class Renderer:
    """Renders scenes into ``width`` x ``height`` images; one GL context per renderer.

    Re-usable across frames and cameras of that size: GPU buffers are cached per :class:`Mesh`
    object (a static scene is uploaded once; a mesh's buffers are freed after the mesh is
    garbage-collected), lens maps per (K, dist, size), and one framebuffer serves every
    internal render size (grown when a lens needs a larger one). A scene's static objects
    (:attr:`simulation.mesh.Scene.static_objects`) are drawn once per camera and kept (up to
    :data:`STATIC_CACHE_BYTES`); later frames draw only the other objects on top and remap only
    the image regions those can reach, with the same result. Closed, outward-oriented parts
    of meshes (:func:`closed_outward_faces`) are drawn with back faces culled while the camera is
    outside their bounding box. Not thread-safe: use one renderer per thread (or one process
    per core, see :class:`simulation.dataset.SamplePool`).

    ``times``: when set, every render adds its stages to it (see :class:`StageTimes`).
    """

    def __init__(self, width: int, height: int, near_m: float = DEFAULT_NEAR_M,
                 far_m: float = DEFAULT_FAR_M) -> None:
        if width < 1 or height < 1:
            raise ValueError(f"renderer: bad image size {width}x{height}")
        if not 0.0 < near_m < far_m:
            raise ValueError(f"renderer: need 0 < near_m < far_m, got {near_m}, {far_m}")
        self.width, self.height = int(width), int(height)
        self.near_m, self.far_m = float(near_m), float(far_m)
        self.ctx = create_context()
        import moderngl

        self._mgl = moderngl
        with self.ctx:
            # Window y runs down the image (see projection_matrix): counter-clockwise faces
            # seen from outside are clockwise on screen.
            self.ctx.front_face = "cw"
            self.ctx.cull_face = "back"
            self._programs = (_Program(self.ctx, textured=False),
                              _Program(self.ctx, textured=True))
            # moderngl reads the info strings once, on first use: with the context current
            self._gl_renderer = str(self.ctx.info.get("GL_RENDERER", "?"))
        self._meshes: dict[int, _GpuMesh] = {}
        self._dead_meshes: list[int] = []
        self._lens_maps: collections.OrderedDict[tuple[bytes, bytes, int, int], LensMap] = (
            collections.OrderedDict()
        )
        self._targets: _Targets | None = None
        self._static: collections.OrderedDict[tuple[Any, ...], _KeptStatic] = (
            collections.OrderedDict()
        )
        self._ids_out = np.zeros((self.height, self.width), np.int32)
        self.times: StageTimes | None = None
        log.debug("renderer %dx%d on %s", width, height, self._gl_renderer)

    # ---------------------------------------------------------------------------- lifecycle
    def release(self) -> None:
        """Free every GPU resource and the GL context (the renderer is unusable afterwards)."""
        with self.ctx:
            for gm in self._meshes.values():
                gm.release()
            self._meshes.clear()
            self._release_static()
            if self._targets is not None:
                self._targets.release()
                self._targets = None
            for prog in self._programs:
                prog.release()
        self.ctx.release()

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    @property
    def gl_renderer(self) -> str:
        """The GL implementation drawing the images (e.g. ``llvmpipe (LLVM 15.0.6, 256 bits)``
        on a CPU)."""
        return self._gl_renderer

    @property
    def num_uploaded_meshes(self) -> int:
        """How many meshes have GPU buffers right now."""
        return len(self._meshes)

    # ---------------------------------------------------------------------------- caches
    def lens_map(self, camera: CameraModel) -> LensMap:
        """The cached :class:`LensMap` of ``camera`` (key: K, dist, width, height)."""
        key = (camera.K.tobytes(), camera.dist.tobytes(), camera.width, camera.height)
        lm = self._lens_maps.get(key)
        if lm is None:
            lm = lens_map(camera)
            self._lens_maps[key] = lm
            if len(self._lens_maps) > LENS_MAP_CACHE_SIZE:
                self._lens_maps.popitem(last=False)
        else:
            self._lens_maps.move_to_end(key)
        return lm

    def upload(self, meshes: Iterable[Mesh]) -> int:
        """Upload the ``meshes`` that have no GPU buffers yet (e.g. a training set's floor and
        wall textures before timing); returns how many were new. Rendering uploads what it
        needs by itself."""
        with self.ctx:
            self._purge_dead_meshes()
            return self._upload_new(list(meshes))

    def _upload_new(self, meshes: Sequence[Mesh]) -> int:
        """GPU buffers for the meshes not uploaded yet, all before any draw call of a frame
        (a texture's mipmaps built mid-frame stall llvmpipe), with one batched
        :func:`closed_outward_faces_many` for all of them."""
        new: dict[int, Mesh] = {}
        for mesh in meshes:
            key = id(mesh)
            if key in new or len(mesh.faces) == 0:
                continue
            gm = self._meshes.get(key)
            if gm is not None:
                if gm.ref() is mesh:
                    continue
                gm.release()  # a collected mesh whose id was re-used before it was purged
                del self._meshes[key]
            new[key] = mesh
        if new:
            todo = list(new.values())
            for mesh, closed in zip(todo, closed_outward_faces_many(todo), strict=True):
                self._meshes[id(mesh)] = self._create_gpu_mesh(mesh, closed)
        return len(new)

    def _create_gpu_mesh(self, mesh: Mesh, closed: np.ndarray) -> _GpuMesh:
        key = id(mesh)
        textured = mesh.texture is not None
        prog = self._programs[int(textured)]
        columns = [mesh.vertices, mesh.normals, mesh.colors] + ([mesh.uv] if textured else [])
        vertices = np.hstack(columns).astype(np.float32)  # type: ignore[arg-type]
        vbo = self.ctx.buffer(vertices.tobytes())
        faces = np.concatenate([mesh.faces[closed], mesh.faces[~closed]])  # closed parts first
        ibo = self.ctx.buffer(np.ascontiguousarray(faces, np.uint32).tobytes())
        layout = "3f 3f 3f 2f" if textured else "3f 3f 3f"
        vao = self.ctx.vertex_array(prog.program, [(vbo, layout, *prog.attributes)],
                                    index_buffer=ibo, index_element_size=4)
        texture = None
        if textured:
            assert mesh.texture is not None
            img = np.ascontiguousarray(mesh.texture[::-1])  # uv (0, 0) = bottom-left
            texture = self.ctx.texture((img.shape[1], img.shape[0]), 3, data=img.tobytes(),
                                       alignment=1)
            texture.build_mipmaps()
            texture.filter = (self._mgl.LINEAR_MIPMAP_NEAREST, self._mgl.LINEAR)
        dead = self._dead_meshes

        def on_collected(_ref: weakref.ref[Mesh], k: int = key) -> None:
            dead.append(k)  # freed at the next render, with this renderer's context current

        ref = weakref.ref(mesh, on_collected)
        num_closed = int(closed.sum())
        box = mesh.vertices[mesh.faces[closed].ravel()] if num_closed else mesh.vertices[:1]
        return _GpuMesh(ref, prog, vbo, ibo, vao, texture, num_closed, len(faces),
                        box.min(axis=0).astype(np.float64), box.max(axis=0).astype(np.float64),
                        mesh.vertices.min(axis=0).astype(np.float64),
                        mesh.vertices.max(axis=0).astype(np.float64))

    def _purge_dead_meshes(self) -> None:
        while self._dead_meshes:
            key = self._dead_meshes.pop()
            gm = self._meshes.get(key)
            if gm is not None and gm.ref() is None:
                gm.release()
                del self._meshes[key]

    def _targets_for(self, width: int, height: int) -> _Targets:
        t = self._targets
        if t is None or not t.fits(width, height):
            capacity = (width, height) if t is None else (max(width, t.capacity[0]),
                                                          max(height, t.capacity[1]))
            if t is not None:
                t.release()
            self._release_static()  # kept renders are copied whole: same size only
            t = self._targets = _Targets(self.ctx, capacity)
            log.debug("renderer %dx%d: framebuffer %dx%d", self.width, self.height, *capacity)
        return t

    # ---------------------------------------------------------------------------- rendering
    def render(self, scene: Scene, camera: CameraModel,
               out: RenderOutput | None = None) -> RenderOutput:
        """Draw ``scene`` through ``camera`` (its size must be the renderer's).

        Returns a :class:`RenderOutput`; with ``out`` (e.g. from :meth:`RenderOutput.empty`)
        its arrays are overwritten and returned instead of allocating new ones.
        """
        return self.render_many([(scene, camera)], None if out is None else [out])[0]

    def render_many(self, views: Sequence[tuple[Scene, CameraModel]],
                    outs: Sequence[RenderOutput] | None = None) -> list[RenderOutput]:
        """Draw several (scene, camera) views in one batch: one context switch, the meshes new
        to the renderer of *all* views uploaded together before the first draw, then each view
        drawn and read back in turn through the shared framebuffer. The images are exactly
        those of :meth:`render` one view at a time.

        Why views are not tiled into one larger framebuffer: on llvmpipe a frame's fixed cost
        is small next to its pixels, and a framebuffer several times larger falls out of the
        CPU caches; ``smartedge bench render`` measures the tiled floor beside the plain one.
        """
        views = list(views)
        if outs is not None and len(outs) != len(views):
            raise ValueError(f"render_many: {len(outs)} outputs for {len(views)} views")
        for _, camera in views:
            if (camera.width, camera.height) != (self.width, self.height):
                raise ValueError(
                    f"camera {camera.camera_id} is {camera.width}x{camera.height}, the "
                    f"renderer {self.width}x{self.height}"
                )
        if outs is None:
            outs = [RenderOutput.empty(self.width, self.height) for _ in views]
        else:
            for out in outs:
                _check_out(out, self.width, self.height)
        clock = StageClock(self.times)
        lens = [self.lens_map(camera) for _, camera in views]
        clock.lap("lens_map")
        # Every GL call goes to the thread's current context: with several renderers in one
        # process (one per image size, say) each must make its own current first.
        with self.ctx:
            self._purge_dead_meshes()
            self._upload_new([obj.mesh for scene, _ in views for obj in scene.objects])
            clock.lap("upload")
            for (scene, camera), lm, out in zip(views, lens, outs, strict=True):
                self._draw(scene, camera, lm, out, clock)
        if self.times is not None:
            self.times.images += len(views)
        return list(outs)

    def _draw(self, scene: Scene, camera: CameraModel, lm: LensMap, out: RenderOutput,
              clock: StageClock) -> None:
        rw, rh = lm.render_size
        t = self._targets_for(rw, rh)
        frame = self._frame(scene, camera, lm)
        if frame.num_static:
            self._draw_on_kept_static(scene, camera, lm, frame, t, out, clock)
            return
        t.fbo_color.clear(*frame.background, 1.0)
        t.fbo_labels.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        t.fbo.use()
        self._issue(frame, (0, 0, rw, rh))
        if clock.times is not None:
            self.ctx.finish()  # rasterization happens here, not in the read-back
        clock.lap("draw")
        self._read_back(t, lm, frame.background, out, clock)

    def _draw_on_kept_static(self, scene: Scene, camera: CameraModel, lm: LensMap,
                             frame: _Frame, t: _Targets, out: RenderOutput,
                             clock: StageClock) -> None:
        """Draw a scene with static objects: their render (all three targets and the depth
        buffer) is copied from the cache, drawn once per camera; the other objects are drawn
        on top (the same draws in the same order as one pass); only the image regions they can
        reach are read back and remapped, the rest of the image is the kept one."""
        viewport = (0, 0, *lm.render_size)
        static = scene.objects[:scene.static_objects]
        key = (camera.K.tobytes(), camera.dist.tobytes(), camera.T_cam_world.tobytes(),
               (camera.width, camera.height), tuple(map(id, static)), frame.light_cam,
               frame.ambient, frame.background)
        kept = self._static.get(key)
        if kept is None:
            t.fbo_color.clear(*frame.background, 1.0)
            t.fbo_labels.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            t.fbo.use()
            self._issue(frame, viewport, slice(0, frame.num_static))
            static_out = RenderOutput.empty(self.width, self.height)
            self._read_back(t, lm, frame.background, static_out, StageClock(None))
            kept = self._keep_static(key, static, t, static_out)
        else:
            self._static.move_to_end(key)
            self.ctx.copy_framebuffer(t.fbo, kept.targets.fbo)
        t.fbo.use()
        self._issue(frame, viewport, slice(frame.num_static, None))
        if clock.times is not None:
            self.ctx.finish()
        clock.lap("draw")
        rects = frame.dynamic_rects or []
        regions = [self._output_region(rect, lm) for rect in rects]
        if frame.dynamic_rects is None or any(r is None for r in regions):
            self._read_back(t, lm, frame.background, out, clock)  # not bounded: everything
            return
        self._read_back_regions(t, lm, frame.background, kept.out,
                                [r for r in regions if r is not None], out, clock)

    def _frame(self, scene: Scene, camera: CameraModel, lm: LensMap) -> _Frame:
        """Everything one view's draw calls need (uniform bytes, per object: buffers, ids,
        whether back faces may be culled), computed with a few batched numpy calls."""
        rw, rh = lm.render_size
        proj = np.ascontiguousarray(
            projection_matrix(lm.K_render, rw, rh, self.near_m, self.far_m).T, np.float32
        ).tobytes()
        light = camera.T_cam_world[:3, :3] @ np.asarray(scene.light_dir_world, np.float64)
        norm = float(np.linalg.norm(light))
        light_cam = tuple(light / norm) if norm > 0 else (0.0, 0.0, 0.0)
        objects = [obj for obj in scene.objects if len(obj.mesh.faces)]
        num_static = sum(1 for obj in scene.objects[:scene.static_objects]
                         if len(obj.mesh.faces))
        draws: list[_Draw] = []
        if objects:
            gms = [self._meshes[id(obj.mesh)] for obj in objects]
            T_world_obj = np.stack([obj.T_world_object for obj in objects])
            T_cam_obj = camera.T_cam_world @ T_world_obj
            # GLSL mat3 is column-major: writing inv(R) row-major uploads inv(R).T.
            normal = np.ascontiguousarray(np.linalg.inv(T_cam_obj[:, :3, :3]), np.float32)
            cam_obj = np.ascontiguousarray(T_cam_obj.transpose(0, 2, 1), np.float32)
            outside = self._outside_boxes(gms, T_world_obj, camera.position_world)
            draws = [_Draw(gm, cam_obj[k].tobytes(), normal[k].tobytes(),
                           int(obj.instance_id), int(obj.class_id), bool(outside[k]))
                     for k, (gm, obj) in enumerate(zip(gms, objects, strict=True))]
        rects = None
        if num_static:
            rects = self._dynamic_rects(gms[num_static:], T_cam_obj[num_static:], lm)
        bg = tuple(float(c) for c in scene.background_rgb)
        return _Frame(proj, light_cam, float(scene.ambient), (bg[0], bg[1], bg[2]), draws,
                      num_static, rects)

    def _dynamic_rects(self, gms: Sequence[_GpuMesh], T_cam_obj: np.ndarray, lm: LensMap
                       ) -> list[tuple[int, int, int, int]]:
        """Per mesh of ``gms`` placed by ``T_cam_obj`` (N, 4, 4), the internal-render pixels
        (x0, y0, x1, y1), inclusive, covering every fragment it can draw: its bounding box's
        corners projected through the internal pinhole (perspective keeps a point set's
        projection inside that of its convex hull), plus 2 px; meshes wholly outside the render
        or behind the near plane are left out. A box crossing the near plane is cut at it
        first, as GL clips what it draws."""
        rw, rh = lm.render_size
        if not gms:
            return []
        lo = np.stack([gm.mesh_lo for gm in gms])
        hi = np.stack([gm.mesh_hi for gm in gms])
        pick = np.array([[(i >> k) & 1 for k in range(3)] for i in range(8)], bool)  # (8, 3)
        corners = np.where(pick[None], hi[:, None], lo[:, None])  # (N, 8, 3)
        cam = corners @ T_cam_obj[:, :3, :3].transpose(0, 2, 1) + T_cam_obj[:, None, :3, 3]
        # GL clips at z = near: what can be drawn lies in the box's part in front of that
        # plane, whose corners are the box corners in front plus where its edges cross it
        near = self.near_m * (1.0 + 1e-6)
        rects = []
        K = lm.K_render
        for pts in cam:
            front = pts[:, 2] >= near
            if not front.any():
                continue  # wholly behind the near plane: clipped away
            if not front.all():
                a, b = pts[_BOX_EDGES[:, 0]], pts[_BOX_EDGES[:, 1]]
                cross = (a[:, 2] >= near) != (b[:, 2] >= near)
                a, b = a[cross], b[cross]
                s = (near - a[:, 2]) / (b[:, 2] - a[:, 2])
                pts = np.concatenate([pts[front], a + s[:, None] * (b - a)])
                pts[:, 2] = np.maximum(pts[:, 2], near)
            z = pts[:, 2]
            u = K[0, 0] * pts[:, 0] / z + K[0, 1] * pts[:, 1] / z + K[0, 2]
            v = K[1, 1] * pts[:, 1] / z + K[1, 2]
            x0, x1 = max(0, math.floor(float(u.min())) - 2), min(rw - 1,
                                                                 math.ceil(float(u.max())) + 2)
            y0, y1 = max(0, math.floor(float(v.min())) - 2), min(rh - 1,
                                                                 math.ceil(float(v.max())) + 2)
            if x0 <= x1 and y0 <= y1:
                rects.append((x0, y0, x1, y1))
        return rects

    def _issue(self, frame: _Frame, viewport: tuple[int, int, int, int],
               draws: slice = slice(None)) -> None:
        """The draw calls ``draws`` of ``frame`` (default: all) into the bound framebuffer's
        ``viewport``."""
        mgl = self._mgl
        self.ctx.viewport = viewport
        self.ctx.enable_only(mgl.DEPTH_TEST)
        culling = False
        for prog in self._programs:
            prog.proj.write(frame.proj)
            prog.light.value = frame.light_cam
            prog.ambient.value = frame.ambient
        for d in frame.draws[draws]:
            gm = d.gm
            prog = gm.program
            prog.cam_obj.write(d.cam_obj)
            prog.normal.write(d.normal)
            prog.instance_id.value = d.instance_id
            prog.class_id.value = d.class_id
            if gm.texture is not None:
                gm.texture.use(0)
            if d.cull_closed:
                if not culling:
                    self.ctx.enable(mgl.CULL_FACE)
                    culling = True
                gm.vao.render(mgl.TRIANGLES, vertices=3 * gm.num_closed)
                first = gm.num_closed
            else:
                first = 0
            if first < gm.num_faces:
                if culling:
                    self.ctx.disable(mgl.CULL_FACE)
                    culling = False
                gm.vao.render(mgl.TRIANGLES, vertices=3 * (gm.num_faces - first),
                              first=3 * first)

    # ---------------------------------------------------------------------------- floor
    def gl_floor(self, views: Sequence[tuple[Scene, CameraModel]], seconds: float = 2.0,
                 tiles: int = 1, static: bool = False) -> float:
        """Seconds per view of the GL work alone: the draw calls of ``views`` (the same
        triangles, textures, shaders and framebuffer size as :meth:`render`) replayed from
        pre-computed uniforms, with the clears and the read-back of the three targets, and
        nothing else per frame (no scene, lens map, uploads, remap or labels): the floor of
        what this GL (llvmpipe on a CPU) can do for these images.

        ``static``: replay what :meth:`render` does for scenes with static objects instead
        (copy their kept render, draw the other objects on top) rather than every draw.
        ``tiles`` > 1 (every draw only): that many views tiled into one framebuffer (a
        near-square grid of cells of the largest internal size), each drawn in its own
        viewport, read back with one read per target: the batching that :meth:`render_many`
        does not do, measured.
        """
        views = list(views)
        if static and tiles > 1:
            raise ValueError("gl_floor: tiles are measured with every draw (static=False)")
        lens = [self.lens_map(camera) for _, camera in views]
        with self.ctx:
            self._purge_dead_meshes()
            self._upload_new([obj.mesh for scene, _ in views for obj in scene.objects])
            frames = [self._frame(scene, camera, lm)
                      for (scene, camera), lm in zip(views, lens, strict=True)]
            cw = max(lm.render_size[0] for lm in lens)
            ch = max(lm.render_size[1] for lm in lens)
            cols = max(1, math.ceil(math.sqrt(tiles)))
            rows = math.ceil(tiles / cols)
            t = _Targets(self.ctx, (cols * cw, rows * ch))
            kept: list[_Targets | None] = [None] * len(frames)
            try:
                rgba, _, ids, inv_depth = t.host(cols * cw, rows * ch)
                full = (0, 0, cols * cw, rows * ch)

                def clear() -> None:
                    t.fbo_color.clear(0.0, 0.0, 0.0, 1.0)
                    t.fbo_labels.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
                    t.fbo.use()

                if static:
                    for j, frame in enumerate(frames):
                        if frame.num_static:
                            clear()
                            self._issue(frame, (0, 0, *lens[j].render_size),
                                        slice(0, frame.num_static))
                            kept[j] = _Targets(self.ctx, t.capacity, host=False)
                            self.ctx.copy_framebuffer(kept[j].fbo, t.fbo)

                def one_pass(first: int) -> None:
                    j = first % len(frames)
                    k_j = kept[j]
                    if k_j is None:
                        clear()
                        for k in range(tiles):
                            j = (first + k) % len(frames)
                            rw, rh = lens[j].render_size
                            self._issue(frames[j], ((k % cols) * cw, (k // cols) * ch, rw, rh))
                    else:
                        self.ctx.copy_framebuffer(t.fbo, k_j.fbo)
                        t.fbo.use()
                        self._issue(frames[j], (0, 0, *lens[j].render_size),
                                    slice(frames[j].num_static, None))
                    t.fbo.read_into(rgba, full, components=4, attachment=0)
                    t.fbo.read_into(ids, full, components=1, attachment=1, dtype="u4")
                    t.fbo.read_into(inv_depth, full, components=1, attachment=2, dtype="f4")

                for k in range(3):
                    one_pass(k * tiles)
                passes, t0 = 0, time.perf_counter()
                while passes < 3 or time.perf_counter() - t0 < seconds:
                    one_pass(passes * tiles)
                    passes += 1
                return (time.perf_counter() - t0) / (passes * tiles)
            finally:
                t.release()
                for k_t in kept:
                    if k_t is not None:
                        k_t.release()

    def _keep_static(self, key: tuple[Any, ...], objects: Sequence[Any], t: _Targets,
                     out: RenderOutput) -> _KeptStatic:
        """Copy the framebuffer (the static objects just drawn) into the cache under ``key``,
        with ``out``, their image; the least recently used renders go when
        :data:`STATIC_CACHE_BYTES` would be exceeded."""
        cap_w, cap_h = t.capacity
        limit = max(1, STATIC_CACHE_BYTES // (16 * cap_w * cap_h + 15 * out.color_rgb.size // 3))
        while len(self._static) >= limit:
            _, old = self._static.popitem(last=False)
            old.targets.release()
        kept = _KeptStatic(_Targets(self.ctx, t.capacity, host=False), out, tuple(objects))
        self.ctx.copy_framebuffer(kept.targets.fbo, t.fbo)
        self._static[key] = kept
        return kept

    def _output_region(self, rect: tuple[int, int, int, int], lm: LensMap
                       ) -> tuple[int, int, int, int] | None:
        """Image pixels (x0, y0, x1, y1), inclusive, whose value can depend on the internal
        pixels ``rect`` (the lens maps them there, bilinear footprint included); ``None``:
        not known, the whole image. (0, 0, -1, -1): none."""
        x0, y0, x1, y1 = rect
        if lm.identity:
            return rect
        # the rectangle's boundary (1 px wider for the bilinear footprint), every 4 px, through
        # the lens: a continuous one-to-one map inside the fold radius takes the rectangle to
        # the region its boundary's image encloses
        xs = np.arange(x0 - 1.0, x1 + 1.0 + 4.0, 4.0)
        ys = np.arange(y0 - 1.0, y1 + 1.0 + 4.0, 4.0)
        xs[-1], ys[-1] = min(xs[-1], x1 + 1.0), min(ys[-1], y1 + 1.0)
        pts = np.concatenate([np.column_stack([xs, np.full_like(xs, y0 - 1.0)]),
                              np.column_stack([xs, np.full_like(xs, ys[-1])]),
                              np.column_stack([np.full_like(ys, x0 - 1.0), ys]),
                              np.column_stack([np.full_like(ys, xs[-1]), ys])])
        Kr = lm.K_render
        xy = np.column_stack([(pts[:, 0] - Kr[0, 2]) / Kr[0, 0],
                              (pts[:, 1] - Kr[1, 2]) / Kr[1, 1]])
        if not float(np.hypot(xy[:, 0], xy[:, 1]).max()) < lm.fold_radius:
            return None
        assert lm.K is not None and lm.dist is not None
        d = distort_normalized(xy, lm.dist)
        K = lm.K
        u = K[0, 0] * d[:, 0] + K[0, 1] * d[:, 1] + K[0, 2]
        v = K[1, 1] * d[:, 1] + K[1, 2]
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(v))):
            return None
        ox0, ox1 = max(0, math.floor(float(u.min())) - 2), min(self.width - 1,
                                                                 math.ceil(float(u.max())) + 2)
        oy0, oy1 = max(0, math.floor(float(v.min())) - 2), min(self.height - 1,
                                                                  math.ceil(float(v.max())) + 2)
        if ox0 > ox1 or oy0 > oy1:
            return (0, 0, -1, -1)
        return (ox0, oy0, ox1, oy1)

    def _read_back_regions(self, t: _Targets, lm: LensMap, bg: tuple[float, float, float],
                           static: RenderOutput, regions: Sequence[tuple[int, int, int, int]],
                           out: RenderOutput, clock: StageClock) -> None:
        """``out`` = the kept static image with the image pixels of ``regions`` (inclusive
        boxes, possibly overlapping) read back and remapped from the framebuffer: outside them
        the other objects changed nothing. Each pixel is computed exactly as
        :meth:`_read_back` computes it (twice where regions overlap: the same value)."""
        for name in ("color_rgb", "depth_m", "instance_id", "class_id"):
            np.copyto(getattr(out, name), getattr(static, name))
        clock.lap("read_back")
        for region in regions:
            x0, y0, x1, y1 = region
            if x0 <= x1 and y0 <= y1:
                self._read_back_region(t, lm, bg, region, out)
        clock.lap("remap")

    def _read_back_region(self, t: _Targets, lm: LensMap, bg: tuple[float, float, float],
                          region: tuple[int, int, int, int], out: RenderOutput) -> None:
        """The image pixels ``region`` (inclusive box) of ``out`` from the framebuffer."""
        x0, y0, x1, y1 = region
        roi = (slice(y0, y1 + 1), slice(x0, x1 + 1))
        fbo = t.fbo
        if lm.identity:
            src = (x0, y0, x1 - x0 + 1, y1 - y0 + 1)
            rgba, _, ids, inv_depth = t.host(src[2], src[3])
            fbo.read_into(rgba, src, components=4, attachment=0)
            fbo.read_into(ids, src, components=1, attachment=1, dtype="u4")
            fbo.read_into(inv_depth, src, components=1, attachment=2, dtype="f4")
            cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB, dst=out.color_rgb[roi])
            depth = inv_depth
        else:
            assert lm.color_maps is not None and lm.nearest_map is not None
            rw, rh = lm.render_size
            map1, map2 = lm.color_maps[0][roi], lm.color_maps[1][roi]
            near = lm.nearest_map[roi]
            # the internal pixels these image pixels read (bilinear: the one right/below too)
            both = np.concatenate([map1.reshape(-1, 2), near.reshape(-1, 2)])
            sx0, sy0 = (max(0, int(v)) for v in both.min(axis=0))
            sx1, sy1 = (min(m, int(v) + 1) for m, v in zip((rw - 1, rh - 1),
                                                             both.max(axis=0), strict=True))
            if sx0 > sx1 or sy0 > sy1:  # every pixel of the region maps outside the render
                sx0, sy0, sx1, sy1 = 0, 0, 0, 0
            src = (sx0, sy0, sx1 - sx0 + 1, sy1 - sy0 + 1)
            rgba, rgb, ids, inv_depth = t.host(src[2], src[3])
            fbo.read_into(rgba, src, components=4, attachment=0)
            fbo.read_into(ids, src, components=1, attachment=1, dtype="u4")
            fbo.read_into(inv_depth, src, components=1, attachment=2, dtype="f4")
            cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB, dst=rgb)
            offset = np.array([sx0, sy0], np.int16)
            # maps point into the whole render: shift them into the block read back (pixels
            # without preimage stay far outside and keep the border value)
            map1 = map1 - offset
            near = near - offset
            border = tuple(round(255.0 * min(max(c, 0.0), 1.0)) for c in bg)
            cv2.remap(rgb, map1, map2, cv2.INTER_LINEAR, dst=out.color_rgb[roi],
                      borderMode=cv2.BORDER_CONSTANT, borderValue=border)
            ids_roi = np.empty((y1 - y0 + 1, x1 - x0 + 1), np.int32)
            depth = np.empty((y1 - y0 + 1, x1 - x0 + 1), np.float32)
            for src_img, dst in ((ids, ids_roi), (inv_depth, depth)):
                cv2.remap(src_img, near, None,  # type: ignore[call-overload]
                          cv2.INTER_NEAREST, dst=dst, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0)
            ids = ids_roi
        packed = ids.view(np.uint32)
        np.right_shift(packed, 8, out=out.instance_id[roi].view(np.uint32))
        np.bitwise_and(packed, 0xFF, out=out.class_id[roi].view(np.uint32))
        with np.errstate(divide="ignore"):
            np.reciprocal(depth, out=out.depth_m[roi])

    def _release_static(self) -> None:
        for kept in self._static.values():
            kept.targets.release()
        self._static.clear()

    def _outside_boxes(self, gms: Sequence[_GpuMesh], T_world_obj: np.ndarray,
                       cam_world: np.ndarray) -> np.ndarray:
        """(N,) bool per object: it has closed parts, the camera is clear of their bounding box
        (by more than the near distance, so near-plane clipping cannot open the mesh) and the
        object transform keeps handedness."""
        result = np.zeros(len(gms), bool)
        idx = [k for k, gm in enumerate(gms) if gm.num_closed]
        if not idx:
            return result
        A = T_world_obj[idx, :3, :3]
        det = np.linalg.det(A)
        ok = det > 0.0
        if not ok.any():
            return result
        sel = np.asarray(idx)[ok]
        cam_obj = np.linalg.solve(A[ok], (cam_world[:3] - T_world_obj[sel, :3, 3])[..., None])
        cam_obj = cam_obj[..., 0]
        margin = 2.0 * self.near_m / np.maximum(np.abs(det[ok]) ** (1.0 / 3.0), 1e-9)
        lo = np.stack([gms[k].box_lo for k in sel]) - margin[:, None]
        hi = np.stack([gms[k].box_hi for k in sel]) + margin[:, None]
        result[sel] = np.any(cam_obj < lo, axis=1) | np.any(cam_obj > hi, axis=1)
        return result

    def _read_back(self, t: _Targets, lm: LensMap, bg: tuple[float, float, float],
                   out: RenderOutput, clock: StageClock) -> None:
        fbo = t.fbo
        rw, rh = lm.render_size
        viewport = (0, 0, rw, rh)
        rgba, rgb, ids, inv_depth = t.host(rw, rh)
        ids_out = self._ids_out
        fbo.read_into(rgba, viewport, components=4, attachment=0)
        if lm.identity:
            fbo.read_into(ids_out, viewport, components=1, attachment=1, dtype="u4")
            fbo.read_into(out.depth_m, viewport, components=1, attachment=2, dtype="f4")
            clock.lap("read_back")
            cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB, dst=out.color_rgb)
        else:
            assert lm.color_maps is not None and lm.nearest_map is not None
            fbo.read_into(ids, viewport, components=1, attachment=1, dtype="u4")
            fbo.read_into(inv_depth, viewport, components=1, attachment=2, dtype="f4")
            clock.lap("read_back")
            cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB, dst=rgb)
            border = tuple(round(255.0 * min(max(c, 0.0), 1.0)) for c in bg)
            cv2.remap(rgb, *lm.color_maps, cv2.INTER_LINEAR, dst=out.color_rgb,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=border)
            for src, dst in ((ids, ids_out), (inv_depth, out.depth_m)):
                cv2.remap(src, lm.nearest_map, None,  # type: ignore[call-overload]
                          cv2.INTER_NEAREST, dst=dst, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0)
        packed = ids_out.view(np.uint32)
        np.right_shift(packed, 8, out=out.instance_id.view(np.uint32))
        np.bitwise_and(packed, 0xFF, out=out.class_id.view(np.uint32))
        with np.errstate(divide="ignore"):
            np.reciprocal(out.depth_m, out=out.depth_m)  # 1 / 0 (nothing drawn) = inf
        clock.lap("remap")


def _check_out(out: RenderOutput, width: int, height: int) -> None:
    expected = (
        ("color_rgb", np.uint8, (height, width, 3)), ("depth_m", np.float32, (height, width)),
        ("instance_id", np.int32, (height, width)), ("class_id", np.int32, (height, width)),
    )
    for name, dtype, shape in expected:
        arr = getattr(out, name)
        if arr.dtype != dtype or arr.shape != shape or not arr.flags.c_contiguous:
            raise ValueError(
                f"render: out.{name} must be a C-contiguous {np.dtype(dtype).name} array of "
                f"shape {shape}, got {arr.dtype} {arr.shape}"
            )
