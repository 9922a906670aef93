"""Orchestration: the one scan path every command shares, the daemon's pipeline, the daemon,
batch processing, live-session control and systemd notification."""
