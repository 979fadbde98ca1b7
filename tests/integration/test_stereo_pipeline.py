"""``artrack run stereo``: IR blobs per camera -> rigid bodies, recorded and scored against the recorded truth."""

import json

import pytest

from tests.integration.support import START_S
from tests.viewer_contents import RrdContents

pytestmark = pytest.mark.integration

FRAMES = 40


def test_stereo_run_records_body_poses_that_score_within_half_a_millimetre(procs, tmp_path):
    out, view = tmp_path / "stereo.mcap", tmp_path / "stereo.rrd"
    job = procs.artrack("run", "stereo", "--source", "synthetic:ir_rig", "--frames", str(FRAMES), "--record", str(out),
                        "--rerun", str(view), name="job")
    assert job.wait(4 * START_S) == 0, job.describe()
    scored = {}
    for body in ("tool", "wand"):
        check = procs.run("eval", str(out), str(out), "--est-key", f"pose/body/{body}", "--gt-key", "cam0/truth",
                          "--child", f"body/{body}", "--align", "none", "--json")
        assert check.poll() == 0, check.describe()
        scored[body] = json.loads(check.stdout)
    # Each body's poses against the scene's truth of the same frames, not aligned: the rig frame is the world.
    assert scored["tool"]["matched"] >= 0.7 * FRAMES and scored["wand"]["matched"] >= 0.5 * FRAMES, scored
    for body, score in scored.items():
        assert score["ate_m"]["median"] <= 0.0005, (body, score["ate_m"])
    points = procs.run("export", str(out), "--key", "points", "--format", "jsonl")
    seqs = [json.loads(line)["header"]["seq"] for line in points.stdout.splitlines()]
    # one Points3D per joined instant (a loaded machine may drop frames at the blobs nodes: latest wins)
    assert len(seqs) >= 0.8 * FRAMES and seqs == sorted(set(seqs)), points.describe()
    stats = procs.run("export", str(out), "--key", "node/bodies/stats", "--format", "jsonl")
    (joined,) = json.loads(stats.stdout.splitlines()[-1])["synced"]
    assert joined["by"] == "seq" and [i["name"] for i in joined["inputs"]] == ["cam0", "cam1"], joined
    assert 0 < joined["sets"] <= len(seqs) and all(i["joined"] <= i["received"] for i in joined["inputs"]), joined
    viewed = RrdContents(view)
    assert {"world/cam1/image/clean_blobs", "world/points/labelled", "world/pose/body/tool"} <= viewed.entities
    assert viewed.rows("world/cam1/image", "Pinhole:image_from_camera") and viewed.rows("world/cam1",
                                                                                          "Transform3D:translation")


def test_a_missing_rig_file_is_refused_before_anything_starts(procs, tmp_path):
    job = procs.run("run", "stereo", "--source", "synthetic:ir_rig", "--frames", "5",
                    "--rig-file", str(tmp_path / "no-rig.yaml"))
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    # the scene's bodies file, said as the job takes it, then the refusal in one line
    assert len(lines) == 2 and "using --bodies " in lines[0] and "as synthetic:ir_rig renders it" in lines[0]
    assert "nodes.bodies: " in lines[1] and "no-rig.yaml: cannot read" in lines[1], job.stderr
