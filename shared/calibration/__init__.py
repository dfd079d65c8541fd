"""Site calibration: camera intrinsics from board images, sensor poses from surveyed points (OpenCV,
SciPy); `rmmdet calibrate` writes the results into a site file."""
