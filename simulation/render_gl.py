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
outside their bounding box (same image, half the rasterization work on llvmpipe).

Texture coordinates follow OpenGL/OBJ: (0, 0) is the *bottom*-left corner of the texture
image, v grows upwards, and textures repeat outside [0, 1].
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import weakref
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
        return LensMap(K.copy(), (W, H), identity=True)

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
    invalid = upsample(bad.astype(np.float32)) > 0.0  # any bad sample in the cell: empty
    num_invalid = int(np.count_nonzero(invalid))
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
                   nearest_map=nearest_map, num_without_preimage=num_invalid)


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
    faces = mesh.faces.astype(np.int64)
    result = np.zeros(len(faces), bool)
    if len(faces) < 4:
        return result
    keys = np.round(mesh.vertices.astype(np.float64) / weld_m).astype(np.int64)
    _, welded = np.unique(keys, axis=0, return_inverse=True)
    f = welded.reshape(-1)[faces]
    keep = np.flatnonzero((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    if len(keep) < 4:
        return result
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
    v = mesh.vertices.astype(np.float64)
    fv = mesh.faces[keep]
    volume6 = np.einsum("ij,ij->i", v[fv[:, 0]], np.cross(v[fv[:, 1]], v[fv[:, 2]]))
    part_volume = np.bincount(part, weights=volume6, minlength=num_parts)
    result[keep] = (~part_open & (part_volume > 0.0))[part]
    return result


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

    def release(self) -> None:
        for obj in (self.vao, self.vbo, self.ibo, self.texture):
            if obj is not None:
                obj.release()


class _Targets:
    """The framebuffer of the internal render and its host-side read-back buffers."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int, out_width: int,
                 out_height: int) -> None:
        self.size = (width, height)
        self.color = ctx.renderbuffer(self.size, 4, dtype="f1")
        self.ids = ctx.renderbuffer(self.size, 1, dtype="u4")
        self.inv_depth = ctx.renderbuffer(self.size, 1, dtype="f4")
        self.depth = ctx.depth_renderbuffer(self.size)
        self.fbo = ctx.framebuffer([self.color, self.ids, self.inv_depth], self.depth)
        # glClear writes one float value into every attachment (bit-cast for integer ones), so
        # the background colour and the zeroed labels are cleared through separate framebuffers.
        self.fbo_color = ctx.framebuffer([self.color])
        self.fbo_labels = ctx.framebuffer([self.ids, self.inv_depth], self.depth)
        # RGBA reads back ~10x faster than RGB on Mesa; cv2 drops the alpha (numpy's strided
        # copy would cost more than the whole read-back).
        self.rgba = np.zeros((height, width, 4), np.uint8)
        self.color_rgb = np.zeros((height, width, 3), np.uint8)
        # Packed ids as int32 (cv2.remap has no unsigned 32-bit type; nearest copies bits).
        self.ids_host = np.zeros((height, width), np.int32)
        self.inv_depth_host = np.zeros((height, width), np.float32)
        self.ids_out = np.zeros((out_height, out_width), np.int32)

    def release(self) -> None:
        for obj in (self.fbo, self.fbo_color, self.fbo_labels, self.color, self.ids,
                    self.inv_depth, self.depth):
            obj.release()


class Renderer:
    """Renders scenes into ``width`` x ``height`` images; one GL context per renderer.

    Re-usable across frames and cameras of that size: GPU buffers are cached per :class:`Mesh`
    object (a static scene is uploaded once; a mesh's buffers are freed after the mesh is
    garbage-collected), lens maps per (K, dist, size). Closed, outward-oriented parts of meshes
    (:func:`closed_outward_faces`) are drawn with back faces culled while the camera is outside
    their bounding box. Not thread-safe: use one renderer per thread.
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
        self._meshes: dict[int, _GpuMesh] = {}
        self._dead_meshes: list[int] = []
        self._lens_maps: collections.OrderedDict[tuple[bytes, bytes, int, int], LensMap] = (
            collections.OrderedDict()
        )
        self._targets: _Targets | None = None
        log.debug("renderer %dx%d on %s", width, height, self.ctx.info.get("GL_RENDERER"))

    # ---------------------------------------------------------------------------- lifecycle
    def release(self) -> None:
        """Free every GPU resource and the GL context (the renderer is unusable afterwards)."""
        with self.ctx:
            for gm in self._meshes.values():
                gm.release()
            self._meshes.clear()
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

    def _gpu_mesh(self, mesh: Mesh) -> _GpuMesh:
        key = id(mesh)
        gm = self._meshes.get(key)
        if gm is not None:
            if gm.ref() is mesh:
                return gm
            gm.release()  # a collected mesh whose id was re-used before it was purged
        textured = mesh.texture is not None
        prog = self._programs[int(textured)]
        columns = [mesh.vertices, mesh.normals, mesh.colors] + ([mesh.uv] if textured else [])
        vertices = np.hstack(columns).astype(np.float32)  # type: ignore[arg-type]
        vbo = self.ctx.buffer(vertices.tobytes())
        closed = closed_outward_faces(mesh)
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
        gm = _GpuMesh(ref, prog, vbo, ibo, vao, texture, num_closed, len(faces),
                      box.min(axis=0).astype(np.float64), box.max(axis=0).astype(np.float64))
        self._meshes[key] = gm
        return gm

    def _purge_dead_meshes(self) -> None:
        while self._dead_meshes:
            key = self._dead_meshes.pop()
            gm = self._meshes.get(key)
            if gm is not None and gm.ref() is None:
                gm.release()
                del self._meshes[key]

    def _targets_for(self, width: int, height: int) -> _Targets:
        t = self._targets
        if t is None or t.size != (width, height):
            if t is not None:
                t.release()
            t = self._targets = _Targets(self.ctx, width, height, self.width, self.height)
        return t

    # ---------------------------------------------------------------------------- rendering
    def render(self, scene: Scene, camera: CameraModel,
               out: RenderOutput | None = None) -> RenderOutput:
        """Draw ``scene`` through ``camera`` (its size must be the renderer's).

        Returns a :class:`RenderOutput`; with ``out`` (e.g. from :meth:`RenderOutput.empty`)
        its arrays are overwritten and returned instead of allocating new ones.
        """
        if (camera.width, camera.height) != (self.width, self.height):
            raise ValueError(
                f"camera {camera.camera_id} is {camera.width}x{camera.height}, the renderer "
                f"{self.width}x{self.height}"
            )
        if out is None:
            out = RenderOutput.empty(self.width, self.height)
        else:
            _check_out(out, self.width, self.height)
        lm = self.lens_map(camera)
        # Every GL call goes to the thread's current context: with several renderers in one
        # process (one per image size, say) each must make its own current first.
        with self.ctx:
            self._purge_dead_meshes()
            self._draw(scene, camera, lm, out)
        return out

    def _draw(self, scene: Scene, camera: CameraModel, lm: LensMap, out: RenderOutput) -> None:
        rw, rh = lm.render_size
        t = self._targets_for(rw, rh)
        mgl = self._mgl

        bg = tuple(float(c) for c in scene.background_rgb)
        t.fbo_color.clear(bg[0], bg[1], bg[2], 1.0)
        t.fbo_labels.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        t.fbo.use()
        self.ctx.enable_only(mgl.DEPTH_TEST)
        culling = False
        proj = np.ascontiguousarray(
            projection_matrix(lm.K_render, rw, rh, self.near_m, self.far_m).T, np.float32
        ).tobytes()
        light = camera.T_cam_world[:3, :3] @ np.asarray(scene.light_dir_world, np.float64)
        norm = float(np.linalg.norm(light))
        light_cam = tuple(light / norm) if norm > 0 else (0.0, 0.0, 0.0)
        for prog in self._programs:
            prog.proj.write(proj)
            prog.light.value = light_cam
            prog.ambient.value = float(scene.ambient)
        cam_world = np.append(camera.position_world, 1.0)
        for obj in scene.objects:
            if len(obj.mesh.faces) == 0:
                continue
            gm = self._gpu_mesh(obj.mesh)
            prog = gm.program
            T_cam_obj = camera.T_cam_world @ obj.T_world_object
            R = T_cam_obj[:3, :3]
            prog.cam_obj.write(np.ascontiguousarray(T_cam_obj.T, np.float32).tobytes())
            # GLSL mat3 is column-major: writing inv(R) row-major uploads inv(R).T.
            prog.normal.write(np.ascontiguousarray(np.linalg.inv(R), np.float32).tobytes())
            prog.instance_id.value = int(obj.instance_id)
            prog.class_id.value = int(obj.class_id)
            if gm.texture is not None:
                gm.texture.use(0)
            if gm.num_closed and self._outside_box(gm, obj.T_world_object, cam_world):
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

        self._read_back(t, lm, bg, out)

    def _outside_box(self, gm: _GpuMesh, T_world_object: np.ndarray,
                     cam_world: np.ndarray) -> bool:
        """The camera is clear of the mesh's bounding box (by more than the near distance, so
        near-plane clipping cannot open the mesh) and the object transform keeps handedness."""
        A = T_world_object[:3, :3]
        det = float(np.linalg.det(A))
        if det <= 0.0:
            return False
        cam_obj = np.linalg.solve(A, cam_world[:3] - T_world_object[:3, 3])
        margin = 2.0 * self.near_m / max(abs(det) ** (1.0 / 3.0), 1e-9)
        return bool(np.any(cam_obj < gm.box_lo - margin) or np.any(cam_obj > gm.box_hi + margin))

    def _read_back(self, t: _Targets, lm: LensMap, bg: tuple[float, ...],
                   out: RenderOutput) -> None:
        fbo = t.fbo
        fbo.read_into(t.rgba, components=4, attachment=0)
        if lm.identity:
            cv2.cvtColor(t.rgba, cv2.COLOR_RGBA2RGB, dst=out.color_rgb)
            fbo.read_into(t.ids_out, components=1, attachment=1, dtype="u4")
            fbo.read_into(out.depth_m, components=1, attachment=2, dtype="f4")
        else:
            assert lm.color_maps is not None and lm.nearest_map is not None
            fbo.read_into(t.ids_host, components=1, attachment=1, dtype="u4")
            fbo.read_into(t.inv_depth_host, components=1, attachment=2, dtype="f4")
            cv2.cvtColor(t.rgba, cv2.COLOR_RGBA2RGB, dst=t.color_rgb)
            border = tuple(round(255.0 * min(max(c, 0.0), 1.0)) for c in bg)
            cv2.remap(t.color_rgb, *lm.color_maps, cv2.INTER_LINEAR, dst=out.color_rgb,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=border)
            for src, dst in ((t.ids_host, t.ids_out), (t.inv_depth_host, out.depth_m)):
                cv2.remap(src, lm.nearest_map, None,  # type: ignore[call-overload]
                          cv2.INTER_NEAREST, dst=dst, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0)
        packed = t.ids_out.view(np.uint32)
        np.right_shift(packed, 8, out=out.instance_id.view(np.uint32))
        np.bitwise_and(packed, 0xFF, out=out.class_id.view(np.uint32))
        with np.errstate(divide="ignore"):
            np.reciprocal(out.depth_m, out=out.depth_m)  # 1 / 0 (nothing drawn) = inf


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
