"""Pose estimation algorithms (marker poses, marker maps, calibration) and their node; pure numpy/OpenCV."""
