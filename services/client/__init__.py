"""artrack's client library: what an app needs to follow tracked targets and look at the service.

Depends on ``protocol`` and zenoh only. ``connect()`` joins the bus with the same options as the
nodes; the ``Client`` it returns iterates poses (``poses``, ``poses_async``), calls back
(``on_pose``), answers the latest pose on demand (``latest``), and lists and queries services
(``services``, ``status``, ``calibration``). Apps never build key strings or decode bytes.
"""

from services.bus.security import Security
from services.bus.settings import BusError, BusSettings
from services.client.client import Client, connect
from services.client.streams import AsyncPoseStream, PoseStream, PoseUpdate

__all__ = ["AsyncPoseStream", "BusError", "BusSettings", "Client", "PoseStream", "PoseUpdate", "Security", "connect"]
