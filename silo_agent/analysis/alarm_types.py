"""The alarm types the domain evaluates: the one list every output (Sparkplug, Home Assistant,
Prometheus, MQTT topics) declares."""

# Alarm types every consumer can count on (Sparkplug NBIRTH and HA declare them up front);
# others may appear and are added as they are seen.
ALARM_TYPES = (
    "collapse",
    "level_high",
    "level_low",
    "change",
    "camera",
    "coverage",
    "cache",
    "calibration",
)
