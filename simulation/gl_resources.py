"""The GPU-side pieces of :class:`simulation.render_gl.Renderer`: the shader program, one
mesh's buffers, the per-view draw list and the framebuffer with its host read-back buffers.

One draw pass writes three render targets (RGBA8 colour; R32UI ``instance_id << 8 | class_id``,
exact integers; R32F 1 / z, perspective-exact). The GL context is created and moderngl imported
only in :mod:`simulation.render_gl`; the classes here receive the context from it.
"""

from __future__ import annotations

import dataclasses
import weakref
from typing import Any, Final

import numpy as np

from simulation.mesh import Mesh

#: A ``moderngl.Context`` (typed loosely: only :mod:`simulation.render_gl` imports moderngl).
GLContext = Any

# Lambert shading (a key light, an optional fill light, each with a colour, and an optional
# Blinn-Phong highlight of the key light) is evaluated per vertex (Gouraud): on llvmpipe small
# triangles cost whole 4x4 pixel blocks of fragment shading, so a lean fragment shader is most
# of the speed. Meshes without a texture use a variant without the uv varying and the texture
# fetch.
_VERTEX_SHADER: Final = """
#version 330
uniform mat4 u_proj;
uniform mat4 u_cam_obj;
uniform mat3 u_normal_cam_obj;
uniform vec3 u_light_cam;
uniform float u_ambient;
uniform vec3 u_light_rgb;
uniform vec3 u_fill_cam;
uniform vec3 u_fill_rgb;
uniform float u_specular;
uniform float u_shininess;
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
    float lit = max(dot(n, u_light_cam), 0.0);
    v_color = in_color * (u_ambient + (1.0 - u_ambient) * (
        u_light_rgb * lit + u_fill_rgb * max(dot(n, u_fill_cam), 0.0)));
    if (u_specular > 0.0 && lit > 0.0) {  // Blinn-Phong highlight of the key light
        vec3 h = normalize(u_light_cam - normalize(p.xyz));
        v_color += u_specular * (1.0 - u_ambient) * u_light_rgb
            * pow(max(dot(n, h), 0.0), u_shininess);
    }
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


class ShaderProgram:
    """One shader variant and its uniforms."""

    def __init__(self, ctx: GLContext, textured: bool) -> None:
        self.textured = textured
        self.program = ctx.program(vertex_shader=_shader_variant(_VERTEX_SHADER, textured),
                                   fragment_shader=_shader_variant(_FRAGMENT_SHADER, textured))
        if textured:
            self.program["u_texture"].value = 0  # type: ignore[union-attr]
        u: Any = self.program  # moderngl types members as a union of uniform kinds
        self.proj, self.cam_obj, self.normal = u["u_proj"], u["u_cam_obj"], u["u_normal_cam_obj"]
        self.light, self.ambient = u["u_light_cam"], u["u_ambient"]
        self.light_rgb, self.fill, self.fill_rgb = (u["u_light_rgb"], u["u_fill_cam"],
                                                    u["u_fill_rgb"])
        self.specular, self.shininess = u["u_specular"], u["u_shininess"]
        self.instance_id, self.class_id = u["u_instance_id"], u["u_class_id"]
        self.attributes = ("in_position", "in_normal", "in_color") + (("in_uv",) if textured
                                                                      else ())

    def release(self) -> None:
        self.program.release()


@dataclasses.dataclass
class GpuMesh:
    ref: weakref.ref[Mesh]
    program: ShaderProgram
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
class Draw:
    """One object's draw calls in one view: uniform bytes and whether its closed parts may be
    drawn with back faces culled."""

    gm: GpuMesh
    cam_obj: bytes
    normal: bytes
    instance_id: int
    class_id: int
    cull_closed: bool


@dataclasses.dataclass(frozen=True)
class Frame:
    """Everything the draw calls of one view need."""

    proj: bytes
    light_cam: tuple[float, ...]
    ambient: float
    background: tuple[float, float, float]
    draws: list[Draw]
    #: the first ``num_static`` draws are the scene's static objects
    num_static: int = 0
    #: per other (non-static) object, the internal-render pixels (x0, y0, x1, y1), inclusive,
    #: its draws can touch (a box around its projected bounds; empty boxes left out);
    #: ``None``: not known (an object reaches behind the near plane), the whole render
    dynamic_rects: list[tuple[int, int, int, int]] | None = None
    #: key light colour (3), fill light direction in the camera frame (3) and colour (3),
    #: specular strength and exponent (see :class:`simulation.mesh.Scene`)
    lighting: tuple[float, ...] = (1.0, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 16.0)


class Targets:
    """The framebuffer of the internal render and its host-side read-back buffers.

    Allocated at a *capacity* (width, height) and drawn in its lower-left ``render_size``
    corner (viewport at the origin, so every pixel lands where a framebuffer of exactly that size
    puts it): randomized cameras, whose internal render size changes with every lens, re-use one
    framebuffer instead of allocating four render buffers per image.
    """

    def __init__(self, ctx: GLContext, capacity: tuple[int, int], *,
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
