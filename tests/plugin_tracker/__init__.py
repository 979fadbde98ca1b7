"""Node kinds and a tracker that exist only here, found through ``ARTRACK_PLUGINS=tests.plugin_tracker``."""
