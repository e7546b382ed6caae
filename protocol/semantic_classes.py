"""The indoor semantic class legend: names, ids and display colours (numpy only).

Ids are the positions in :data:`SEMANTIC_CLASSES`. One numbering for everything semantic: the
simulation's per-pixel class images (``simulation.mesh.CLASSES`` is this tuple), the
segmentation network's outputs, the ``class_ids`` of :class:`protocol.messages.SemanticCloud`
and the map's classes. Id 0 (``unlabeled``) is what the renderer writes where nothing was drawn.
"""

from __future__ import annotations

from typing import Final

import numpy as np

#: Class names in id order (a reduced ADE20K-like indoor set).
SEMANTIC_CLASSES: Final[tuple[str, ...]] = (
    "unlabeled", "floor", "wall", "ceiling", "door", "table", "chair", "shelf", "cabinet",
    "box", "obstacle", "person", "robot", "distractor",
)
#: Class name → id.
SEMANTIC_CLASS_ID: Final[dict[str, int]] = {name: i for i, name in enumerate(SEMANTIC_CLASSES)}
NUM_SEMANTIC_CLASSES: Final[int] = len(SEMANTIC_CLASSES)

#: (NUM_SEMANTIC_CLASSES, 3) uint8 RGB display colour per class id.
SEMANTIC_CLASS_COLORS: Final[np.ndarray] = np.array(
    [
        (0, 0, 0),        # unlabeled
        (140, 120, 90),   # floor
        (180, 180, 170),  # wall
        (220, 220, 255),  # ceiling
        (8, 255, 51),     # door
        (255, 6, 82),     # table
        (204, 70, 3),     # chair
        (0, 160, 160),    # shelf
        (224, 5, 255),    # cabinet
        (255, 184, 6),    # box
        (120, 120, 70),   # obstacle
        (150, 5, 61),     # person
        (0, 102, 200),    # robot
        (255, 255, 0),    # distractor
    ],
    dtype=np.uint8,
)
SEMANTIC_CLASS_COLORS.setflags(write=False)

#: RGB of voxels without semantic information (prior geometry only).
NO_SEMANTICS_COLOR: Final[tuple[int, int, int]] = (128, 128, 128)


def class_colors(num_classes: int) -> np.ndarray:
    """(num_classes, 3) uint8 RGB colours: the legend's for its ids, a fixed pseudo-random
    palette for ids beyond it."""
    if num_classes <= NUM_SEMANTIC_CLASSES:
        return SEMANTIC_CLASS_COLORS[:num_classes].copy()
    extra = np.random.default_rng(13).integers(
        32, 256, size=(num_classes - NUM_SEMANTIC_CLASSES, 3)
    )
    return np.concatenate([SEMANTIC_CLASS_COLORS, extra.astype(np.uint8)])
