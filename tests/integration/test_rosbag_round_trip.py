"""A ROS 2 bag through a tracker and back: the shipped marker recording exported to a bag, tracked from the bag
(``--source rosbag2:DIR``), the run exported to a bag again; its poses are those of tracking the recording."""

from __future__ import annotations

import pytest
from rosbags.rosbag2 import Reader

from services.recorder.export import Export
from services.recorder.rosbag import TYPESTORE, export_rosbag
from tests.integration.support import ROOT

pytestmark = pytest.mark.integration

MARKERS = ROOT / "recordings" / "markers.mcap"
TRACK = ("--marker-length", "0.05", "--progress", "off", "--quiet")
MARKER_KEYS = [f"pose/cam0/marker/{marker}" for marker in range(6)]


def bag_poses(folder) -> dict[tuple[int, str], tuple[tuple[float, ...], tuple[float, ...]]]:
    """``{(stamp ns, topic): (translation, quaternion x y z w)}`` of every PoseStamped in a bag."""
    poses = {}
    with Reader(folder) as reader:
        wanted = [c for c in reader.connections if c.msgtype == "geometry_msgs/msg/PoseStamped"]
        for connection, _, data in reader.messages(connections=wanted):
            message = TYPESTORE.deserialize_cdr(data, connection.msgtype)
            stamp = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
            p, q = message.pose.position, message.pose.orientation
            poses[(stamp, connection.topic)] = ((p.x, p.y, p.z), (q.x, q.y, q.z, q.w))
    return poses


def test_tracking_a_bag_gives_the_poses_of_tracking_the_recording_it_came_from(procs, tmp_path):
    export_rosbag(MARKERS, tmp_path / "in")
    from_bag = procs.run("run", "marker", "--source", f"rosbag2:{tmp_path / 'in'}", "--stamps", "source",
                         "--record", str(tmp_path / "bag_run.mcap"), *TRACK, timeout=120)
    assert from_bag.poll() == 0, from_bag.describe()
    from_recording = procs.run("run", "marker", "--source", f"recording:{MARKERS}", "--record",
                               str(tmp_path / "recording_run.mcap"), *TRACK, timeout=120)
    assert from_recording.poll() == 0, from_recording.describe()
    exported = procs.run("export", str(tmp_path / "bag_run.mcap"), "--format", "rosbag2", "-o", str(tmp_path / "out"))
    assert exported.poll() == 0, exported.describe()

    seq_of = {m.header.stamp_ns: m.header.seq for _, _, m in Export(MARKERS, "cam0/image", "jsonl").messages()}
    got = {(seq_of[stamp], topic): pose for (stamp, topic), pose in bag_poses(tmp_path / "out").items()}
    expected = {(header.seq, "/pose/cam0/marker_" + key.rsplit("/", 1)[1]): (t.translation, t.rotation)
                for key in MARKER_KEYS
                for header, t in Export(tmp_path / "recording_run.mcap", key, "tum").transforms()}
    assert len(expected) > 6 * 100
    assert set(got) == set(expected)  # the same frames tracked, the same markers in each
    for pair, (translation, rotation) in expected.items():
        assert got[pair][0] == pytest.approx(translation, abs=1e-9), pair
        assert got[pair][1] == pytest.approx(rotation, abs=1e-9), pair


def test_a_missing_bag_is_refused_in_one_line_before_anything_starts(procs, tmp_path):
    job = procs.run("run", "marker", "--source", f"rosbag2:{tmp_path / 'none'}", "--marker-length", "0.05")
    assert job.poll() == 2, job.describe()
    lines = [line for line in job.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and f"nodes.capture: rosbag2:{tmp_path / 'none'}: no such folder" in lines[0], job.stderr
