"""One MQTT connection and the state of its current session, shared by the transport that
opens it, the pump that feeds it outbox rows and the session messages sent on it directly.

The JSON link carries the agent's own topics (kinds `json` and `binary`); the Sparkplug link,
a second connection because MQTT allows one Last Will per connection, carries kind
`sparkplug`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import paho.mqtt.client as mqtt

KIND_JSON = "json"
KIND_BINARY = "binary"
KIND_SPARKPLUG = "sparkplug"
JSON_LINK = "json"
SPARKPLUG_LINK = "sparkplug"
HEIGHTMAP_CONTENT_TYPE = "application/vnd.silo-agent.heightmap;version=2"


@dataclass
class Link:
    """One MQTT connection (JSON or Sparkplug) and the state of its current session."""

    name: str
    kinds: tuple[str, ...]
    client: mqtt.Client | None = None
    retry_at: float = 0.0
    delay: float = 0.0
    connected: bool = False
    refused: str | None = None
    connected_at: float = 0.0
    max_packet: int | None = None  # the broker's Maximum Packet Size (MQTT 5 CONNACK)
    will_seq: int = 0  # seq of the Last Will of the JSON link, above all the session sends
    probing: bool = False  # one message in flight at a time, to find one the broker drops us over
    suspect: tuple[int, int] = (0, 0)  # (row id, probing sessions in a row it ended in flight)
    last_id: int = 0
    inflight: dict[int, tuple[int, str]] = field(default_factory=dict)
    direct: dict[int, str] = field(default_factory=dict)
    acked: set[int] = field(default_factory=set)
    acked_rows: list[int] = field(default_factory=list)
    bd_seq: int = 0
    born: bool = False
    declared: frozenset[str] = frozenset()  # the metrics of the session's last NBIRTH
    spb_seq: int = 0

    def reset_session(self) -> None:
        self.connected = False
        self.refused = None
        self.max_packet = None
        self.last_id = 0
        self.inflight.clear()
        self.direct.clear()
        self.acked.clear()
        self.born = False
        self.declared = frozenset()
        self.spb_seq = 0

    def publish_direct(self, topic: str, payload: bytes, *, retain: bool, qos: int = 1) -> int:
        """Publish outside the outbox (a message of this session only); its mid lands in
        `acked` once the broker has it."""
        assert self.client is not None
        info = self.client.publish(topic, payload, qos=qos, retain=retain)
        self.direct[info.mid] = topic
        return info.mid
