"""lidar_cam_calib: extrinsic calibration of range sensors and cameras (ROS 2 Jazzy)."""
__version__ = "0.1.0"
