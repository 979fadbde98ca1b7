"""A node joining two cameras' streams with ``Node.synced``, fed by two publisher processes.

The second camera's stream misses frames (joined by sequence number) or is skewed, a few
frames beyond the tolerance (joined by stamp). The node republishes every pair; the test
checks the pairs and, through the node's ``NodeStats`` on the bus, what it could not join.
"""

import json
import sys

import pytest

from protocol.sensors import Image
from services.bus.pubsub import Inbox, Role

from .busprobe import BASE_STAMP_NS
from .support import HERE, START_S, collect, probe_argv, start_node, states, wait_live, wait_until

pytestmark = pytest.mark.integration

FRAMES = 40
PERIOD_NS = 33_333_333  # the probe's frame spacing
DEPTH = 64  # above FRAMES: however the two probes start, no frame waits long enough to be evicted


def start_pairs(procs, session, keys, *args: str, depth: int = DEPTH):
    """The joining node (``syncnode.py``) up on the bus, and inboxes of the pairs it republishes."""
    outs = [Inbox(session, f"{keys.prefix}/pairs/{camera}", Image, Role.RESULT) for camera in ("cam0", "cam1")]
    node = procs.start([sys.executable, str(HERE / "syncnode.py"), "pairs", "--depth", str(depth), *args],
                       name="pairs")
    wait_live(session, keys, {"pairs"}, [node])
    return node, outs


def start_cameras(procs, *cam1_args: str) -> None:
    """cam0 with every frame, cam1 changed by ``cam1_args`` (``busprobe.py`` options), both at 30 Hz."""
    common = ("--role", "result", "--rate", "30", "--width", "64", "--height", "48")
    procs.start(probe_argv("image", str(FRAMES), "--key", "cam0/image", *common), name="cam0")
    procs.start(probe_argv("image", str(FRAMES), "--key", "cam1/image", *common, *cam1_args), name="cam1")


def pairs_and_stats(session, keys, outs, expected_pairs: int, received: tuple[int, int]):
    """The pairs republished as ``[(cam0 image, cam1 image)]`` and the node's stats, once it has formed
    ``expected_pairs`` sets and ``received`` frames from cam0 and cam1."""
    try:
        left, right = (collect(inbox, expected_pairs) for inbox in outs)
    finally:
        for inbox in outs:
            inbox.close()

    def settled():
        stats = states(session, keys).get("pairs")
        if stats is None or len(stats.synced) != 1:
            return None
        (group,) = stats.synced
        done = (group.sets == expected_pairs and stats.processed == expected_pairs
                and tuple(i.received for i in group.inputs) == received)
        return stats if done else None

    stats = wait_until(settled, 30.0, "the pairs node's stats to count every frame", interval_s=0.2)
    return list(zip(left, right, strict=True)), stats


def test_joined_by_sequence_number_with_frames_missing_on_one_camera(bus, procs, session):
    keys = bus.keys
    missing = [5, 17, 18, 39]
    node, outs = start_pairs(procs, session, keys, "--by", "seq")
    start_cameras(procs, "--skip", ",".join(map(str, missing)))
    expected = [i for i in range(FRAMES) if i not in missing]
    pairs, stats = pairs_and_stats(session, keys, outs, len(expected), (FRAMES, FRAMES - len(missing)))

    assert [(a.header.seq, b.header.seq) for a, b in pairs] == [(i, i) for i in expected]
    assert all(a.header.stamp_ns == b.header.stamp_ns for a, b in pairs)
    (group,) = stats.synced
    cam0, cam1 = group.inputs
    assert (group.by, group.sets, group.dropped, group.resets) == ("seq", len(expected), 0, 0)
    assert (cam0.name, cam0.key, cam1.name, cam1.key) == ("cam0", keys.image("cam0"), "cam1", keys.image("cam1"))
    # 5, 17 and 18 were overtaken by the next pair; 39 has no later pair and still waits
    assert (cam0.received, cam0.joined, cam0.superseded, cam0.evicted, cam0.out_of_order) == (40, 36, 3, 0, 0)
    assert (cam1.received, cam1.joined, cam1.unjoined) == (36, 36, 0)
    assert stats.unjoined == 3
    assert node.poll() is None

    listed = procs.run("list", "--timeout", "1.5")
    assert listed.poll() == 0, listed.describe()
    header, row = (line.split() for line in listed.stdout.splitlines())
    assert dict(zip(header, row, strict=True))["UNJOINED"] == "3", listed.stdout
    status = procs.run("status", "--timeout", "1", "--json")
    assert [n["unjoined"] for n in json.loads(status.stdout)["unsupervised"]] == [3], status.describe()


def test_joined_by_stamp_within_the_tolerance_and_skewed_frames_left_out(bus, procs, session):
    keys = bus.keys
    beyond = [10, 11, 30]  # 7 ms late: outside the 5 ms tolerance
    node, outs = start_pairs(procs, session, keys, "--by", "stamp", "--tolerance-ms", "5")
    start_cameras(procs, "--offset-ms", "4.5", *(arg for i in beyond for arg in ("--offset-at", f"{i}=7")))
    expected = [i for i in range(FRAMES) if i not in beyond]
    pairs, stats = pairs_and_stats(session, keys, outs, len(expected), (FRAMES, FRAMES))

    assert [(a.header.seq, b.header.seq) for a, b in pairs] == [(i, i) for i in expected]
    assert [a.header.stamp_ns for a, _ in pairs] == [BASE_STAMP_NS + i * PERIOD_NS for i in expected]
    assert all(b.header.stamp_ns - a.header.stamp_ns == 4_500_000 for a, b in pairs)
    (group,) = stats.synced
    cam0, cam1 = group.inputs
    assert (group.by, group.tolerance_ns, group.sets) == ("stamp", 5_000_000, len(expected))
    assert (cam0.received, cam0.joined, cam0.superseded) == (FRAMES, len(expected), len(beyond))
    assert (cam1.received, cam1.joined, cam1.superseded) == (FRAMES, len(expected), len(beyond))
    assert cam0.evicted == cam1.evicted == cam0.out_of_order == cam1.out_of_order == 0
    assert stats.unjoined == 2 * len(beyond)
    assert node.poll() is None


def test_a_two_camera_capture_joined_latest_wins_gives_only_matching_pairs(bus, procs, session):
    keys = bus.keys
    frames = 30
    node, outs = start_pairs(procs, session, keys, "--by", "stamp", "--role", "frame", "--backlog", "2", depth=8)
    capture = start_node(procs, "capture", "rig", source="synthetic:ir_rig", cameras=["cam0", "cam1"],
                         frames=frames, fps=30, wait_for_subscriber=True)

    def counted():
        """The node's stats once every frame of both cameras reached the join or was dropped before it (or, the
        frames being latest-wins on a busy machine, never reached the node: missing, told once the source ended)."""
        assert capture.poll() in (None, 0), capture.describe()
        stats = states(session, keys).get("pairs")
        if stats is None or not stats.synced:
            return None
        arrived = {s.key: s for s in stats.streams if s.direction == "in"}
        done = all(arrived[i.key].messages + arrived[i.key].missing == frames
                   and i.received + arrived[i.key].dropped == arrived[i.key].messages for i in stats.synced[0].inputs)
        return stats if done else None

    stats = wait_until(counted, START_S, "the pairs node to take every frame of both cameras", interval_s=0.2)
    (group,) = stats.synced
    handed_out = group.sets - group.dropped
    try:
        left, right = (collect(inbox, handed_out) for inbox in outs)
    finally:
        for inbox in outs:
            inbox.close()

    seqs = [a.header.seq for a in left]
    assert seqs == sorted(set(seqs)) and [b.header.seq for b in right] == seqs
    assert all(a.header.stamp_ns == b.header.stamp_ns for a, b in zip(left, right, strict=True))
    cam0, cam1 = group.inputs
    assert cam0.joined == cam1.joined == group.sets >= 1
    assert group.sets + cam0.unjoined <= frames and group.sets + cam1.unjoined <= frames
    inputs_dropped = sum(s.dropped for s in stats.streams if s.direction == "in")
    assert stats.dropped == inputs_dropped + group.dropped  # the sets let go count as the node's drops
    assert node.poll() is None


def test_a_slow_node_joined_latest_wins_takes_the_newest_sets_and_counts_the_rest_dropped(bus, procs, session):
    """A node spending 100 ms on each pair of a 30 Hz rig, with a backlog of two sets: the pairs it takes match
    and come in order up to the last one, and every set it let go counts in its drops."""
    keys = bus.keys
    node, outs = start_pairs(procs, session, keys, "--by", "seq", "--role", "frame", "--backlog", "2",
                             "--work-ms", "100")
    start_cameras(procs)

    def settled():
        stats = states(session, keys).get("pairs")
        if stats is None or len(stats.synced) != 1:
            return None
        (group,) = stats.synced
        done = (tuple(i.received for i in group.inputs) == (FRAMES, FRAMES) and group.sets == FRAMES
                and stats.processed == group.sets - group.dropped)
        return stats if done else None

    stats = wait_until(settled, 30.0, "the slow node to take its last set", interval_s=0.2)
    (group,) = stats.synced
    try:
        left, right = (collect(inbox, group.sets - group.dropped) for inbox in outs)
    finally:
        for inbox in outs:
            inbox.close()
    seqs = [a.header.seq for a in left]
    assert seqs == sorted(set(seqs)) and [b.header.seq for b in right] == seqs
    assert seqs[-1] == FRAMES - 1  # the newest sets wait: the last one is never dropped
    assert group.dropped >= FRAMES // 3, group  # 30 sets a second into a node that takes 10
    assert stats.dropped == group.dropped + sum(s.dropped for s in stats.streams if s.direction == "in")
    assert node.poll() is None
