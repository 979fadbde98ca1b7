"""Integration tests: real artrack processes talking over a real Zenoh router on loopback."""
