"""Meshroom nodes of nplps (loaded by Meshroom from MESHROOM_PLUGINS_PATH)."""
