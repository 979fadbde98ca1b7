"""The bus: Zenoh session settings, transport, security, discovery, and typed publishing and
subscribing with stream statistics. Below both the node runtime and the client library; it
knows nothing of nodes."""
