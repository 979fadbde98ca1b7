"""Detection: square fiducial markers (ArUco / AprilTag) and blobs (IR threshold, LoG scale space, HSV colour)
found in images, and the node that publishes markers."""
