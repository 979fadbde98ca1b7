"""Detection in images, one package per kind of feature: ``markers`` (ArUco / AprilTag), ``blobs`` (IR threshold,
LoG scale space, HSV colour) and ``keypoints`` (corners and descriptors); algorithms and their nodes."""
