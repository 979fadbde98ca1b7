"""The SLAM map: its data apart from what works on it.

World = the first keyframe's camera frame (OpenCV camera frame: x right, y down, z forward), in the
map's arbitrary monocular units.

- ``keyframe``, ``map_point``: a keyframe (pose, features, the point each keypoint observes) and a
  map point (position, observations, summary, counters);
- ``point_summary``: a point's representative descriptor, viewing direction and distance range,
  computed from its observations;
- ``database``: ``MapDatabase``, the keyframes and points under one lock, and every change to them
  that keeps observations and summaries consistent;
- ``covisibility``: ``CovisibilityGraph``, which keyframes share points, and a frame's local map;
- ``cleaner``: ``LocalMapCleaner``, the culling of recent points that failed;
- map I/O: ``sync`` keeps a copy of a database in another process in step (snapshots, the changes
  noted in a ``journal``, tracking counters); ``file`` saves a map to a file and loads it back.
"""
