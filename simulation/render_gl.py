"""Headless OpenGL rendering of a :class:`~simulation.mesh.Scene` through a calibrated camera.

The only module of the project that imports moderngl (imported lazily, so importing this module
never needs it). One draw pass with three render targets (RGBA8 colour; R32UI
``instance_id << 8 | class_id``, exact integers; R32F 1 / z, perspective-exact) yields, for
every pixel of the image *as the real, distorted lens sees it*:

- ``color_rgb`` (H, W, 3) uint8: albedo (× texture) × (ambient + (1 - ambient) · max(0, n·l)),
  lit per vertex and two-sided (a face seen from behind is lit with its normal flipped); the
  scene may colour the light, add a fill light and a specular highlight
  (:class:`~simulation.mesh.Scene`);
- ``depth_m`` (H, W) float32: z of the surface point in the camera optical frame, metres,
  ``np.inf`` where nothing was drawn;
- ``instance_id`` / ``class_id`` (H, W) int32: exact (never interpolated), 0 where nothing (or
  an object with id 0) was drawn. :class:`~simulation.mesh.SceneObject` keeps instance ids
  below 2**24 and class ids below 256, which the packing relies on.

Camera model (:mod:`simulation.lens`): the OpenGL projection is built from the intrinsics in
the OpenCV convention, so a vertex lands exactly where ``cv2.projectPoints`` puts it and a pixel
is covered when its centre lies inside the projected triangle. The GL window's first row is the
image's top row, so targets are read back without flipping. With lens distortion the scene is
rendered undistorted through an internal pinhole camera, then warped to the distorted image with
the camera's :class:`~simulation.lens.LensMap` and ``cv2.remap`` (colour: bilinear; depth and
ids: nearest, so label edges sit within half a pixel of the exact ones; exact near the image
centre). Pixels of a lens model that have no undistorted preimage stay empty.

Closed, outward-oriented parts of meshes (:func:`simulation.mesh.closed_outward_faces`) are
drawn with back faces culled while the camera is outside their bounding box (same image, half the
rasterization work on llvmpipe). The static part of a scene (``Scene.static_objects``: the
site's floor, walls and furniture) is drawn once per camera and kept; later frames copy it back,
draw the other objects on top and read back and remap only the image regions those can reach
(same image; see :class:`Renderer`). The GL objects behind this are in
:mod:`simulation.gl_resources`, the per-stage timing in :mod:`simulation.render_stages`.

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

from core.camera import CameraModel
from protocol.errors import SmartedgeError
from simulation.gl_resources import Draw, Frame, GpuMesh, ShaderProgram, Targets
from simulation.lens import (
    DEFAULT_FAR_M,
    DEFAULT_NEAR_M,
    LensMap,
    image_region,
    lens_map,
    projection_matrix,
)
from simulation.mesh import Mesh, Scene, closed_outward_faces_many
from simulation.render_stages import StageClock, StageTimes

if TYPE_CHECKING:
    import moderngl

log = logging.getLogger(__name__)

#: Debian packages that provide headless EGL on Mesa (software llvmpipe or a GPU driver).
EGL_DEBIAN_PACKAGES: Final = "libegl1 libegl-mesa0 libgl1-mesa-dri libgl1"
#: Lens maps kept per renderer (randomized training cameras would otherwise pile up).
LENS_MAP_CACHE_SIZE: Final = 16
#: Memory for kept renders of scenes' static objects per renderer, bytes (16 bytes per pixel of
#: the internal render: ~7 MB per 848x480 camera, so the paper lab's four cameras fit many times)
STATIC_CACHE_BYTES: Final = 128 * 2**20


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


@dataclasses.dataclass
class _KeptStatic:
    """The render of a scene's static objects through one camera: the framebuffer state
    (``targets``, copied back before the other objects are drawn), the image it gives
    (``out``) and the static objects themselves (referenced so that the ids in the cache key
    are not re-used by other objects)."""

    targets: Targets
    out: RenderOutput
    objects: tuple[Any, ...]


#: The 12 edges of a box as pairs of corner indices (corner i has bit k set: max along axis k).
_BOX_EDGES: Final = np.array([(i, i | 1 << k) for i in range(8) for k in range(3)
                              if not i & 1 << k])


class Renderer:
    """Renders scenes into ``width`` x ``height`` images; one GL context per renderer.

    Re-usable across frames and cameras of that size: GPU buffers are cached per :class:`Mesh`
    object (a static scene is uploaded once; a mesh's buffers are freed after the mesh is
    garbage-collected), lens maps per (K, dist, size), and one framebuffer serves every
    internal render size (grown when a lens needs a larger one). A scene's static objects
    (:attr:`simulation.mesh.Scene.static_objects`) are drawn once per camera and kept (up to
    :data:`STATIC_CACHE_BYTES`); later frames draw only the other objects on top and remap only
    the image regions those can reach, with the same result. Closed, outward-oriented parts
    of meshes (:func:`simulation.mesh.closed_outward_faces`) are drawn with back faces culled
    while the camera is outside their bounding box. Not thread-safe: use one renderer per
    thread (or one process per core, see :class:`simulation.dataset.SamplePool`).

    ``times``: when set, every render adds its stages to it (see
    :class:`simulation.render_stages.StageTimes`).
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
            self._programs = (ShaderProgram(self.ctx, textured=False),
                              ShaderProgram(self.ctx, textured=True))
            # moderngl reads the info strings once, on first use: with the context current
            self._gl_renderer = str(self.ctx.info.get("GL_RENDERER", "?"))
        self._meshes: dict[int, GpuMesh] = {}
        self._dead_meshes: list[int] = []
        self._lens_maps: collections.OrderedDict[tuple[bytes, bytes, int, int], LensMap] = (
            collections.OrderedDict()
        )
        self._targets: Targets | None = None
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
        :func:`simulation.mesh.closed_outward_faces_many` for all of them."""
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

    def _create_gpu_mesh(self, mesh: Mesh, closed: np.ndarray) -> GpuMesh:
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
        return GpuMesh(ref, prog, vbo, ibo, vao, texture, num_closed, len(faces),
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

    def _targets_for(self, width: int, height: int) -> Targets:
        t = self._targets
        if t is None or not t.fits(width, height):
            capacity = (width, height) if t is None else (max(width, t.capacity[0]),
                                                          max(height, t.capacity[1]))
            if t is not None:
                t.release()
            self._release_static()  # kept renders are copied whole: same size only
            t = self._targets = Targets(self.ctx, capacity)
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
                             frame: Frame, t: Targets, out: RenderOutput,
                             clock: StageClock) -> None:
        """Draw a scene with static objects: their render (all three targets and the depth
        buffer) is copied from the cache, drawn once per camera; the other objects are drawn
        on top (the same draws in the same order as one pass); only the image regions they can
        reach are read back and remapped, the rest of the image is the kept one."""
        viewport = (0, 0, *lm.render_size)
        static = scene.objects[:scene.static_objects]
        key = (camera.K.tobytes(), camera.dist.tobytes(), camera.T_cam_world.tobytes(),
               (camera.width, camera.height), tuple(map(id, static)), frame.light_cam,
               frame.ambient, frame.background, frame.lighting)
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
        regions = [image_region(lm, rect, self.width, self.height) for rect in rects]
        if frame.dynamic_rects is None or any(r is None for r in regions):
            self._read_back(t, lm, frame.background, out, clock)  # not bounded: everything
            return
        self._read_back_regions(t, lm, frame.background, kept.out,
                                [r for r in regions if r is not None], out, clock)

    def _frame(self, scene: Scene, camera: CameraModel, lm: LensMap) -> Frame:
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
        draws: list[Draw] = []
        if objects:
            gms = [self._meshes[id(obj.mesh)] for obj in objects]
            T_world_obj = np.stack([obj.T_world_object for obj in objects])
            T_cam_obj = camera.T_cam_world @ T_world_obj
            # GLSL mat3 is column-major: writing inv(R) row-major uploads inv(R).T.
            normal = np.ascontiguousarray(np.linalg.inv(T_cam_obj[:, :3, :3]), np.float32)
            cam_obj = np.ascontiguousarray(T_cam_obj.transpose(0, 2, 1), np.float32)
            outside = self._outside_boxes(gms, T_world_obj, camera.position_world)
            draws = [Draw(gm, cam_obj[k].tobytes(), normal[k].tobytes(),
                           int(obj.instance_id), int(obj.class_id), bool(outside[k]))
                     for k, (gm, obj) in enumerate(zip(gms, objects, strict=True))]
        rects = None
        if num_static:
            rects = self._dynamic_rects(gms[num_static:], T_cam_obj[num_static:], lm)
        bg = tuple(float(c) for c in scene.background_rgb)
        fill = camera.T_cam_world[:3, :3] @ np.asarray(scene.fill_dir_world, np.float64)
        fill_norm = float(np.linalg.norm(fill))
        fill = fill / fill_norm if fill_norm > 0 else np.zeros(3)
        lighting = (*map(float, scene.light_rgb), *map(float, fill), *map(float, scene.fill_rgb),
                    float(scene.specular), float(scene.shininess))
        return Frame(proj, light_cam, float(scene.ambient), (bg[0], bg[1], bg[2]), draws,
                      num_static, rects, lighting)

    def _dynamic_rects(self, gms: Sequence[GpuMesh], T_cam_obj: np.ndarray, lm: LensMap
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

    def _issue(self, frame: Frame, viewport: tuple[int, int, int, int],
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
            lit = frame.lighting
            prog.light_rgb.value, prog.fill.value = lit[0:3], lit[3:6]
            prog.fill_rgb.value = lit[6:9]
            prog.specular.value, prog.shininess.value = lit[9], lit[10]
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
            t = Targets(self.ctx, (cols * cw, rows * ch))
            kept: list[Targets | None] = [None] * len(frames)
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
                            kept[j] = Targets(self.ctx, t.capacity, host=False)
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

    def _keep_static(self, key: tuple[Any, ...], objects: Sequence[Any], t: Targets,
                     out: RenderOutput) -> _KeptStatic:
        """Copy the framebuffer (the static objects just drawn) into the cache under ``key``,
        with ``out``, their image; the least recently used renders go when
        :data:`STATIC_CACHE_BYTES` would be exceeded."""
        cap_w, cap_h = t.capacity
        limit = max(1, STATIC_CACHE_BYTES // (16 * cap_w * cap_h + 15 * out.color_rgb.size // 3))
        while len(self._static) >= limit:
            _, old = self._static.popitem(last=False)
            old.targets.release()
        kept = _KeptStatic(Targets(self.ctx, t.capacity, host=False), out, tuple(objects))
        self.ctx.copy_framebuffer(kept.targets.fbo, t.fbo)
        self._static[key] = kept
        return kept

    def _read_back_regions(self, t: Targets, lm: LensMap, bg: tuple[float, float, float],
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

    def _read_back_region(self, t: Targets, lm: LensMap, bg: tuple[float, float, float],
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

    def _outside_boxes(self, gms: Sequence[GpuMesh], T_world_obj: np.ndarray,
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

    def _read_back(self, t: Targets, lm: LensMap, bg: tuple[float, float, float],
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
