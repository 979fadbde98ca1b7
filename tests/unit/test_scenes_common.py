"""Every scene: registry, options validation, frame layout, determinism and random access."""

import numpy as np
import pytest

from services.synthetic import SCENES, CameraModel, SceneFrame, make_scene

NAMES = sorted(SCENES)
SMALL = {"width": 160, "height": 120}


@pytest.fixture(scope="module", params=NAMES)
def scene(request):
    return make_scene(request.param, **SMALL)


def test_registry_holds_the_four_scenes():
    assert NAMES == ["ir_rig", "markers", "pattern", "planar_target", "room"]


def test_unknown_scene_is_named_with_the_valid_ones():
    with pytest.raises(ValueError, match=r"unknown scene 'boxes'.*ir_rig, markers, pattern, planar_target, room"):
        make_scene("boxes")


@pytest.mark.parametrize("name", NAMES)
def test_unknown_option_is_named_with_the_valid_ones(name):
    with pytest.raises(ValueError, match=r"unknown option\(s\) colour .*valid options: .*blur_px.*seed"):
        make_scene(name, colour=True)


@pytest.mark.parametrize(("options", "message"), [
    ({"width": 10}, "width=10"),
    ({"height": 480.0}, "height=480.0"),
    ({"fps": 0}, "fps=0"),
    ({"fps": float("nan")}, "fps=nan"),
    ({"noise_std": -1.0}, "noise_std=-1.0"),
    ({"noise_std": "2"}, "noise_std='2'"),
    ({"blur_px": -0.5}, "blur_px=-0.5"),
    ({"exposure": 0.0}, "exposure=0.0"),
    ({"seed": -1}, "seed=-1"),
    ({"seed": True}, "seed=True"),
])
@pytest.mark.parametrize("name", NAMES)
def test_invalid_common_options_are_rejected(name, options, message):
    with pytest.raises(ValueError, match=f"option {message}"):
        make_scene(name, **options)


@pytest.mark.parametrize(("name", "options", "message"), [
    ("markers", {"dictionary": "DICT_5X5_2"}, "dictionary='DICT_5X5_2': must be one of .*DICT_4X4_50"),
    ("markers", {"dictionary": 5}, "dictionary=5"),
    ("markers", {"ids": (1, 1)}, r"ids=\(1, 1\)"),
    ("markers", {"ids": ([1], 2)}, r"ids=\(\[1\], 2\)"),
    ("markers", {"ids": "0,1"}, "ids='0,1'"),
    ("markers", {"ids": (50,)}, r"ids=\(50,\): .*\[0, 49\]"),
    ("markers", {"ids": ()}, r"ids=\(\)"),
    ("markers", {"marker_length": 0.0}, "marker_length=0.0"),
    ("ir_rig", {"camera_count": 1}, "camera_count=1"),
    ("ir_rig", {"body_count": 5}, "body_count=5"),
    ("ir_rig", {"distortion": 1}, "distortion=1"),
    ("ir_rig", {"occlusion_rate": 1.5}, "occlusion_rate=1.5"),
    ("planar_target", {"target_width": -0.2}, "target_width=-0.2"),
    ("planar_target", {"lighting": 1.0}, "lighting=1.0"),
    ("room", {"boxes": 5}, "boxes=5"),
])
def test_invalid_scene_options_are_rejected(name, options, message):
    with pytest.raises(ValueError, match=f"option {message}"):
        make_scene(name, **options)


def test_options_are_normalised():
    scene = make_scene("markers", ids=[3, 1], fps=60, marker_length=1)
    assert scene.options.ids == (3, 1) and scene.options.fps == 60.0 and isinstance(scene.options.fps, float)


@pytest.mark.parametrize("index", [-1, 1.5, True])
def test_bad_index_is_rejected(scene, index):
    with pytest.raises(ValueError, match="frame index"):
        scene.render(index)


def test_frame_layout(scene):
    frame = scene.render(4)
    assert isinstance(frame, SceneFrame) and frame.index == 4
    assert frame.time_s == pytest.approx(4 / 30)
    names = [camera.name for camera in scene.cameras]
    assert names == [f"cam{i}" for i in range(len(names))]
    assert list(frame.images) == names and list(frame.truth) == names
    for camera in scene.cameras:
        assert isinstance(camera, CameraModel)
        assert camera.K.shape == (3, 3) and camera.dist.shape == (5,) and camera.T_rig_camera.shape == (4, 4)
        image = frame.images[camera.name]
        assert image.dtype == np.uint8 and image.shape == (camera.height, camera.width) == (120, 160)
        for parent, child, T in frame.truth[camera.name]:
            assert isinstance(parent, str) and isinstance(child, str)
            assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
            assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9) and np.linalg.det(T[:3, :3]) > 0


@pytest.mark.parametrize("name", NAMES)
def test_same_seed_and_index_give_identical_pixels_and_truth(name):
    options = {**SMALL, "seed": 7, "noise_std": 3.0, "blur_px": 0.7}
    a, b = make_scene(name, **options).render(11), make_scene(name, **options).render(11)
    for camera in a.images:
        assert np.array_equal(a.images[camera], b.images[camera])
        assert all(np.array_equal(x[2], y[2]) for x, y in zip(a.truth[camera], b.truth[camera], strict=True))


@pytest.mark.parametrize("name", NAMES)
def test_another_seed_gives_another_frame(name):
    a, b = make_scene(name, **SMALL, seed=1).render(3), make_scene(name, **SMALL, seed=2).render(3)
    assert any(not np.array_equal(a.images[c], b.images[c]) for c in a.images)


@pytest.mark.parametrize("name", NAMES)
def test_noise_differs_between_frames_and_cameras(name):
    scene = make_scene(name, **SMALL, noise_std=4.0)
    clean = make_scene(name, **SMALL)
    residuals = [scene.render(i).images[c].astype(int) - clean.render(i).images[c]
                 for i in (1, 2) for c in (camera.name for camera in clean.cameras)]
    assert all(not np.array_equal(residuals[0], r) for r in residuals[1:])


@pytest.mark.parametrize("name", NAMES)
def test_render_does_not_depend_on_call_order(name):
    options = {**SMALL, "noise_std": 2.0}
    fresh = make_scene(name, **options).render(9)
    busy = make_scene(name, **options)
    for index in (30, 2, 9, 0, 31):
        busy.render(index)
    again = busy.render(9)
    for camera in fresh.images:
        assert np.array_equal(fresh.images[camera], again.images[camera])


@pytest.mark.parametrize("name", NAMES)
def test_fps_sets_time_and_path_speed(name):
    at_30, at_60 = make_scene(name, **SMALL).render(5), make_scene(name, **SMALL, fps=60).render(10)
    assert at_60.time_s == at_30.time_s == pytest.approx(5 / 30)
    for camera in at_30.truth:
        assert [t[:2] for t in at_30.truth[camera]] == [t[:2] for t in at_60.truth[camera]]
        assert all(np.allclose(x[2], y[2]) for x, y in zip(at_30.truth[camera], at_60.truth[camera], strict=True))


def test_exposure_blur_and_noise_act_as_stated():
    clean = make_scene("planar_target", lighting=0.0, defocus=0.0).render(3).images["cam0"].astype(float)
    brighter = make_scene("planar_target", lighting=0.0, defocus=0.0, exposure=1.5).render(3).images["cam0"]
    unsaturated = clean < 150
    assert np.allclose(brighter[unsaturated], np.round(clean[unsaturated] * 1.5), atol=1)
    blurred = make_scene("planar_target", lighting=0.0, defocus=0.0, blur_px=2.0).render(3).images["cam0"]
    assert np.abs(np.diff(blurred.astype(float), axis=1)).mean() < 0.6 * np.abs(np.diff(clean, axis=1)).mean()
    noisy = make_scene("planar_target", lighting=0.0, defocus=0.0, noise_std=5.0).render(3).images["cam0"]
    inside = (clean > 30) & (clean < 225)
    residual = noisy[inside] - clean[inside]
    assert abs(residual.mean()) < 0.1 and residual.std() == pytest.approx(5.0, rel=0.05)
