"""The stereo tracker's messages and nodes' pure parts: blobs per frame, rig and bodies, poses and covariances."""

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from protocol import Header, Pose, decode, encode
from protocol.detections import BLOB_CLIPPED, BLOB_MERGED, BLOB_OCCLUDED, BLOB_SPLIT, Blobs
from protocol.mocap import Points3D
from protocol.poses import PoseQuality
from services.calibration.rig import Rig, write_rig
from services.convert import matrix_from_transform
from services.detection.blobs.bright import BlobFlag
from services.detection.blobs.node import Params as BlobParams
from services.detection.blobs.node import UnusableFrame, as_message, detector
from services.estimation.bodies.correspondence import triangulate_blobs
from services.estimation.bodies.file import check_bodies, save_bodies
from services.estimation.bodies.node import (
    Params,
    body_poses,
    load,
    pixels,
    point_arrays,
    points_message,
)
from services.estimation.bodies.rigid import match_bodies
from services.geometry.absolute_orientation import child_frame_covariance
from services.launcher.tracker import Tracker
from services.synthetic import make_scene
from services.synthetic.ir_rig import LAYOUTS


def disc_image(dtype=np.uint8, scale: float = 1.0) -> np.ndarray:
    image = np.full((60, 80), 10, np.float64)
    yy, xx = np.mgrid[:60, :80]
    image[(xx - 30.3) ** 2 + (yy - 20.6) ** 2 <= 16] = 220
    image[(xx - 60.0) ** 2 + (yy - 40.0) ** 2 <= 9] = 220
    return (image * scale).astype(dtype)


def test_blob_flag_bits_on_the_wire_are_the_detectors():
    assert (BLOB_MERGED, BLOB_OCCLUDED, BLOB_CLIPPED, BLOB_SPLIT) == (BlobFlag.MERGED, BlobFlag.OCCLUDED,
                                                                      BlobFlag.CLIPPED, BlobFlag.SPLIT)


def test_blobs_and_points_travel_unchanged_and_refuse_misaligned_rows():
    blobs = Blobs(header=Header(stamp_ns=3, frame_id="cam1", seq=9), method="log",
                  centroids=np.array([[1.25, 2.5], [3.0, 4.0]]), areas=np.array([12, 20], np.float32),
                  radii=np.array([2, 2.5], np.float32), quality=np.array([0.9, 0.4], np.float32),
                  flags=np.array([0, BLOB_MERGED], np.uint8))
    assert decode(encode(blobs)) == blobs
    points = Points3D(header=Header(stamp_ns=3, frame_id="world", seq=9), bodies=("wand",),
                      points=np.eye(3), residual_px=np.ones(3, np.float32), views=np.full(3, 2, np.uint8),
                      covariances=np.zeros((3, 3, 3)), body=np.array([0, -1, 0], np.int32))
    assert decode(encode(points)) == points
    with pytest.raises(ValueError, match="same number of rows"):
        Blobs(header=blobs.header, centroids=np.zeros((2, 2)), areas=np.zeros(1, np.float32),
              radii=np.zeros(2, np.float32), quality=np.zeros(2, np.float32), flags=np.zeros(2, np.uint8))
    with pytest.raises(ValueError, match="index one of the 1 bodies"):
        Points3D(header=points.header, bodies=("wand",), points=points.points, residual_px=points.residual_px,
                 views=points.views, covariances=points.covariances, body=np.array([0, 1, -1], np.int32))


def test_a_pose_carries_its_fit_residual_and_a_version_1_pose_still_decodes():
    pose = Pose(header=Header(stamp_ns=1, frame_id="world"), child_frame_id="body/tool",
                quality=PoseQuality(inliers=4, residual_rms_m=0.0002))
    assert decode(encode(pose)) == pose
    older = json.loads(encode(pose))
    older["version"] = 1
    del older["quality"]["residual_rms_m"]
    assert decode(json.dumps(older).encode()).quality.residual_rms_m is None


@pytest.mark.parametrize("method", ["ir", "log"])
def test_mono8_mono16_and_colour_frames_give_the_same_blobs(method):
    find = detector(BlobParams(method=method))
    mono = find(disc_image())
    assert len(mono) == 2
    wide = find(disc_image(np.uint16, 257.0))
    colour = find(cv2.cvtColor(disc_image(), cv2.COLOR_GRAY2BGR))
    for other in (wide, colour):
        np.testing.assert_allclose(other.centroids, mono.centroids, atol=0.02)
    expected = [[30.3, 20.6], [60.0, 40.0]]
    order = np.argsort(mono.centroids[:, 0])
    np.testing.assert_allclose(mono.centroids[order], expected, atol=0.15)


def test_the_colour_method_finds_its_hue_and_says_why_it_cannot_use_a_mono_frame():
    image = np.zeros((60, 80, 3), np.uint8)
    cv2.circle(image, (30, 20), 5, (0, 0, 230), -1)   # red
    cv2.circle(image, (60, 40), 5, (230, 0, 0), -1)   # blue
    found = detector(BlobParams(method="colour", hue_deg=0.0))(image)
    assert len(found) == 1 and np.allclose(found.centroids[0], (30, 20), atol=0.1)
    with pytest.raises(UnusableFrame, match="colour method needs bgr8 frames, not mono16"):
        detector(BlobParams(method="colour"))(disc_image(np.uint16))


def test_child_frame_covariance_matches_sampled_perturbations():
    rng = np.random.default_rng(4)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    T[:3, 3] = (0.2, -0.1, 2.0)
    L = rng.normal(size=(6, 6)) * 1e-3
    world = L @ L.T  # (dtheta, dt), world axes
    draws = rng.multivariate_normal(np.zeros(6), world, 20000)
    R = T[:3, :3]
    rho = draws[:, 3:] @ R  # R^T dt, row-wise
    phi = np.array([Rotation.from_matrix(R.T @ Rotation.from_rotvec(d).as_matrix() @ R).as_rotvec()
                    for d in draws[:, :3]])
    sampled = np.cov(np.hstack([rho, phi]).T)
    np.testing.assert_allclose(child_frame_covariance(world, T), sampled, atol=0.05 * np.abs(world).max())


def test_rig_and_bodies_files_are_checked_before_start(tmp_path):
    with pytest.raises(ValueError, match="no/such/rig.yaml: cannot read"):
        load(Params(rig_file=tmp_path / "no/such/rig.yaml"))
    scene = make_scene("ir_rig", camera_count=3)
    write_rig(tmp_path / "rig.yaml", Rig("bar", scene.cameras[:2]))
    with pytest.raises(ValueError, match=r"no camera cam2 in the rig \(it has cam0, cam1\)"):
        load(Params(cameras=("cam0", "cam1", "cam2"), rig_file=tmp_path / "rig.yaml"))
    rig, bodies = load(Params(rig_file=tmp_path / "rig.yaml"))
    assert rig is not None and rig.names == ("cam0", "cam1")
    assert bodies == {}  # no bodies file: no body is looked for
    assert not check_bodies(LAYOUTS)
    save_bodies(tmp_path / "bodies.yaml", {"wand": LAYOUTS["wand"]})
    assert list(load(Params(bodies=tmp_path / "bodies.yaml"))[1]) == ["wand"]
    (tmp_path / "bad.yaml").write_text("bodies: []\n")
    with pytest.raises(ValueError, match="bad.yaml: bodies: must be a non-empty list"):
        load(Params(bodies=tmp_path / "bad.yaml"))


def test_the_stereo_template_gives_a_blobs_node_per_camera_and_one_node_for_the_rig():
    stereo = Tracker.load("stereo")
    flags = stereo.flags({})
    assert "--cameras" not in {f.option for f in flags}
    nodes = stereo.expand(["cam0", "cam1", "cam2"], {"threshold": "80"}, flags)
    assert set(nodes) == {"blobs-cam0", "blobs-cam1", "blobs-cam2", "bodies"}
    assert nodes["blobs-cam2"].params == {"camera": "cam2", "threshold": "80"}
    assert nodes["bodies"].kind == "rigid_bodies" and nodes["bodies"].params == {"cameras": ["cam0", "cam1", "cam2"]}


def test_blobs_through_the_wire_give_body_poses_within_half_a_millimetre():
    """The nodes' per-frame path in-process, scored against the scene's truth."""
    scene = make_scene("ir_rig")
    find = detector(BlobParams())
    errors, found = [], 0
    for index in range(0, 40, 2):
        images, _ = scene.draw(index)
        header = Header(stamp_ns=index, frame_id="world", seq=index)
        sent = [decode(encode(as_message(header, "ir", find(images[c.name])))) for c in scene.cameras]
        points = triangulate_blobs(scene.cameras, [pixels(b, flagged=False) for b in sent])
        matching = match_bodies(LAYOUTS, *point_arrays(points))
        labelled = points_message(header, points, list(LAYOUTS), matching)
        assert np.count_nonzero(labelled.body >= 0) == sum(m.spheres_used for m in matching.bodies.values())
        truth = scene.body_poses(index)
        for pose in body_poses(header, matching):
            name = pose.child_frame_id.removeprefix("body/")
            errors.append(np.linalg.norm(matrix_from_transform(pose.transform)[:3, 3] - truth[name][:3, 3]))
            assert pose.covariance is not None and pose.quality.inliers >= 3
            found += 1
    assert found >= 40  # of 60 body-frames; the rest have spheres merged in one of the two cameras
    assert np.median(errors) < 0.0005 and max(errors) < 0.003
