"""A body defined from seen sphere centres: its frame's rule, and `artrack bodies check`'s verdicts."""

import numpy as np
import pytest

from services.cli import main
from services.estimation.bodies.definition import body_frame
from services.estimation.bodies.file import save_bodies
from services.estimation.bodies.rigid import pairwise_distances
from services.geometry.rotation import matrix_from_rotvec
from services.geometry.se3 import transform_points
from services.synthetic.ir_rig import LAYOUTS


def seen(spheres: np.ndarray, seed: int) -> np.ndarray:
    """``spheres`` moved somewhere in front of a rig and shuffled, as triangulation hands them over."""
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = matrix_from_rotvec(rng.normal(0.0, 1.0, 3)), rng.uniform(-0.5, 0.5, 3) + [0, 0, 2.2]
    return rng.permutation(transform_points(T, spheres))


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_the_body_frame_follows_its_rule(name):
    points = seen(LAYOUTS[name], 1)
    spheres, T_world_body = body_frame(points)
    np.testing.assert_allclose(transform_points(T_world_body, spheres)[np.lexsort(spheres.T)].mean(axis=0),
                               points.mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(np.sort(pairwise_distances(spheres), axis=None),
                               np.sort(pairwise_distances(points), axis=None), atol=1e-12)
    np.testing.assert_allclose(spheres.mean(axis=0), 0.0, atol=1e-12)
    assert np.isclose(np.linalg.det(T_world_body[:3, :3]), 1.0) and np.all(np.diff(spheres[:, 0]) >= 0)
    # principal axes, cross-checked against the eigenvectors of the spheres' scatter
    values, vectors = np.linalg.eigh(np.cov(points.T))
    for axis, vector in zip(T_world_body[:3, :3].T, vectors[:, ::-1].T, strict=True):
        assert abs(abs(axis @ vector) - 1.0) < 1e-9
    scatter = np.cov(spheres.T)
    np.testing.assert_allclose(scatter - np.diag(np.diag(scatter)), 0.0, atol=1e-12)
    assert np.all(np.diff(np.diag(scatter)) <= 0)
    for column in (0, 1):
        assert spheres[np.argmax(np.abs(spheres[:, column])), column] > 0


def test_the_same_spheres_seen_anywhere_give_the_same_body():
    first, _ = body_frame(seen(LAYOUTS["glove"], 2))
    again, _ = body_frame(seen(LAYOUTS["glove"], 3))
    np.testing.assert_allclose(first, again, atol=1e-12)


def test_too_few_or_malformed_points_are_refused():
    with pytest.raises(ValueError, match="at least 3"):
        body_frame(np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        body_frame(np.zeros((4, 2)))


def test_bodies_check_exits_by_what_it_finds(tmp_path, capsys):
    good, doubtful, bad = tmp_path / "good.yaml", tmp_path / "doubtful.yaml", tmp_path / "bad.yaml"
    save_bodies(good, {"wand": LAYOUTS["wand"], "tool": LAYOUTS["tool"]})
    save_bodies(doubtful, {"tool": LAYOUTS["tool"], "copy": LAYOUTS["tool"] + 0.001})
    bad.write_text("bodies: 3\n")
    assert main(["bodies", "check", str(good)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("wand: 3 spheres, distances ") and out[-1] == "2 bodies, 0 warning(s)"
    shortest = pairwise_distances(LAYOUTS["wand"])[np.triu_indices(3, 1)].min()
    assert f"distances {shortest * 1e3:.1f} to" in out[0]
    assert main(["bodies", "check", str(doubtful)]) == 1
    out = capsys.readouterr().out
    assert "warning: body 'copy' is too like body 'tool'" in out and "warning(s)" in out
    assert main(["bodies", "check", str(bad)]) == 2
    assert capsys.readouterr().out == ""


def test_define_refuses_a_time_outside_the_recording_naming_its_span(tmp_path, capsys):
    from protocol import Header, Points3D, encode
    from services.recorder.writing import RecordingWriter

    record = tmp_path / "seen.mcap"
    writer = RecordingWriter(record, metadata={"namespace": "ar", "rig": "rig0"})
    spheres = seen(LAYOUTS["tool"], seed=3)
    for i in range(60):  # 2 s at 30 Hz: the last message 59/30 = 1.967 s after the first
        n = len(spheres)
        points = Points3D(header=Header(stamp_ns=10**18 + i * 10**9 // 30, frame_id="world", seq=i), points=spheres,
                          residual_px=np.zeros(n, np.float32), views=np.full(n, 2, np.uint8),
                          covariances=np.zeros((n, 3, 3)), body=np.full(n, -1, np.int32))
        writer.write("ar/rig0/points", encode(points), i)
    writer.close()
    bodies = tmp_path / "bodies.yaml"
    for at in ("99", "-1"):
        assert main(["bodies", "define", "probe", "--from", str(record), "--at", at, "--bodies", str(bodies)]) == 2
        assert f"--at {at}: {record} holds points from 0 to 1.967 s" in capsys.readouterr().err
    assert not bodies.exists()
    assert main(["bodies", "define", "probe", "--from", str(record), "--at", "1.967", "--bodies", str(bodies)]) == 0
    assert "probe: 4 spheres" in capsys.readouterr().out
