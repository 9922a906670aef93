"""What every MQTT session announces outside the outbox, and the state it announces.

On each (re)connection and whenever it changes: the retained `P/status`, the retained state of
every alarm type, the Home Assistant discovery config, the latest live height map, and on the
Sparkplug link the NBIRTH (when the primary host, if one is named, is online). The producers
(`Telemetry.publish_*`, any thread) change `NodeState` under its lock and mark what is dirty;
the network thread sends it.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import structlog
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from silo_agent.analysis.alarm_types import ALARM_TYPES, AlarmEvent, idle_alarm
from silo_agent.config import MqttConfig
from silo_agent.telemetry import homeassistant, sparkplug
from silo_agent.telemetry.link import HEIGHTMAP_CONTENT_TYPE, JSON_LINK, Link
from silo_agent.telemetry.outbox import Outbox
from silo_agent.telemetry.payloads import (
    AgentState,
    CameraState,
    Envelope,
    OutboxState,
    StatusPayload,
    alarm_payload,
)
from silo_agent.telemetry.pump import publish_packet_size

log = structlog.get_logger(__name__)


def live_too_large(size: int, max_packet: int | None) -> str | None:
    """Why a live map packet of `size` bytes cannot go to a broker whose Maximum Packet Size
    is `max_packet` (MQTT 5 CONNACK), or None."""
    if max_packet is None or size <= max_packet:
        return None
    return (
        f"live map of {size:,} bytes is larger than the broker's Maximum Packet Size "
        f"({max_packet:,} bytes): use a coarser live.grid_step_m or raise the broker's limit"
    )


@dataclass(frozen=True)
class LiveMapSend:
    """A live map waiting for the network thread."""

    payload: bytes
    stale_after: float  # monotonic: not sent by then (or a period after it may go), dropped
    qos: int
    period_s: float  # the least time between two maps on the wire


@dataclass
class NodeState:
    """What `P/status`, the alarm states, HA discovery and the births report, and which of
    them a session must send again; every field is guarded by `lock`."""

    cameras: dict[str, CameraState]
    expire_after_s: int | None  # how long HA keeps showing a reading without a new one
    lock: threading.Lock = field(default_factory=threading.Lock)
    last_scan_id: str | None = None
    # the last scan, if it gave no result: {scan_id, captured_at, reason} (the page says so)
    last_failure: dict[str, str | None] | None = None
    alarm_types: list[str] = field(default_factory=lambda: list(ALARM_TYPES))
    alarm_states: dict[str, AlarmEvent] = field(
        default_factory=lambda: {t: idle_alarm(t) for t in ALARM_TYPES}
    )
    live_map: LiveMapSend | None = None
    live_refused: str | None = None  # why the last live map could not be sent
    status_dirty: bool = False
    alarms_dirty: bool = False
    ha_dirty: bool = False
    rebirth: bool = False


@dataclass(frozen=True)
class Identity:
    """Who the agent is on the broker: its topics and the names its messages carry."""

    base: str
    silo_id: str
    version: str
    client_id: str
    spb_topics: sparkplug.Topics

    def topic(self, suffix: str) -> str:
        return f"{self.base}/{suffix}"


class Session:
    """Sends the session messages of `NodeState` on each link (the transport's SessionHooks;
    Home Assistant and Sparkplug host events come from the command dispatcher)."""

    def __init__(
        self,
        cfg: MqttConfig,
        me: Identity,
        outbox: Outbox,
        state: NodeState,
        spb_node: sparkplug.SparkplugNode,
    ) -> None:
        self.cfg = cfg
        self.me = me
        self.outbox = outbox
        self.state = state
        self.spb_node = spb_node
        self._host_online = False
        self._host_ts = -1
        self._waiting_since = -1.0  # connected_at of the session that logged its wait
        self._live_sent = -float("inf")  # monotonic time the last live map went out

    def status_payload(self, state: AgentState, env: Envelope) -> StatusPayload:
        pending, _ = self.outbox.size()
        with self.state.lock:
            cameras = list(self.state.cameras.values())
            last_scan_id = self.state.last_scan_id
        return StatusPayload(
            **env.model_dump(),
            state=state,
            version=self.me.version,
            client_id=self.me.client_id,
            cameras=cameras,
            last_scan_id=last_scan_id,
            outbox=OutboxState(
                pending=pending,
                dropped=self.outbox.counter("dropped"),
                rejected=self.outbox.counter("rejected"),
                dead_lettered=self.outbox.counter("dead_lettered"),
            ),
        )

    def status(self, state: AgentState, env: Envelope) -> bytes:
        return self.status_payload(state, env).to_bytes()

    def connected(self, link: Link) -> None:
        if link.name == JSON_LINK:
            with self.state.lock:
                self.state.status_dirty = True
                self.state.alarms_dirty = True
                self.state.ha_dirty = self.cfg.homeassistant.enabled

    def outbox_changed(self) -> None:
        with self.state.lock:
            self.state.status_dirty = True

    def homeassistant_online(self) -> None:
        """HA restarted: it forgets discovery and retained states it did not keep."""
        with self.state.lock:
            self.state.ha_dirty = True
            self.state.alarms_dirty = True

    def rebirth_requested(self) -> None:
        with self.state.lock:
            self.state.rebirth = True

    def host_state(self, link: Link, online: bool, stamp: int) -> None:
        """The Sparkplug primary host's STATE; an older one than the last seen is ignored."""
        if stamp < self._host_ts:
            return
        self._host_ts = stamp
        self._host_online = online
        if not online and link.born and link.client is not None:
            # Sparkplug 3.0: when the primary host goes offline the edge node says NDEATH and
            # reconnects; the next session (new bdSeq) births when the host is back.
            log.warning("Sparkplug primary host offline, NDEATH and reconnect")
            link.client.publish(
                self.me.spb_topics.node("NDEATH"),
                sparkplug.SparkplugNode.death(link.bd_seq),
                qos=1,
            )
            link.refused = "primary host went offline"

    def serve(self, link: Link) -> bool:
        if link.name == JSON_LINK:
            self._serve_json(link)
            return True
        return self._serve_sparkplug(link)

    def _serve_json(self, link: Link) -> None:
        state = self.state
        with state.lock:
            status_dirty, state.status_dirty = state.status_dirty, False
            ha_dirty, state.ha_dirty = state.ha_dirty, False
            alarms_dirty, state.alarms_dirty = state.alarms_dirty, False
        if status_dirty:
            self._publish_status(link, "online")
        if ha_dirty and self.cfg.homeassistant.enabled:
            self._publish_discovery(link)
        if alarms_dirty:
            self._publish_alarm_states(link)
        self._send_live(link)

    def _serve_sparkplug(self, link: Link) -> bool:
        """Birth when allowed and asked (or not born yet); rows only follow a birth."""
        with self.state.lock:
            rebirth, self.state.rebirth = self.state.rebirth, False
        may_birth = self.cfg.sparkplug.primary_host_id is None or self._host_online
        if may_birth and (rebirth or not link.born):
            self._publish_birth(link)
            return link.born
        if rebirth:
            with self.state.lock:
                self.state.rebirth = True  # keep it for when the host is back
        if not may_birth and not link.born and self._waiting_since != link.connected_at:
            # once per session: an operator who sees no NBIRTH learns why
            self._waiting_since = link.connected_at
            log.info(
                "Sparkplug waiting for the primary host to be online before NBIRTH",
                primary_host_id=self.cfg.sparkplug.primary_host_id,
            )
        return link.born

    def live_packet(self, payload: bytes, qos: int) -> tuple[str, Properties | None, int]:
        """Topic, MQTT 5 properties and packet size of a live map."""
        props = None
        if self.cfg.protocol == "5":
            props = Properties(PacketTypes.PUBLISH)
            props.ContentType = HEIGHTMAP_CONTENT_TYPE
        topic = self.me.topic("heightmap/live")
        return topic, props, publish_packet_size(topic, payload, qos, props, props is not None)

    def _send_live(self, link: Link) -> None:
        """The newest live map, unless stale; held while the previous one went out less than
        a period ago (the network thread's turns vary: maps must not bunch up on the wire)."""
        now = time.monotonic()
        with self.state.lock:
            live = self.state.live_map
            if live is None or now < self._live_sent + live.period_s:
                return
            self.state.live_map = None
        if now > max(live.stale_after, self._live_sent + 2 * live.period_s):
            return  # not sent within a period of when it could go: stale
        assert link.client is not None
        topic, props, size = self.live_packet(live.payload, live.qos)
        problem = live_too_large(size, link.max_packet)
        if problem is not None:  # the broker would close the connection over it
            with self.state.lock:
                self.state.live_refused = problem
            return
        link.client.publish(topic, live.payload, qos=live.qos, retain=False, properties=props)
        self._live_sent = now

    def _publish_status(self, link: Link, state: AgentState) -> int:
        payload = self.status(state, self.outbox.next_envelope())
        return link.publish_direct(self.me.topic("status"), payload, retain=True)

    def _publish_alarm_states(self, link: Link) -> None:
        """The current state of every alarm type, retained, so a fresh subscriber (HA) never
        shows an alarm as unknown; the outbox sends later changes after these."""
        with self.state.lock:
            states = list(self.state.alarm_states.values())
        for event in states:
            payload = alarm_payload(self.outbox.next_envelope(), event).to_bytes()
            link.publish_direct(self.me.topic(f"alarm/{event.type}"), payload, retain=True)

    def _publish_discovery(self, link: Link) -> None:
        ha = self.cfg.homeassistant
        with self.state.lock:
            alarm_types = list(self.state.alarm_types)
            expire_after_s = self.state.expire_after_s
        topic, payload = homeassistant.discovery_config(
            discovery_prefix=ha.discovery_prefix,
            base_topic=self.me.base,
            silo_id=self.me.silo_id,
            version=self.me.version,
            alarm_types=alarm_types,
            expire_after_s=expire_after_s,
        )
        link.publish_direct(topic, payload, retain=True)
        log.info("Home Assistant discovery published", topic=topic)

    def _publish_birth(self, link: Link) -> None:
        with self.state.lock:
            payload = self.spb_node.birth(link.bd_seq)
            link.declared = frozenset(self.spb_node.datatypes)
        link.publish_direct(self.me.spb_topics.node("NBIRTH"), payload, retain=False, qos=0)
        link.born = True
        link.spb_seq = 0
        log.info("Sparkplug NBIRTH", bd_seq=link.bd_seq)
