"""Evaluation maths and trajectory file I/O (the model is evo's ``core``/``tools`` split).

``metrics``: pure numpy alignment, stamp matching and APE statistics; ``trajectory_io``: TUM
files; ``cramer_rao``: the Cramer-Rao bound of the planar pose and camera-placement planning.
"""

from __future__ import annotations
