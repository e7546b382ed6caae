"""The simulation glue of the top floor: what wires the simulated site (:mod:`simulation`, a
plug-in) into the services and the experiments.

- :mod:`.plugins`: registers the simulated frame sources into the edge agent and the simulated
  robot adapter into the robot bridge (``smartedge edge-agent`` / ``robot-bridge`` start here);
- :mod:`.rendered_detections`: the closed loop in simulated time (rendered frames through the
  edge's ONNX pipeline, for ``smartedge evaluate paper --detections cnn``);
- :mod:`.training_views`: rendered training views for ``smartedge train``;
- :mod:`.robot_camera`: ``smartedge robot-camera``, the simulated robot's head RGB-D camera as
  semantic clouds in ``base_link``.

Nothing is imported here, so ``smartedge edge-agent`` on an edge board loads only what it uses.
"""

from __future__ import annotations
