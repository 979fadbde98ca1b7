"""Static data for a subscriber that comes late: what was published once is asked for on its queryable.

A node publishes its static data (``protocol.keys.Keys.latched``: static transforms, image targets) once
and answers queries on the same key with it. A subscriber that may come after that publication (a recorder
or a viewer started while the rig runs) asks, as it subscribes, for the static keys its expression covers
and takes the answers as it takes what is published: ``ask_latched`` hands each to the subscriber's own
``offer``. A subscriber there before the publication gets the data twice, published and answered: the same
description, which a reader keeps once.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import zenoh

from services.bus.shm import received_bytes


def ask_latched(session: zenoh.Session, subscribed: str, latched: Iterable[str],
                offer: Callable[[str, bytes], object]) -> list[str]:
    """Query, without waiting, each expression of ``latched`` that intersects ``subscribed``; every answer on a
    key that ``subscribed`` includes goes to ``offer(key, payload)`` as it comes (on Zenoh's thread), one per
    replier. Returns the expressions queried."""
    wanted = zenoh.KeyExpr(subscribed)

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is not None and wanted.includes(reply.ok.key_expr):
            offer(str(reply.ok.key_expr), received_bytes(reply.ok.payload))

    asked = [expression for expression in latched if wanted.intersects(zenoh.KeyExpr(expression))]
    for expression in asked:
        session.get(expression, on_reply, consolidation=zenoh.ConsolidationMode.NONE)
    return asked
