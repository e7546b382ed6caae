"""The lab wing: what a lab runs to measure, evaluate and train the system, beside the app
(:mod:`smartedge`).

- ``bench``: ``smartedge bench <what>``, the benchmarks and the fault harness;
- ``experiments``: the paper's experiments (``smartedge evaluate paper``, ``fleet``,
  ``calibration``);
- ``evaluation``: evaluation maths: trajectory metrics, the Cramer-Rao bound, keypoint scores;
- ``demo``: ``smartedge demo``, the whole system on the simulated paper site over Zenoh;
- ``evaluate``: ``smartedge evaluate``, trajectory metrics and the paper's experiments;
- ``render``: ``smartedge render``, rendered camera images of the simulated site with labels;
- ``train``: ``smartedge train``, a network trained on synthetic renders only;
- ``simulated_head``: ``smartedge sim-head``, the simulated robot's moving head as a ROS 2
  robot publishes it;
- ``launcher``: the one service launcher: a smartedge service as a process with its log,
  waited for until it listens, stopped; free ports, process memory;
- ``rendered_detections``: the closed loop in simulated time: rendered images through the
  edge's ONNX pipeline as a detection source;
- ``training_views``: the simulation's renderer as the training data's view source;
- ``coco_renders``: rendered samples as a COCO keypoints dataset with the renderer's exact labels;
- ``commands``: the lab's commands, which reach the CLI through the ``smartedge.commands``
  entry point (pyproject.toml).

May import every other package of the project; nothing outside the lab imports it.
"""
