"""rgbd-calib: extrinsic calibration of multi-camera RGB-D rigs with a double-sided ArUco board."""

__version__ = "0.1.0"
