"""Monocular SLAM from one calibrated camera: camera tracking relative to its first keyframe while a
map of 3D points is built, in one process (``system.SlamSystem``).

Two-view geometry (``two_view``) and the initialisation that decides from two frames whether, and
how, a map can be started (``initialisation``); ORB features (``features``), descriptor matching
(``matching``) and search by projection (``projection``); the map of keyframes and points
(``map``: its database, covisibility graph, point culling, and its copy in the mapping process);
tracking of each frame (``frontend``); local mapping of each keyframe (``mapping``); the
optimisation both need (``optimisation``: local bundle adjustment by Ceres through pycolmap, robust
pose-only refinement); the tuning numbers (``settings``); relocalisation in the whole map after a
lost frame (``relocalisation``); map files, to localise later runs in a saved map (``map.file``).
"""
