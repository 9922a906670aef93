"""Helpers the tests share: simulated and synthetic scans, a private mosquitto, the agent
in a subprocess, librealsense playback. Imported as `tests.support.<module>`."""
