"""silo-agent: grain silo inventory from RealSense depth cameras (BICM reconstruction, MQTT)."""


def __getattr__(name: str) -> str:
    """`__version__`, read from the installed metadata on first use: importlib.metadata costs
    tens of milliseconds that a command which never shows the version should not pay."""
    if name != "__version__":
        raise AttributeError(f"module 'silo_agent' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        found = version("silo-agent")
    except PackageNotFoundError:  # running from a source tree that was never installed
        found = "0.0.0+source"
    globals()["__version__"] = found
    return found
