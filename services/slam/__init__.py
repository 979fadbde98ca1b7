"""Monocular SLAM from one calibrated camera: camera tracking relative to its first keyframe while a
map of 3D points is built.

The room will hold the frontend (tracking each frame against the map), the map (keyframes, points,
covisibility), relocalisation and a node. So far it holds the start of a map: two-view geometry
(``two_view``) and the initialisation that decides from two frames whether, and how, a map can be
started (``initialisation``); and the optimisation the map and tracking need (``optimisation``:
local bundle adjustment by Ceres through pycolmap, robust pose-only refinement).
"""
