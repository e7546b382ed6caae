"""The simulation's renderer as the training data's view source (top floor: it knows both the
simulation and :mod:`training`, which never imports the simulation)."""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from training.data import Geometry, SetSpec


@dataclasses.dataclass
class SimulationViews:
    """Labelled views of ``scenario_path`` (its site, room and robot) from
    :class:`simulation.dataset.SampleGenerator`; ``robot_model`` / ``robot_mesh``: the robot
    (None mesh: the built-in HSR-like one). Picklable: render processes rebuild the generators
    from the path."""

    scenario_path: str
    robot_model: Any
    robot_mesh: Any = None

    def renderer(self, spec: SetSpec, geometry: Geometry) -> Callable[[int], Any]:
        from simulation.dataset import SampleGenerator
        from simulation.scenario import load_scenario

        scenario = load_scenario(Path(self.scenario_path))
        return SampleGenerator(scenario, spec.mode, seed=spec.seed, width=geometry.frame_w,
                               height=geometry.frame_h, robot_mesh=self.robot_mesh,
                               robot_model=self.robot_model)

    def augment(self, image_rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        from simulation.image_effects import augment

        return augment(image_rgb, rng)

    def identity(self) -> dict[str, Any]:
        digest = hashlib.sha256()
        digest.update(np.ascontiguousarray(self.robot_model.keypoints_base_m,
                                           np.float64).tobytes())
        if self.robot_mesh is not None:
            digest.update(np.ascontiguousarray(self.robot_mesh.vertices, np.float64).tobytes())
        return {"scenario": Path(self.scenario_path).name,
                "robot_model": self.robot_model.name,
                "keypoint_names": list(self.robot_model.keypoint_names),
                "robot_mesh": "built-in" if self.robot_mesh is None else "custom",
                "fingerprint": digest.hexdigest()[:16]}
