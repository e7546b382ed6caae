"""``smartedge calibrate``: a site's calibration from what a lab has (a printed ChArUco board,
and the robot itself). One module per verb group; the algorithms live in
:mod:`backend_service.calibration`."""
