"""``undistort_image``: OpenCV's ``cv2.undistort`` with remap tables made once per camera."""

import cv2
import numpy as np

from services.geometry.camera import _undistort_maps, intrinsics, undistort_image

K = intrinsics(640, 480, 64.0)
DIST = np.array([-0.28, 0.09, 0.0005, -0.0003, -0.01])


def test_it_gives_what_cv2_undistort_gives_for_grey_and_colour_frames():
    rng = np.random.default_rng(3)
    for shape in ((480, 640), (480, 640, 3)):
        image = rng.integers(0, 256, shape, dtype=np.uint8)
        np.testing.assert_array_equal(undistort_image(image, K, DIST), cv2.undistort(image, K, DIST))


def test_the_tables_are_made_once_per_camera_and_size():
    _undistort_maps.cache_clear()
    image = np.zeros((480, 640), np.uint8)
    for _ in range(3):
        undistort_image(image, K, DIST)
    undistort_image(np.zeros((240, 320), np.uint8), K, DIST)
    info = _undistort_maps.cache_info()
    assert (info.misses, info.hits) == (2, 2)
