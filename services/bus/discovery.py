"""What is on the bus: live nodes (liveliness tokens) and their state (queryables).

Used by client apps and by ``artrack list`` / ``status`` alike.
"""

from __future__ import annotations

import threading
import time
from typing import TypeVar

import zenoh

from protocol.codec import DecodeError, decode
from protocol.keys import Keys
from protocol.message import Message
from protocol.system import ClientState, NodeStats

M = TypeVar("M", bound=Message)


def live_nodes(session: zenoh.Session, keys: Keys, timeout_s: float) -> list[tuple[str, str]]:
    """``(rig, name)`` of every node holding a liveliness token in the namespace.

    Listens for ``timeout_s``: a session that has just opened learns of existing tokens
    only as its links come up, so a one-shot query right after opening can miss them.
    """
    found: set[tuple[str, str]] = set()
    lock = threading.Lock()

    def on_token(sample: zenoh.Sample) -> None:
        node = keys.split_node(str(sample.key_expr))
        with lock:
            (found.add if sample.kind == zenoh.SampleKind.PUT else found.discard)(node)

    subscriber = session.liveliness().declare_subscriber(keys.all_nodes(), on_token, history=True)
    try:
        time.sleep(timeout_s)
    finally:
        subscriber.undeclare()
    with lock:
        return sorted(found)


def token_held(session: zenoh.Session, key: str, timeout_s: float) -> bool:
    """Whether some session holds a liveliness token at ``key`` now (one query, answered within ``timeout_s``)."""
    return any(reply.ok is not None for reply in session.liveliness().get(key, timeout=timeout_s))


def every_answer(session: zenoh.Session, selector: str, cls: type[M], timeout_s: float,
                 payload: bytes | None = None) -> list[tuple[str, M]]:
    """``(key, message)`` of every reply of type ``cls`` to a query on ``selector`` (carrying ``payload``
    when given), one per replier even when several answer on the same key; other replies are skipped."""
    found: list[tuple[str, M]] = []
    for reply in session.get(selector, timeout=timeout_s, payload=payload,
                             consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is None:
            continue
        try:
            message = decode(reply.ok.payload.to_bytes())
        except DecodeError:
            continue
        if isinstance(message, cls):
            found.append((str(reply.ok.key_expr), message))
    return found


def answers(session: zenoh.Session, selector: str, cls: type[M], timeout_s: float,
            payload: bytes | None = None) -> dict[str, M]:
    """Key -> message of the replies of type ``cls`` to a query on ``selector`` (carrying ``payload``
    when given): one per key; other replies are skipped."""
    return dict(every_answer(session, selector, cls, timeout_s, payload))


def first_answers(session: zenoh.Session, selector: str, cls: type[M], timeout_s: float,
                  payload: bytes | None = None) -> dict[str, M]:
    """``answers``, asked again until some come or ``timeout_s`` is over.

    A session that has just opened may not yet know the queryables its router knows: a
    query then ends at once, empty, though an answer was there to have.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        found = answers(session, selector, cls, max(0.05, deadline - time.monotonic()), payload)
        if found or time.monotonic() >= deadline:
            return found
        time.sleep(0.05)


def node_states(session: zenoh.Session, keys: Keys, timeout_s: float) -> dict[tuple[str, str], NodeStats]:
    """The NodeStats every reachable node answers on its state queryable, by ``(rig, name)``."""
    return {keys.split_node(key): stats for key, stats in answers(session, keys.all_states(), NodeStats,
                                                                  timeout_s).items()}


def node_reports(session: zenoh.Session, keys: Keys, timeout_s: float) -> list[tuple[tuple[str, str], NodeStats]]:
    """``((rig, name), NodeStats)`` of every node process that answers on its state queryable: two
    processes running under one name on one rig give two entries."""
    return [(keys.split_node(key), stats) for key, stats in every_answer(session, keys.all_states(), NodeStats,
                                                                         timeout_s)]


def client_states(session: zenoh.Session, keys: Keys, timeout_s: float) -> dict[tuple[str, str], ClientState]:
    """The ClientState every connected client app answers, by ``(rig, client id)``."""
    return {keys.split_client(key): state for key, state in answers(session, keys.all_client_states(),
                                                                    ClientState, timeout_s).items()}
