"""silo-agent: grain silo inventory from RealSense depth cameras (BICM reconstruction, MQTT)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("silo-agent")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+source"
