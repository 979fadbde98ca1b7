"""Map files: a map saved and loaded back is the same map; files of another version, another camera,
truncated or garbage are refused with one line naming the file and why."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.geometry.camera import CameraModel, intrinsics
from services.slam.features import FrameFeatures
from services.slam.map.database import MapDatabase
from services.slam.map.file import FORMAT, VERSION, MapFileError, load_map, read_header, save_map
from services.slam.settings import SlamSettings
from services.slam.system import SlamSystem

WIDTH, HEIGHT = 640, 480
KEYFRAMES, KEYPOINTS, POINTS = 4, 200, 150


def camera(width: int = WIDTH, height: int = HEIGHT, fx_offset: float = 0.0) -> CameraModel:
    K = intrinsics(width, height, 64.0)
    K[0, 0] += fx_offset
    return CameraModel("cam0", width, height, K, np.zeros(5), np.eye(4))


def random_map(seed: int = 0) -> MapDatabase:
    """KEYFRAMES keyframes of random features and POINTS points, each seen by two to four keyframes."""
    rng = np.random.default_rng(seed)
    s = SlamSettings()
    slam_map = MapDatabase(s.scale_factor, s.levels)
    for k in range(KEYFRAMES):
        levels = rng.integers(0, s.levels, KEYPOINTS)
        features = FrameFeatures(pixels=rng.uniform(0, [WIDTH, HEIGHT], (KEYPOINTS, 2)), levels=levels,
                                 angles=rng.uniform(0, 360, KEYPOINTS).astype(np.float32),
                                 descriptors=rng.integers(0, 256, (KEYPOINTS, 32), dtype=np.uint8),
                                 sigmas=s.scale_factor ** levels.astype(np.float64))
        T = np.eye(4)
        T[:3, 3] = [-0.1 * k, 0.0, 0.0]
        slam_map.add_keyframe(1_000_000 * k, T, features, np.full(KEYPOINTS, -1, np.int64))
    free = [list(rng.permutation(KEYPOINTS)) for _ in range(KEYFRAMES)]
    for _ in range(POINTS):
        seen = rng.choice(KEYFRAMES, int(rng.integers(2, KEYFRAMES + 1)), replace=False)
        point_id = slam_map.add_point(rng.uniform([-2, -2, 3], [2, 2, 6]), {int(k): int(free[k].pop()) for k in seen})
        slam_map.points[point_id].visible, slam_map.points[point_id].found = int(rng.integers(5, 9)), 4
    return slam_map


def test_a_map_comes_back_as_it_was_saved(tmp_path):
    original = random_map()
    path = tmp_path / "room.map.npz"
    header = save_map(original, camera(), path)
    assert header["counts"] == {"keyframes": KEYFRAMES, "keypoints": KEYFRAMES * KEYPOINTS, "points": POINTS,
                                "observations": sum(len(p.observations) for p in original.points.values())}
    assert read_header(path)["camera"]["width"] == WIDTH
    loaded = load_map(path, camera())
    assert (loaded.scale_factor, loaded.levels) == (original.scale_factor, original.levels)
    assert list(loaded.keyframes) == list(original.keyframes)
    for a, b in zip(original.keyframes.values(), loaded.keyframes.values(), strict=True):
        assert a.stamp_ns == b.stamp_ns and np.array_equal(a.T_camera_world, b.T_camera_world)
        for name in ("pixels", "levels", "angles", "descriptors", "sigmas"):
            assert np.array_equal(getattr(a.features, name), getattr(b.features, name)), name
    assert len(loaded.points) == POINTS
    for a, b in zip(original.points.values(), loaded.points.values(), strict=True):
        assert np.array_equal(a.position, b.position) and a.observations == b.observations
        assert np.array_equal(a.descriptor, b.descriptor) and np.allclose(a.normal, b.normal)
        assert (a.min_distance, a.max_distance, a.visible, a.found) == pytest.approx(
            (b.min_distance, b.max_distance, b.visible, b.found))
    for a, b in zip(original.keyframes.values(), loaded.keyframes.values(), strict=True):
        assert np.array_equal(a.point_ids, b.point_ids)


def test_an_unwritable_path_is_one_clear_error(tmp_path):
    target = tmp_path / "no such folder" / "map.npz"
    with pytest.raises(MapFileError, match="cannot be written") as caught:
        save_map(random_map(), camera(), target)
    assert str(target) in str(caught.value) and not target.parent.exists()


def rewritten(path, target, change) -> None:
    """Copy the map file ``path`` to ``target`` with ``change(header, arrays)`` applied."""
    with np.load(path) as archive:
        arrays = {name: archive[name] for name in archive.files}
    header = json.loads(arrays.pop("header").tobytes())
    change(header, arrays)
    np.savez(target, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)


@pytest.fixture
def saved(tmp_path):
    path = tmp_path / "saved.npz"
    save_map(random_map(), camera(), path)
    return path


def refusal(path, camera_model: CameraModel) -> str:
    with pytest.raises(MapFileError) as caught:
        load_map(path, camera_model)
    message = str(caught.value)
    assert isinstance(caught.value, ValueError) and "\n" not in message and str(path) in message
    return message


def test_another_version_is_refused(saved, tmp_path):
    other = tmp_path / "v2.npz"
    rewritten(saved, other, lambda header, arrays: header.update(version=VERSION + 1))
    assert f"version {VERSION + 1}" in refusal(other, camera())


def test_another_format_is_refused(saved, tmp_path):
    other = tmp_path / "other.npz"
    rewritten(saved, other, lambda header, arrays: header.update(format="points"))
    assert FORMAT in refusal(other, camera())


def test_another_camera_is_refused(saved):
    assert "1280x480" in refusal(saved, camera(width=1280))
    assert "fx" in refusal(saved, camera(fx_offset=2.0))
    distorted = camera()
    distorted = CameraModel("cam0", WIDTH, HEIGHT, distorted.K, np.array([-0.2, 0.0, 0.0, 0.0, 0.0]), np.eye(4))
    assert "distortion" in refusal(saved, distorted)
    assert len(load_map(saved, camera(fx_offset=0.2)).points) == POINTS


def test_truncated_garbage_and_missing_files_are_refused(saved, tmp_path):
    data = saved.read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    assert "not a readable map file" in refusal(truncated, camera())
    for start in (len(data) // 3, len(data) // 2, 2 * len(data) // 3):
        damaged = tmp_path / f"damaged{start}.npz"
        damaged.write_bytes(data[:start] + bytes(64) + data[start + 64:])
        assert "not a readable map file" in refusal(damaged, camera())
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(np.random.default_rng(1).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    assert "not a readable map file" in refusal(garbage, camera())
    plain = tmp_path / "plain.npz"
    np.savez(plain, points=np.zeros((3, 3)))
    assert "no header" in refusal(plain, camera())
    assert "no such file" in refusal(tmp_path / "absent.npz", camera())


@pytest.mark.parametrize(("start", "what"), [
    (b"\x89MCAP0\r\n", "an MCAP recording"), (b"\x89PNG\r\n\x1a\n", "a PNG image"),
    (b"\xff\xd8\xff\xe0", "a JPEG image"), (b"%PDF-1.4", "a PDF document"),
])
def test_a_file_given_by_mistake_is_named_for_what_it_is(tmp_path, start, what):
    wrong = tmp_path / "run.mcap"
    wrong.write_bytes(start + bytes(200))
    message = refusal(wrong, camera())
    assert message == f"map file {wrong}: not a map file: {what} (a map file is the .npz archive --save-map writes)"
    assert "pickle" not in message
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    assert refusal(empty, camera()).endswith("not a readable map file (not an .npz archive, which --save-map writes)")


def test_inconsistent_arrays_are_refused(saved, tmp_path):
    broken = tmp_path / "broken.npz"
    rewritten(saved, broken, lambda header, arrays: arrays.update(
        observation_keypoints=arrays["observation_keypoints"] + KEYPOINTS))
    assert "observations refer" in refusal(broken, camera())
    short = tmp_path / "short.npz"
    rewritten(saved, short, lambda header, arrays: arrays.update(point_positions=arrays["point_positions"][1:]))
    assert "point_positions" in refusal(short, camera())


def test_the_system_refuses_a_map_of_another_camera_or_pyramid(saved):
    with pytest.raises(MapFileError, match="1280x480"):
        SlamSystem(camera(width=1280), mapping="inline", map_path=saved)
    with pytest.raises(MapFileError, match="pyramid"):
        SlamSystem(camera(), SlamSettings(levels=4), mapping="inline", map_path=saved)


def test_an_empty_map_or_no_map_is_refused_for_localisation(tmp_path):
    s = SlamSettings()
    empty = tmp_path / "empty.npz"
    save_map(MapDatabase(s.scale_factor, s.levels), camera(), empty)
    assert load_map(empty, camera()).keyframes == {}
    with pytest.raises(MapFileError, match="no keyframes"):
        SlamSystem(camera(), mapping="inline", map_path=empty, localisation_only=True)
    with pytest.raises(ValueError, match="map_path"):
        SlamSystem(camera(), mapping="inline", localisation_only=True)
