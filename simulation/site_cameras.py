"""What the simulated site's cameras see: images of the site rendered from each camera's *true*
pose (calibration error included) with the robot at its ground-truth pose.

Used by the live simulation (:class:`simulation.live.RenderedCameraFeed`, the demo's edge
agents) and by the paper evaluation's CNN mode (``smartedge evaluate paper --detections cnn``),
so both see the same images.

A real camera never delivers the same frame twice: photon and read noise change every pixel a
little, so averaging estimates over frames of a static robot (the paper's 5-frame average)
helps. :class:`SensorNoise` adds that per frame (zero-mean Gaussian, ``sigma_dn`` digital numbers
of 0-255, from a bank of pre-drawn noise images picked and shifted at random per frame, so it
costs an addition rather than a million random draws). The clean render of a static robot is
cached per camera, so a robot standing at a waypoint costs one render per camera.

Depth (the RGB-D cameras' aligned depth, for semantic clouds) is the renderer's camera-frame z
with :class:`DepthNoise`: a stereo camera's error grows with the square of the distance, and
nothing is measured beyond its range. The robot's head camera (:meth:`SiteCameraRenderer.
render_head`) is rendered from the robot's true pose without the robot itself in the scene.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import TYPE_CHECKING

import numpy as np

from core.camera import CameraModel
from core.geometry import se3_from_planar
from core.site import HeadCamera
from protocol.errors import UnknownIdError

if TYPE_CHECKING:
    from simulation.render_gl import Renderer, RenderOutput

log = logging.getLogger(__name__)

#: default temporal noise of the simulated cameras (digital numbers, 0-255): a D455-class colour
#: sensor in an indoor lab is around 1-3 DN
DEFAULT_SENSOR_NOISE_DN = 2.0
#: noise images drawn per image size (frames pick one at random and shift it)
NOISE_BANK_SIZE = 6


@dataclasses.dataclass(frozen=True)
class SensorNoise:
    """Per-frame sensor noise: ``sigma_dn`` (0 = noise-free images)."""

    sigma_dn: float = DEFAULT_SENSOR_NOISE_DN

    def __post_init__(self) -> None:
        if not (math.isfinite(self.sigma_dn) and self.sigma_dn >= 0.0):
            raise ValueError(f"sensor noise sigma_dn must be >= 0, got {self.sigma_dn}")


#: default depth noise: sigma_z = k z^2 with k for a D455-class stereo camera (~1 % at 4 m)
DEFAULT_DEPTH_SIGMA_PER_M = 0.0025
DEFAULT_MAX_DEPTH_M = 10.0


@dataclasses.dataclass(frozen=True)
class DepthNoise:
    """Per-frame depth noise: zero-mean Gaussian with ``sigma_z = sigma_per_m * z^2`` (metres,
    z in metres) and no depth (0) beyond ``max_depth_m``; ``sigma_per_m`` 0: exact depth."""

    sigma_per_m: float = DEFAULT_DEPTH_SIGMA_PER_M
    max_depth_m: float = DEFAULT_MAX_DEPTH_M

    def __post_init__(self) -> None:
        if not (math.isfinite(self.sigma_per_m) and self.sigma_per_m >= 0.0):
            raise ValueError(f"depth noise sigma_per_m must be >= 0, got {self.sigma_per_m}")
        if not self.max_depth_m > 0.0:
            raise ValueError(f"depth noise max_depth_m must be > 0, got {self.max_depth_m}")

    def apply(self, depth_m: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """(H, W) float32 noisy copy of ``depth_m`` (inf where nothing was drawn becomes 0,
        like a depth camera's "no data"); ``rng`` ``None``: no noise, range limit only."""
        z = np.asarray(depth_m, np.float32)
        out = np.where(np.isfinite(z) & (z <= self.max_depth_m), z, np.float32(0.0))
        if rng is not None and self.sigma_per_m > 0.0:
            noise = rng.standard_normal(out.shape, dtype=np.float32)
            out = out + noise * (np.float32(self.sigma_per_m) * out * out)
            out[out < 0.0] = 0.0
        return out.astype(np.float32, copy=False)


class SiteCameraRenderer:
    """Renders the cameras of a :class:`simulation.scenario.Scenario`.

    ``texture_seed``: the site's textures (the same seed gives the same-looking site);
    ``noise``: per-frame sensor noise; ``depth_noise``: per-frame depth noise. The GL renderer
    is created on first use, in the calling process (one per image size); not thread-safe."""

    def __init__(self, scenario: object, *, texture_seed: int = 0,
                 noise: SensorNoise | None = None,
                 depth_noise: DepthNoise | None = None) -> None:
        from simulation.detections import true_cameras
        from simulation.robot_mesh import builtin_robot_mesh
        from simulation.scenes import site_geometry

        self.scenario = scenario
        self.cameras: dict[str, CameraModel] = true_cameras(scenario)  # type: ignore[arg-type]
        robot_id = scenario.robot_id  # type: ignore[attr-defined]
        self.robot_model = scenario.site.robot_model(robot_id)  # type: ignore[attr-defined]
        self.noise = noise if noise is not None else SensorNoise()
        self.depth_noise = depth_noise if depth_noise is not None else DepthNoise()
        self._geometry = site_geometry(scenario, seed=texture_seed)
        self._robot_mesh = builtin_robot_mesh(self.robot_model)
        self._renderers: dict[tuple[int, int], object] = {}
        self._clean: dict[str, tuple[bytes, RenderOutput]] = {}
        self._noise_bank: dict[tuple[int, int], np.ndarray] = {}
        r, h = self.robot_model.footprint_radius_m, self.robot_model.height_m
        ang = np.linspace(0.0, 2.0 * np.pi, 12, endpoint=False)
        self._hull_base = np.array([[r * math.cos(a), r * math.sin(a), z]
                                    for a in ang for z in (0.0, h / 2, h)])
        #: renders done and served from the static-robot cache (for progress and benchmarks)
        self.renders = 0
        self.cache_hits = 0

    def camera(self, camera_id: str) -> CameraModel:
        try:
            return self.cameras[camera_id]
        except KeyError:
            raise UnknownIdError(f"camera {camera_id!r} is not in the simulated site; known: "
                                 f"{sorted(self.cameras)}") from None

    def robot_in_image(self, camera_id: str, robot_pose: np.ndarray) -> bool:
        """Whether any part of the robot's bounding cylinder projects into the image in front
        of the camera (a cheap test that lets callers skip images without the robot)."""
        cam = self.camera(camera_id)
        T = se3_from_planar(*(float(v) for v in robot_pose[:3]))
        pts = self._hull_base @ T[:3, :3].T + T[:3, 3]
        uv, depth = cam.project(pts)
        ok = np.all(np.isfinite(uv), axis=1) & (depth > 0.1)
        return bool(np.any(ok & cam.in_image(np.where(ok[:, None], uv, -1.0))))

    def render_clean(self, camera_id: str, robot_pose: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB noise-free image with the robot at ``robot_pose`` (x, y, theta);
        the last image per camera is reused while the pose is the same. Do not modify it."""
        return self.render_output(camera_id, robot_pose).color_rgb

    def render_output(self, camera_id: str, robot_pose: np.ndarray) -> RenderOutput:
        """The whole noise-free render (colour, depth, labels) of :meth:`render_clean`, from the
        same per-camera cache. Do not modify it."""
        pose = np.asarray(robot_pose, dtype=np.float64).reshape(-1)[:3]
        key = pose.tobytes()
        cached = self._clean.get(camera_id)
        if cached is not None and cached[0] == key:
            self.cache_hits += 1
            return cached[1]
        from simulation.scenes import site_scene

        cam = self.camera(camera_id)
        scene = site_scene(self._geometry, self._robot_mesh, pose)
        out = self._renderer(cam.width, cam.height).render(scene, cam)
        self._clean[camera_id] = (key, out)
        self.renders += 1
        return out

    def depth(self, camera_id: str, robot_pose: np.ndarray,
              rng: np.random.Generator | None = None) -> np.ndarray:
        """(H, W) float32 depth (camera-frame z, metres, 0 = none) the camera delivers with the
        robot at ``robot_pose``, aligned to its colour image, with :attr:`depth_noise`."""
        return self.depth_noise.apply(self.render_output(camera_id, robot_pose).depth_m, rng)

    def render_head(self, head: HeadCamera, robot_pose: np.ndarray,
                    camera_id: str = "head", T_base_cam: np.ndarray | None = None
                    ) -> RenderOutput:
        """What the robot's head camera sees with the robot at (true) ``robot_pose`` (x, y,
        theta in the world frame): the site without the robot itself (the camera sits inside
        its body mesh). ``T_base_cam``: the camera's pose in the base at this instant (a head
        that pans and tilts, :mod:`simulation.head`); ``None``: the fixed mounting
        ``head.T_base_cam``. Noise-free; add :meth:`add_noise` and :attr:`depth_noise` per
        frame."""
        from simulation.mesh import Scene

        pose = np.asarray(robot_pose, dtype=np.float64).reshape(-1)[:3]
        if T_base_cam is not None:
            head = dataclasses.replace(head, T_base_cam=np.asarray(T_base_cam, np.float64))
        cam = head.camera_model(camera_id, se3_from_planar(*(float(v) for v in pose)))
        scene = Scene(self._geometry.objects)
        self.renders += 1
        return self._renderer(cam.width, cam.height).render(scene, cam)

    def _renderer(self, width: int, height: int) -> Renderer:
        from simulation.render_gl import Renderer

        renderer = self._renderers.get((width, height))
        if renderer is None:
            renderer = self._renderers[(width, height)] = Renderer(width, height)
        return renderer  # type: ignore[return-value]

    def render(self, camera_id: str, robot_pose: np.ndarray,
               rng: np.random.Generator | None = None) -> np.ndarray:
        """The frame the camera delivers: :meth:`render_clean` plus this frame's sensor noise
        (drawn from ``rng``; ``None`` or ``sigma_dn`` 0: the clean image, copied)."""
        clean = self.render_clean(camera_id, robot_pose)
        if rng is None or self.noise.sigma_dn <= 0.0:
            return clean.copy()
        return self.add_noise(clean, rng)

    def add_noise(self, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``image`` plus one frame of sensor noise (a new array)."""
        h, w = image.shape[:2]
        bank = self._noise_bank.get((w, h))
        if bank is None:
            seed_rng = np.random.default_rng([w, h, 7])
            bank = np.clip(np.rint(seed_rng.normal(0.0, self.noise.sigma_dn,
                                                   (NOISE_BANK_SIZE, h, w, 3))),
                           -127, 127).astype(np.int16)
            self._noise_bank[(w, h)] = bank
        k = int(rng.integers(NOISE_BANK_SIZE))
        dy, dx = int(rng.integers(h)), int(rng.integers(w))
        noise = np.roll(bank[k], (dy, dx), axis=(0, 1))
        return np.clip(image.astype(np.int16) + noise, 0, 255).astype(np.uint8)

    def release(self) -> None:
        for r in self._renderers.values():
            r.release()  # type: ignore[attr-defined]
        self._renderers.clear()
        self._clean.clear()
