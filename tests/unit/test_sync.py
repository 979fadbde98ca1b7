"""The input joiner behind ``Node.synced``: joins by sequence and by stamp, bounded memory, counts."""

from __future__ import annotations

from collections import deque
from dataclasses import asdict

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.message import Header
from protocol.system import ErrorReport
from services.bus.pubsub import Received
from services.runtime.node import Synced
from services.runtime.sync import InputCounts, Joiner, join_key, key_tolerance

MS = 1_000_000


def drain(joiner: Joiner) -> list[tuple[int, dict]]:
    sets = []
    while (joined := joiner.pop()) is not None:
        sets.append(joined)
    return sets


def counts(joiner: Joiner, name: str) -> dict[str, int]:
    return asdict(joiner.counts(name))


def test_equal_sequence_numbers_join_into_one_set_in_input_order():
    joiner = Joiner(["left", "right"], ready=10)
    joiner.push("right", 7, "R7")
    assert joiner.pop() is None
    joiner.push("left", 7, "L7")
    key, items = joiner.pop()
    assert key == 7 and items == {"left": "L7", "right": "R7"} and list(items) == ["left", "right"]
    assert counts(joiner, "left") == counts(joiner, "right") == asdict(InputCounts(received=1, joined=1))
    assert joiner.sets == 1 and joiner.pending("left") == joiner.pending("right") == 0


def test_a_missing_message_leaves_its_partner_superseded_by_the_next_set():
    joiner = Joiner(["left", "right"], ready=10)
    for seq in (1, 2, 3):
        joiner.push("left", seq, f"L{seq}")
    for seq in (1, 3):
        joiner.push("right", seq, f"R{seq}")
    assert [key for key, _ in drain(joiner)] == [1, 3]
    assert counts(joiner, "left") == {"received": 3, "joined": 2, "evicted": 0, "superseded": 1, "out_of_order": 0}
    assert joiner.counts("right").unjoined == 0 and joiner.pending("left") == 0


@pytest.mark.parametrize("skew_ns", [0, 5 * MS, -5 * MS, 2 * MS])
def test_stamps_within_the_tolerance_join_either_side_of_the_reference(skew_ns):
    joiner = Joiner(["cam0", "cam1"], tolerance=5 * MS)
    joiner.push("cam0", 1000 * MS, "a")
    joiner.push("cam1", 1000 * MS + skew_ns, "b")
    assert joiner.pop() == (1000 * MS, {"cam0": "a", "cam1": "b"})


@pytest.mark.parametrize("skew_ns", [5 * MS + 1, -5 * MS - 1, 16 * MS])
def test_stamps_just_outside_the_tolerance_do_not_join(skew_ns):
    joiner = Joiner(["cam0", "cam1"], tolerance=5 * MS)
    joiner.push("cam0", 1000 * MS, "a")
    joiner.push("cam1", 1000 * MS + skew_ns, "b")
    assert joiner.pop() is None and joiner.sets == 0
    assert joiner.pending("cam0") == joiner.pending("cam1") == 1


def test_the_nearest_pending_partner_is_taken():
    joiner = Joiner(["cam0", "cam1"], tolerance=5 * MS, ready=10)
    joiner.push("cam1", 996 * MS, "far")
    joiner.push("cam1", 1002 * MS, "near")
    joiner.push("cam0", 1000 * MS, "ref")
    assert drain(joiner) == [(1000 * MS, {"cam0": "ref", "cam1": "near"})]
    assert joiner.pending("cam1") == 1  # 996 ms could still join a reference up to 1001 ms
    joiner.push("cam0", 1033 * MS, "ref2")
    joiner.push("cam1", 1034 * MS, "next")
    assert [items["cam1"] for _, items in drain(joiner)] == ["next"]
    assert counts(joiner, "cam1")["superseded"] == 1


def test_a_steady_skew_joins_every_frame_and_a_larger_one_none():
    period, skew = 33 * MS, 3 * MS
    inside = Joiner(["cam0", "cam1"], tolerance=4 * MS, ready=100)
    outside = Joiner(["cam0", "cam1"], tolerance=2 * MS, ready=100)
    for joiner in (inside, outside):
        for i in range(20):
            joiner.push("cam0", i * period, i)
            joiner.push("cam1", i * period + skew, i)
    assert [items for _, items in drain(inside)] == [{"cam0": i, "cam1": i} for i in range(20)]
    assert drain(outside) == [] and outside.pending("cam0") == outside.depth


def test_messages_reordered_before_their_set_completes_still_join_in_order():
    joiner = Joiner(["left", "right"], ready=10)
    joiner.push("right", 2, "R2")
    joiner.push("right", 1, "R1")
    joiner.push("left", 1, "L1")
    joiner.push("left", 2, "L2")
    assert drain(joiner) == [(1, {"left": "L1", "right": "R1"}), (2, {"left": "L2", "right": "R2"})]
    assert all(joiner.counts(name).unjoined == 0 for name in joiner.names)


def test_a_message_older_than_the_last_set_is_counted_out_of_order():
    joiner = Joiner(["left", "right"], ready=10)
    joiner.push("left", 1, "L1")
    joiner.push("left", 2, "L2")
    joiner.push("right", 2, "R2")
    joiner.push("right", 1, "R1")  # too late: set 2 is out
    joiner.push("right", 3, "R3")
    joiner.push("right", 3, "R3 again")  # repeats a pending key
    assert [key for key, _ in drain(joiner)] == [2]
    assert counts(joiner, "right") == {"received": 4, "joined": 1, "evicted": 0, "superseded": 0, "out_of_order": 2}
    assert counts(joiner, "left")["superseded"] == 1
    assert joiner.pending("right") == 1


def test_a_flood_on_one_input_keeps_memory_bounded_and_counts_evictions():
    joiner = Joiner(["left", "right"], depth=4)
    for seq in range(1000):
        joiner.push("right", seq, seq)
    assert joiner.pending("right") == 4
    assert counts(joiner, "right")["evicted"] == 996
    joiner.push("left", 998, "L")
    assert joiner.pop() == (998, {"left": "L", "right": 998})
    assert counts(joiner, "right")["superseded"] == 2  # 996 and 997 waited for partners
    assert joiner.pending("right") == 1  # 999 may still get one


def test_ready_sets_are_latest_wins_with_ready_1_and_queued_otherwise():
    latest, queued = Joiner(["a", "b"], ready=1), Joiner(["a", "b"], ready=3)
    for joiner in (latest, queued):
        for seq in range(5):
            joiner.push("a", seq, seq)
            joiner.push("b", seq, seq)
    assert [key for key, _ in drain(latest)] == [4] and latest.dropped == 4 and latest.sets == 5
    assert [key for key, _ in drain(queued)] == [2, 3, 4] and queued.dropped == 2


def test_a_source_that_starts_over_is_joined_again_after_depth_late_messages():
    joiner = Joiner(["left", "right"], depth=3, ready=100)
    for seq in range(100, 105):
        joiner.push("left", seq, seq)
        joiner.push("right", seq, seq)
    for seq in range(5):  # both sources restarted, counting from 0
        joiner.push("left", seq, seq)
        joiner.push("right", seq, seq)
    keys = [key for key, _ in drain(joiner)]
    assert keys == [100, 101, 102, 103, 104, 2, 3, 4]
    assert joiner.resets == 1
    assert counts(joiner, "left")["out_of_order"] == 2 and counts(joiner, "right")["out_of_order"] == 2


def test_three_inputs_join_only_when_all_three_are_there():
    joiner = Joiner(["cam0", "cam1", "det"], tolerance=1 * MS, ready=10)
    joiner.push("cam0", 100 * MS, "c0")
    joiner.push("cam1", 100 * MS, "c1")
    assert joiner.pop() is None
    joiner.push("det", 100 * MS + 500, "d")
    assert joiner.pop() == (100 * MS, {"cam0": "c0", "cam1": "c1", "det": "d"})


@pytest.mark.parametrize(("names", "kwargs", "match"), [
    (["only"], {}, "at least two inputs"),
    (["a", "a"], {}, "must differ"),
    (["a", "b"], {"tolerance": -1}, "tolerance must be >= 0"),
    (["a", "b"], {"depth": 0}, "depth and ready must be >= 1"),
    (["a", "b"], {"ready": 0}, "depth and ready must be >= 1"),
])
def test_bad_arguments_are_refused_with_a_reason(names, kwargs, match):
    with pytest.raises(ValueError, match=match):
        Joiner(names, **kwargs)


def test_an_unknown_input_is_refused():
    with pytest.raises(KeyError, match="unknown input 'c'"):
        Joiner(["a", "b"]).push("c", 1, None)


def test_keys_are_read_from_the_header_and_the_tolerance_is_checked_and_converted_to_ns():
    header = Header(stamp_ns=1_700_000_000_123_456_789, seq=42)
    assert join_key(header, "seq") == 42 and join_key(header, "stamp") == header.stamp_ns
    assert key_tolerance("stamp", 0.0025) == 2_500_000 and key_tolerance("seq", 0.0) == 0


@pytest.mark.parametrize(("by", "tolerance_s", "match"), [
    ("time", 0.0, "by must be 'seq' or 'stamp'"),
    ("seq", 0.001, "applies to by='stamp' only"),
    ("stamp", -0.001, "finite number of seconds >= 0"),
    ("stamp", float("nan"), "finite number of seconds >= 0"),
    ("stamp", float("inf"), "finite number of seconds >= 0"),
])
def test_a_bad_join_is_refused_with_a_reason(by, tolerance_s, match):
    with pytest.raises(ValueError, match=match):
        key_tolerance(by, tolerance_s)


pushes = st.lists(st.tuples(st.sampled_from(["a", "b", "c"]), st.integers(0, 40)), max_size=200)


@settings(max_examples=300, deadline=None)
@given(pushes=pushes, tolerance=st.integers(0, 3), depth=st.integers(1, 6), ready=st.integers(1, 4))
def test_whatever_arrives_sets_stay_ordered_and_within_tolerance_and_every_message_is_accounted(
        pushes, tolerance, depth, ready):
    """Sets come out in key order (since the last reset), each within the tolerance of its
    reference, and every message pushed is joined, counted unjoined, or still pending."""
    joiner = Joiner(["a", "b", "c"], tolerance=tolerance, depth=depth, ready=ready)
    taken: list[tuple[int, dict]] = []
    last_key = None
    for name, key in pushes:
        resets = joiner.resets
        joiner.push(name, key, (name, key))
        assert joiner.pending(name) <= depth and joiner.ready() <= ready
        if joiner.resets != resets:
            last_key = None  # sets are ordered since the last reset
        for set_key, items in drain(joiner):
            assert last_key is None or set_key > last_key
            last_key = set_key
            assert items["a"] == ("a", set_key)
            assert all(abs(items[other][1] - set_key) <= tolerance for other in ("b", "c"))
            taken.append((set_key, items))
    assert joiner.sets == len(taken) + joiner.dropped
    for name in joiner.names:
        c = joiner.counts(name)
        assert c.received == sum(1 for pushed, _ in pushes if pushed == name)
        assert c.joined == joiner.sets
        assert c.received == c.joined + c.unjoined + joiner.pending(name)


@settings(max_examples=300, deadline=None)
@given(streams=st.lists(st.sets(st.integers(0, 60)), min_size=2, max_size=3), order=st.randoms())
def test_in_order_streams_join_by_seq_into_exactly_the_common_sequence_numbers(streams, order):
    names = [f"in{i}" for i in range(len(streams))]
    joiner = Joiner(names, depth=64, ready=64)
    queues = {name: sorted(keys) for name, keys in zip(names, streams, strict=True)}
    while any(queues.values()):
        name = order.choice([n for n in names if queues[n]])
        key = queues[name].pop(0)
        joiner.push(name, key, key)
    common = set.intersection(*map(set, streams))
    assert [key for key, _ in drain(joiner)] == sorted(common)


class QueuedInbox:
    """Stands in for an ``Inbox`` whose messages have all arrived already."""

    def __init__(self, key: str, seqs: range):
        self.key = key
        self.queue = deque(Received(key, ErrorReport(header=Header(stamp_ns=seq, seq=seq), node="n", kind="k",
                                                     detail=""), 0) for seq in seqs)

    def take(self) -> Received | None:
        return self.queue.popleft() if self.queue else None


def synced_over_backlog(latest: bool) -> Synced:
    inboxes = {"left": QueuedInbox("l", range(20)), "right": QueuedInbox("r", range(20))}
    return Synced(None, inboxes, Joiner(list(inboxes), depth=4, ready=1 if latest else 4), "seq", latest)


def test_a_backlog_longer_than_the_depth_is_joined_in_order_when_every_set_counts():
    synced = synced_over_backlog(latest=False)
    taken = [synced.take() for _ in range(21)]
    assert [{name: m.header.seq for name, m in pair.items()} for pair in taken[:20]] == [
        {"left": i, "right": i} for i in range(20)]
    assert taken[20] is None
    stats = synced.stats()
    assert (stats.sets, stats.dropped) == (20, 0) and all(i.unjoined == 0 for i in stats.inputs)


def test_a_backlog_joined_latest_wins_hands_out_the_newest_set_and_counts_the_rest():
    synced = synced_over_backlog(latest=True)
    pair = synced.take()
    assert {name: m.header.seq for name, m in pair.items()} == {"left": 19, "right": 19}
    assert synced.take() is None
    stats = synced.stats()
    assert (stats.by, stats.sets, stats.dropped) == ("seq", 20, 19)
    assert [(i.name, i.key, i.received, i.joined, i.unjoined) for i in stats.inputs] == [
        ("left", "l", 20, 20, 0), ("right", "r", 20, 20, 0)]
