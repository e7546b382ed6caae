"""Camera calibration, transport-free: the ChArUco board and its detection (``board``),
intrinsics from board views (``intrinsics``), every camera's pose from board sightings solved
jointly (``board_extrinsics``), and every camera's pose in the robot's map frame with the robot
itself as the target (``robot_target``). The ``smartedge calibrate`` commands
(:mod:`smartedge.calibrate`) read images, recordings or the bus and call these."""
