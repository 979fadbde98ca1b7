"""Detection: square fiducial markers (ArUco / AprilTag) found in images, and the node that publishes them."""
