"""The garbage collector's settling at a node's start."""

from __future__ import annotations

import gc

from services.runtime.memory import settle_heap


def test_settle_heap_leaves_the_objects_alive_at_start_out_of_later_collections():
    gc.unfreeze()
    try:
        marker = ["built", "at start"]
        assert gc.get_freeze_count() == 0 and gc.is_tracked(marker)
        settle_heap()
        frozen = gc.get_freeze_count()
        assert frozen > 1000  # a test process's modules, classes and functions at least
        assert not any(obj is marker for obj in gc.get_objects())  # no generation holds it any more
        later = ["built", "after"]
        assert any(obj is later for obj in gc.get_objects())  # new objects are collected as ever
        gc.collect()
        assert gc.get_freeze_count() == frozen  # a full collection walks none of them
    finally:
        gc.unfreeze()
