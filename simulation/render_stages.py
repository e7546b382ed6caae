"""Wall-clock time per render stage, summed over images: the profiling aid of the renderer,
the training-set generator and ``smartedge bench render``."""

from __future__ import annotations

import time
from typing import Final

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
