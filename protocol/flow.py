"""Flow control of finite sources: acknowledgements (credits) and end-of-stream messages.

A finite source (files, a recording, a scene with a frame count) runs lossless by default: it
sends frame ``N + window`` only once every node that takes its frames has acknowledged frame
``N`` with a ``FlowAck`` on ``node/<name>/ack``. When a source has sent its last frame it
publishes a ``FlowEnd`` on ``node/<name>/end`` carrying the last ``seq`` it sent; every other
node publishes its own ``FlowEnd`` once it has the ends of all the nodes it reads from, has
received everything they say they published and has dealt with it, so a job ends exactly when
the last node is done.

Header: ``stamp_ns`` is the wall-clock time the message was made; ``seq`` is 0.
"""

from __future__ import annotations

from pydantic import Field

from protocol.message import Message


class FlowAck(Message):
    """Node ``node`` has dealt with (processed, or counted as dropped) every frame up to ``seq``.

    ``seq`` -1 says the node is ready (its inputs are subscribed) and has taken no frame yet.
    ``started_ns`` (wall clock) tells one run of the node from the next: a node restarted after a
    crash starts again at -1, having missed what was sent while it was down.
    """

    SCHEMA = "artrack.FlowAck"
    VERSION = 1

    node: str
    seq: int = Field(ge=-1)
    started_ns: int = Field(ge=0)


class FlowEnd(Message):
    """Node ``node`` is done: its sources ended with frame ``last_seq`` (-1: none was sent) and it has
    dealt with every frame up to it. ``frames`` counts the frames a source sent (0 for other nodes);
    ``published`` the messages the node put on each of its keys (full key expressions), so a node
    downstream knows when it has received all of them, whatever order they travel in."""

    SCHEMA = "artrack.FlowEnd"
    VERSION = 1

    node: str
    last_seq: int = Field(ge=-1)
    frames: int = Field(default=0, ge=0)
    published: dict[str, int] = Field(default_factory=dict)
