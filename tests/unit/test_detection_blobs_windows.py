"""IR blob detection, its components measured by the compiled kernel, cross-checked against a plain reference
that measures each component with OpenCV in a window of its own (the border filled by ``cv2.drawContours``, the
rim by ``cv2.dilate``, ``cv2.moments``, ``cv2.arcLength``, ``cv2.contourArea``, ``cv2.convexHull``) and splits
a merged or occluded one there: the same blobs in the same order, the same numbers (see ``assert_same``), on
``ir_rig`` frames and on hard images (merged and cut discs, discs over the border, salt noise, a ring with a
spot in its hole, a large disc among small ones, mono16)."""

import math

import cv2
import numpy as np
import pytest

from services.detection.blobs.bright import (
    BACKGROUND_STRIDE,
    BlobFlag,
    Blobs,
    IrBlobParams,
    ShapeParams,
    detect_ir_blobs,
    grid_median,
    moment_shape,
    shape_flags,
)
from services.detection.blobs.split import split_two_discs
from services.synthetic import make_scene
from tests.blob_images import disc_image

PAD = 2
EXACT = ("centroids", "area", "radius", "perimeter", "circularity", "flags")


def reference_blobs(image: np.ndarray, params: IrBlobParams, shape: ShapeParams) -> Blobs:
    """The IR blobs of ``image`` one component at a time, each measured in a window of its own."""
    height, width = image.shape
    binary = cv2.compare(image, params.threshold, cv2.CMP_GT)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    background = (float(np.median(image[::BACKGROUND_STRIDE, ::BACKGROUND_STRIDE]))
                  if params.background is None else params.background)
    rows = []
    for contour in contours:
        x, y, w, h = cv2.boundingRect(contour)
        if w * h < shape.min_area:
            continue
        x0, y0, x1, y1 = max(x - PAD, 0), max(y - PAD, 0), min(x + w + PAD, width), min(y + h + PAD, height)
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.drawContours(mask, [contour], 0, 255, cv2.FILLED, offset=(-x0, -y0))
        area = float(cv2.countNonZero(mask))
        radius = math.sqrt(area / math.pi)
        if not (shape.min_area <= area <= shape.max_area and params.min_radius <= radius <= params.max_radius):
            continue
        perimeter = cv2.arcLength(contour, True)
        polygon_area = cv2.contourArea(contour)
        square = perimeter * perimeter  # rounded once (Python's ** calls the C library's pow)
        circularity = min(4.0 * math.pi * polygon_area / square, 1.0) if perimeter > 0 else 0.0
        if circularity < shape.min_circularity:
            continue
        others = (binary[y0:y1, x0:x1] > 0) & (mask == 0)
        rim = (cv2.dilate(mask, np.ones((3, 3), np.uint8)) > 0) & ~others
        levels = image[y0:y1, x0:x1].astype(np.float32) - np.float32(background)
        weights = np.where(rim, np.maximum(levels, np.float32(0.0)), np.float32(0.0))
        moments = cv2.moments(weights)
        if moments["m00"] <= 0.0:
            continue
        centroid, axis, roundness = moment_shape(moments)
        hull_area = cv2.contourArea(cv2.convexHull(contour))
        solidity = min(polygon_area / hull_area, 1.0) if hull_area > 0 else 1.0
        flags = shape_flags(weights, centroid, axis, roundness < shape.min_roundness
                            or solidity < params.min_solidity, shape.waist_depth)
        if x == 0 or y == 0 or x + w == width or y + h == height:
            flags |= BlobFlag.CLIPPED
        rows.append((x0 + centroid[0], y0 + centroid[1], area, radius, perimeter, circularity,
                     roundness * solidity, int(flags)))
        if flags & (BlobFlag.MERGED | BlobFlag.OCCLUDED) and (discs := split_two_discs(weights, centroid, axis)):
            for (cx, cy), r in zip(discs.centres, discs.radii, strict=True):
                rows.append((x0 + cx, y0 + cy, math.pi * r * r, r, 2.0 * math.pi * r, 1.0, 1.0 - discs.rms,
                             int(BlobFlag.SPLIT | (flags & BlobFlag.CLIPPED))))
    return Blobs.from_rows(rows)


def hard_images() -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    images = []
    for _ in range(12):
        discs = [(rng.uniform(-5, 165), rng.uniform(-5, 125), rng.uniform(0.5, 9)) for _ in range(rng.integers(1, 25))]
        image = disc_image(discs, background=12)
        images += [image, np.where(rng.random(image.shape) < 0.01, 255, image).astype(np.uint8)]
    ring = np.full((60, 70), 12, np.uint8)
    ring[10:40, 10:40], ring[15:35, 15:35], ring[20:25, 20:25] = 200, 12, 200
    ring[44:60, 50:70] = 230
    images += [ring, np.zeros((30, 30), np.uint8), np.full((30, 30), 200, np.uint8)]
    return images


def scene_images() -> list[np.ndarray]:
    images = []
    for options in ({"body_count": 3}, {"body_count": 4, "occlusion_rate": 1.0, "sphere_radius": 0.02}):
        scene = make_scene("ir_rig", **options)
        images += [scene.render(i).images[camera.name] for i in range(0, 240, 12) for camera in scene.cameras]
    return images


def assert_same(found: Blobs, expected: Blobs) -> None:
    """Bit for bit but the quality (second moments summed in another order than OpenCV's) and the discs split
    off a blob (fitted from those moments' axis): those to 1e-9 relative."""
    assert len(found) == len(expected)
    np.testing.assert_array_equal(found.flags, expected.flags)
    whole = (found.flags & BlobFlag.SPLIT) == 0
    for name in EXACT:
        np.testing.assert_array_equal(getattr(found, name)[whole], getattr(expected, name)[whole], err_msg=name)
        np.testing.assert_allclose(getattr(found, name)[~whole], getattr(expected, name)[~whole], rtol=1e-9,
                                   err_msg=name)
    np.testing.assert_allclose(found.quality, expected.quality, rtol=1e-9, atol=1e-6)
    assert found.flags.dtype == np.uint8


SETTINGS = [(IrBlobParams(), ShapeParams()),
            (IrBlobParams(background=10.3, min_radius=1.0, max_radius=6.0),
             ShapeParams(min_area=0.0, min_circularity=0.0, min_roundness=0.95))]


@pytest.mark.parametrize(("params", "shape"), SETTINGS)
def test_scene_frames_give_the_reference_blobs(params, shape):
    images = scene_images()
    assert sum(len(detect_ir_blobs(image, params, shape)) for image in images) >= 5 * len(images)
    for image in images:
        assert_same(detect_ir_blobs(image, params, shape), reference_blobs(image, params, shape))


@pytest.mark.parametrize(("params", "shape"), SETTINGS)
def test_hard_images_give_the_reference_blobs(params, shape):
    flags = 0
    for image in hard_images():
        for pixels, scaled in ((image, params), (image.astype(np.uint16) * 257,
                                                  params.model_copy(update={"threshold": params.threshold * 257}))):
            found = detect_ir_blobs(pixels, scaled, shape)
            assert_same(found, reference_blobs(pixels, scaled, shape))
            flags |= int(np.bitwise_or.reduce(found.flags, initial=0))
    assert flags == BlobFlag.MERGED | BlobFlag.OCCLUDED | BlobFlag.CLIPPED | BlobFlag.SPLIT


@pytest.mark.parametrize("size", [(48, 64), (49, 63), (7, 9)])
def test_the_grid_median_is_numpys(size):
    image = np.random.default_rng(sum(size)).integers(0, 255, size, dtype=np.uint8)
    assert grid_median(image) == float(np.median(image[::BACKGROUND_STRIDE, ::BACKGROUND_STRIDE]))


def test_a_large_blob_among_small_ones_gives_the_reference_blobs():
    rng = np.random.default_rng(11)
    discs = [(300.0, 200.0, 45.0)] + [(rng.uniform(10, 630), rng.uniform(300, 470), rng.uniform(1.5, 3.0))
                                      for _ in range(60)]
    image = disc_image(discs, (480, 640), background=12)
    found = detect_ir_blobs(image)
    assert np.max(found.area) > 6000
    assert_same(found, reference_blobs(image, IrBlobParams(), ShapeParams()))


def test_an_image_given_as_a_view_or_in_fortran_order_gives_the_blobs_of_its_copy():
    """The kernel takes C-ordered images; any other layout is copied to one first, never measured as it is."""
    image = scene_images()[0]
    expected = detect_ir_blobs(np.ascontiguousarray(image[:, 40:600]))
    assert len(expected) >= 5
    for layout in (image[:, 40:600], np.asfortranarray(image[:, 40:600])):
        assert not layout.flags.c_contiguous
        assert_same(detect_ir_blobs(layout), expected)
