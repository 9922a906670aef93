"""MQTT telemetry: the topic contract (payloads.py), the height-map wire format
(heightmap_codec.py), the durable outbox (outbox.py), the client (mqtt.py), Sparkplug B
(sparkplug.py) and Home Assistant discovery (homeassistant.py). See docs/mqtt.md."""
