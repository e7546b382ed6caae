"""Camera calibration, transport-free (moved out of ``backend_service``):

- ``board``: the ChArUco board: its spec, the printable image and detection of its corners;
- ``intrinsics``: one camera's intrinsics from board views (view selection, coverage, OpenCV
  calibration, the calibration files);
- ``board_extrinsics``: every camera's pose from board sightings by several cameras, solved
  jointly;
- ``robot_target``: every camera's pose in the robot's map frame, with the robot itself as
  the target;
- ``robot_problem``: the joint least-squares problem of the robot-as-target calibration
  (factors, Jacobians, normal equations);
- ``least_squares``: the one Levenberg-Marquardt loop both joint adjustments run;
- ``site_file``: writing calibrated camera poses into a site file (the one writer).

The ``smartedge calibrate`` commands (:mod:`smartedge.commands.calibrate`) read images,
recordings or the bus and call these. Imports only the ground floor of the project
(``protocol`` and ``core``).
"""
