"""A process's part of the bus: what the nodes it runs share.

Every node runs on a ``Host``: one Zenoh session and one ``LocalBus``
(``services.bus.local``). A node alone in its process makes its own; the nodes of a process
group share one (``services.runtime.group``), so the messages between them pass by reference
and reach the bus only when another session subscribes.
"""

from __future__ import annotations

from services.bus.local import LocalBus
from services.bus.session import BusConfig, close_session, open_session


class Host:
    """One Zenoh session for ``bus`` (opened now, BusError when it cannot be) and the local deliveries."""

    def __init__(self, bus: BusConfig):
        self.bus = bus
        self.session = open_session(bus)
        self.local = LocalBus()

    def close(self) -> None:
        """Send what the nodes put (``LocalBus.close``), then close the session and let its callbacks' threads
        end (``close_session``)."""
        self.local.close()
        close_session(self.session)
