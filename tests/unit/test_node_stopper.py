"""``Stopper``: SIGINT/SIGTERM handled from before a process's nodes exist, since a node is live on the bus as
soon as it is made."""

from __future__ import annotations

import os
import signal

from services.runtime.node import Stopper


class Halting:
    """What ``Stopper`` asks of a node: ``stop``."""

    def __init__(self) -> None:
        self.stops = 0

    def stop(self) -> None:
        self.stops += 1


def test_a_signal_before_a_node_is_added_stops_it_as_it_is_added():
    stopper, first, second = Stopper(), Halting(), Halting()
    previous = signal.signal(signal.SIGTERM, stopper)
    try:
        os.kill(os.getpid(), signal.SIGTERM)  # the handler runs here, in the main thread, before any node exists
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert stopper.asked.is_set()
    stopper.add(first)
    stopper.add(second)
    assert (first.stops, second.stops) == (1, 1)


def test_a_signal_stops_every_node_added():
    stopper, nodes = Stopper(), [Halting(), Halting()]
    for node in nodes:
        stopper.add(node)
    assert [node.stops for node in nodes] == [0, 0]
    stopper()
    assert [node.stops for node in nodes] == [1, 1]
