"""Loop closing for monocular SLAM: place recognition (``places``), Sim(3) from 3D-3D matches
(``sim3``), pose-graph optimisation in Sim(3) (``pose_graph``), and the whole closing (``closing``)."""
