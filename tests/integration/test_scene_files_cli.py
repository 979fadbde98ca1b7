"""Tracking from files: `artrack scene export`, the stereo tracker on the exported folders scored against the
exported truth, and `artrack bodies define` taking a body the tracker did not know from its unlabelled points."""

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from protocol.codec import decode
from protocol.mocap import Points3D
from services.estimation.bodies.file import load_bodies, save_bodies
from services.estimation.bodies.rigid import pairwise_distances
from services.geometry.se3 import invert
from services.recorder.pairing import pair
from services.recorder.trajectories import load_trajectory
from services.synthetic.ir_rig import LAYOUTS
from tests.integration.support import START_S

pytestmark = pytest.mark.integration

FRAMES = 40


def test_the_stereo_tracker_on_an_exported_scene_scores_against_the_exported_truth(procs, tmp_path):
    scene, record, out = tmp_path / "scene", tmp_path / "files.mcap", tmp_path / "out"
    made = procs.run("scene", "export", "synthetic:ir_rig", "--frames", str(FRAMES), "-o", str(scene))
    assert made.poll() == 0, made.describe()
    assert {p.name for p in scene.iterdir()} >= {"cam0", "cam1", "rig.yaml", "bodies.yaml", "truth"}
    assert len(list((scene / "cam1").iterdir())) == FRAMES and (scene / "truth" / "tool.tum").is_file()
    job = procs.artrack("run", "stereo", "--source", f"images:{scene}", "--rig-file", str(scene / "rig.yaml"),
                        "--bodies", str(scene / "bodies.yaml"), "--stamps", "source", "--record", str(record),
                        name="job")
    assert job.wait(4 * START_S) == 0, job.describe()
    exported = procs.run("export", str(record), "--key", "pose/body/**", "--format", "tum", "-o", str(out))
    assert exported.poll() == 0, exported.describe()
    for body, least in (("tool", 0.7), ("wand", 0.7)):
        score = procs.run("eval", str(out / "pose" / "body" / f"{body}.tum"), str(scene / "truth" / f"{body}.tum"),
                          "--align", "none", "--json")
        assert score.poll() == 0, score.describe()
        result = json.loads(score.stdout)
        assert result["matched"] >= least * FRAMES and result["ate_m"]["median"] < 0.0005, (body, result)


def test_folders_that_do_not_pair_stop_the_run_in_one_line(procs, tmp_path):
    scene = tmp_path / "scene"
    assert procs.run("scene", "export", "synthetic:ir_rig", "--frames", "3", "-o", str(scene)).poll() == 0
    sorted((scene / "cam1").iterdir())[-1].unlink()
    job = procs.run("run", "stereo", "--source", f"images:{scene}", "--rig-file", str(scene / "rig.yaml"))
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "do not pair up" in lines[0] and "no partner in cam1/" in lines[0], job.stderr


def unlabelled_counts(path) -> list[tuple[float, int, int]]:
    """``(seconds after the first, unlabelled, labelled)`` of every Points3D in the recording."""
    found = []
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if channel.topic.endswith("/points"):
                points = decode(message.data)
                assert isinstance(points, Points3D)
                found.append((points.header.stamp_ns, int((points.body == -1).sum()), int((points.body >= 0).sum())))
    start = min(stamp for stamp, _, _ in found)
    return [((stamp - start) / 1e9, free, labelled) for stamp, free, labelled in found]


def test_a_body_left_out_is_defined_from_its_unlabelled_points_and_then_tracked(procs, tmp_path):
    known, record, again = tmp_path / "bodies.yaml", tmp_path / "seen.mcap", tmp_path / "again.mcap"
    save_bodies(known, {"wand": LAYOUTS["wand"]})
    run = ("run", "stereo", "--source", "synthetic:ir_rig", "--scene-option", "body_count=2", "--frames", str(FRAMES))
    job = procs.artrack(*run, "--bodies", str(known), "--record", str(record), name="seen")
    assert job.wait(4 * START_S) == 0, job.describe()
    # an instant where the wand is found and the tool's four spheres are all there, unlabelled
    at_s = next(t for t, free, labelled in unlabelled_counts(record) if free == 4 and labelled == 3)
    define = ("bodies", "define", "--from", str(record), "--at", f"{at_s:.6f}", "--bodies", str(known))
    defined = procs.run(*define, "probe")
    assert defined.poll() == 0, defined.describe()
    bodies = load_bodies(known)
    assert list(bodies) == ["wand", "probe"]
    ours = np.sort(pairwise_distances(bodies["probe"]), axis=None)
    truth = np.sort(pairwise_distances(LAYOUTS["tool"]), axis=None)
    assert np.abs(ours - truth).max() < 0.001, (ours, truth)
    # the same spheres once more are refused: they are too like the body just defined
    twice = procs.run(*define, "probe2")
    lines = [line for line in twice.stderr.splitlines() if line.strip()]
    assert twice.poll() == 2 and len(lines) == 1 and "too like body 'probe'" in lines[0], twice.describe()
    assert list(load_bodies(known)) == ["wand", "probe"]
    job = procs.artrack(*run, "--bodies", str(known), "--record", str(again), name="again")
    assert job.wait(4 * START_S) == 0, job.describe()
    estimated = load_trajectory(again, key="pose/body/probe")
    true_tool = load_trajectory(again, key="cam0/truth", child="body/tool")
    pairs = pair(estimated, true_tool, "stamp", 1_000_000).rows
    assert len(pairs) >= 0.7 * FRAMES, len(pairs)
    # the new body rides on the tool: its pose in the tool's frame stays put
    T_tool_probe = np.array([invert(true_tool.poses[j]) @ estimated.poses[i] for i, j in pairs])
    offsets = T_tool_probe[:, :3, 3]
    assert np.abs(offsets - np.median(offsets, axis=0)).max() < 0.002, offsets
