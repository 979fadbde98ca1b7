"""Calibration files and methods: ROS camera_info YAML in and out, intrinsic calibration from
chessboard and ChArUco photos."""
