"""Evaluation maths (the model is evo's ``core``/``tools`` split; the TUM trajectory files are
:mod:`core.trajectory`).

- ``metrics``: trajectory metrics: pure numpy alignment, stamp matching and APE statistics;
- ``scoring``: estimates and corrections against the simulator's truth (errors, corrections to
  the wrong robot): the one scoring the demo, the fault harness and the experiments call;
- ``cramer_rao``: the Cramer-Rao bound of the planar pose and camera-placement planning;
- ``keypoint_choice``: which keypoints on the robot's base make its heading observable;
- ``keypoints``: held-out evaluation of the deployed detector and keypoint models.

Part of the lab wing: may import every other package.
"""

from __future__ import annotations
