"""Bounds on what one input may ask of the machine, in one place (docs/limits.md lists them).

A config or scan past a bound is refused with an error naming it, before any large allocation:
a region at a fine grid step, or a cloud file that never ends, must not exhaust memory or hang.
"""

MAX_GRID_CELLS = 4_000_000  # region bounding box / grid_step_m^2: a 40 m square at 2 cm
MAX_CLOUD_POINTS = 10_000_000  # one camera's cloud (a D455 frame has 0.4 million pixels)
MAX_SCAN_POINTS = 16_000_000  # all cameras of one scan together: 8 cameras of 2 million
MAX_PLY_HEADER_BYTES = 64 * 1024  # a PLY header longer than this is not a point cloud
MAX_MANIFEST_BYTES = 16 * 1024 * 1024  # scan.json (it carries the config snapshot)
MAX_CONFIG_BYTES = MAX_MANIFEST_BYTES  # a config file: it must fit in a scan's manifest
MAX_COORDINATE_M = 100_000.0  # |translation| of an extrinsic: far beyond any silo, within float32
MAX_DURATION_S = 366 * 24 * 3600.0  # any configured interval or timeout: at most a year
MAX_CALIBRATION_CAPTURES = 20  # calibrate --captures: each a scan kept (4-8 pool the noise)
MAX_REQUEST_ID_CHARS = 128  # a command's request_id, echoed in every reply
MAX_COMMAND_BYTES = 65536  # a command's payload (P/cmd/scan, P/cmd/live): a few hundred at most
MAX_TOPIC_PREFIX_BYTES = 1024  # topic_prefix, discovery_prefix: MQTT allows 65,535 per topic
MIN_LIVE_RATE_HZ = 0.01  # a live map at least every 100 s: a slower rate is no live map at all
MAX_WAITING_REQUESTS = 10  # scan requests waiting for the next scan (they share it)


class LimitExceeded(ValueError):
    """An input past one of the bounds above; the message names the input and the bound."""
