"""The MQTT connections and the network thread that owns them: connecting with back-off,
credentials and TLS, the Last Wills, paho's callbacks, and per loop turn the session messages
(asked of the layer above) and then the outbox rows (the pump).

The paho client is recreated for every connection attempt: paho would otherwise re-send its
own in-flight copies after a reconnect, out of step with the outbox (which re-sends every
unacknowledged row itself, oldest first, with its original msg_id, seq and ts).

Sparkplug runs on a second MQTT connection because MQTT allows one Last Will per connection
and both `P/status` = offline and the Sparkplug NDEATH must be wills. The NDEATH will of each
attempt carries the outbox's current bdSeq; only a CONNACK accepting the session advances it,
so failed attempts reuse it and the sessions a host sees are numbered one apart.

`by_hand` (`silo-agent publish` and `flush`): the JSON link alone, sending outbox rows and
nothing else: no Last Will, no `stopped`, no session messages, no subscriptions. `P/status`,
the alarm states, Home Assistant and the Sparkplug session are the agent's; the Sparkplug rows
wait in the outbox for its next session, which births before it sends them.
"""

from __future__ import annotations

import random
import socket
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol

import paho.mqtt.client as mqtt
import structlog
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.properties import Properties

from silo_agent.config import MqttConfig
from silo_agent.config.mqtt import read_secret
from silo_agent.telemetry import sparkplug
from silo_agent.telemetry.link import (
    JSON_LINK,
    KIND_BINARY,
    KIND_JSON,
    KIND_SPARKPLUG,
    SPARKPLUG_LINK,
    Link,
)
from silo_agent.telemetry.outbox import Outbox
from silo_agent.telemetry.payloads import AgentState, Envelope
from silo_agent.telemetry.pump import Pump

log = structlog.get_logger(__name__)

LOOP_TIMEOUT_S = 0.01
Subscriptions = Mapping[str, list[tuple[str, int]]]  # link name -> (topic filter, QoS)


@dataclass(frozen=True)
class Credentials:
    """The broker password and the TLS key's passphrase, read once at start."""

    password: str | None
    key_password: str | None

    @classmethod
    def from_config(cls, cfg: MqttConfig) -> Credentials:
        tls = cfg.tls
        return cls(
            password=read_secret(cfg.password_file, cfg.password_env, "mqtt.password"),
            key_password=(
                read_secret(tls.key_password_file, tls.key_password_env, "mqtt.tls.key_password")
                if tls
                else None
            ),
        )


class SessionHooks(Protocol):
    """What the transport asks of the layer above: the messages of each session."""

    def status(self, state: AgentState, env: Envelope) -> bytes:
        """The `P/status` payload in `state` (the Last Will says offline, a stop stopped)."""

    def connected(self, link: Link) -> None:
        """A new session on `link`: what it announces must be sent again."""

    def serve(self, link: Link) -> bool:
        """One loop turn on a connected link: send the session messages; False holds back
        the outbox rows (a Sparkplug link before its birth)."""

    def outbox_changed(self) -> None:
        """A row left the outbox unsent: `P/status` must report the new counters."""


class Transport:
    """The JSON link (and the Sparkplug link if enabled), served by `run()` in one thread.
    Messages arriving on either link go to `on_message`."""

    def __init__(
        self,
        cfg: MqttConfig,
        client_id: str,
        credentials: Credentials,
        outbox: Outbox,
        *,
        status_topic: str,
        spb_topics: sparkplug.Topics,
        subscriptions: Subscriptions,
        session: SessionHooks,
        on_message: Callable[[Link, mqtt.MQTTMessage], None],
        by_hand: bool = False,
    ) -> None:
        self.cfg = cfg
        self.by_hand = by_hand
        self.client_id = client_id
        self.credentials = credentials
        self.outbox = outbox
        self.status_topic = status_topic
        self.spb_topics = spb_topics
        self.subscriptions = subscriptions
        self.session = session
        self.on_message = on_message
        self.pump = Pump(cfg, outbox, session.outbox_changed)
        self.stopping = threading.Event()
        self.links = [Link(JSON_LINK, (KIND_JSON, KIND_BINARY))]
        if not cfg.sparkplug.enabled:  # rows left by a run with Sparkplug on: never to be sent
            outbox.discard_kind(KIND_SPARKPLUG)
        elif not by_hand:  # by hand they wait for the agent's Sparkplug session
            self.links.append(Link(SPARKPLUG_LINK, (KIND_SPARKPLUG,)))
        for link in self.links:
            link.delay = cfg.reconnect_min_s

    def run(self) -> None:
        """The network thread: until `stopping` is set and the outbox is drained (or
        shutdown_timeout_s has passed), then `stopped`, NDEATH and disconnect."""
        deadline: float | None = None
        while True:
            if self.stopping.is_set():
                if deadline is None:
                    deadline = time.monotonic() + self.cfg.shutdown_timeout_s
                if self._drained() or time.monotonic() >= deadline:
                    break
            self.outbox.tend()
            for link in self.links:
                try:
                    self._step(link)
                except Exception:  # a bug must not end publishing: log, reconnect, go on
                    log.exception("MQTT loop error", link=link.name)
                    self.drop(link, "internal error")
            if not any(link.client for link in self.links):
                self.stopping.wait(0.05)  # a stop ends the wait at once
        self._shutdown()

    def drop(self, link: Link, reason: str) -> None:
        """Close `link` after an error (or for a restart of the thread) and reconnect later;
        never raises, whatever state the error left the link in."""
        try:
            self._close(link, reason)
        except Exception:
            log.exception("MQTT connection could not be closed cleanly", link=link.name)
            link.client = None
            link.reset_session()
            self._schedule_retry(link, reason, quiet=True)

    def _drained(self) -> bool:
        json_link = self.links[0]
        return not json_link.connected or self.pump.drained(json_link)

    def _step(self, link: Link) -> None:
        now = time.monotonic()
        if link.client is None:
            if now >= link.retry_at and not self.stopping.is_set():
                self._open(link)
            return
        rc = link.client.loop(timeout=LOOP_TIMEOUT_S)
        self.pump.flush_acks(link)
        if link.refused is not None or rc != mqtt.MQTT_ERR_SUCCESS:
            reason = link.refused or mqtt.error_string(rc)
            self._close(link, reason)
            return
        if link.connected:
            self._serve(link)

    def _serve(self, link: Link) -> None:
        """Per loop turn on a connected link: session messages, then outbox rows."""
        if self.by_hand:
            self.pump.send(link)
            return
        if link.name == JSON_LINK and self.outbox.near_will_seq(link.will_seq):
            # the session is about to use the seq of its own Last Will: a new session arms
            # a higher one
            link.refused = "re-arming the Last Will above the seq in use"
            return
        if self.session.serve(link):
            self.pump.send(link)

    def _new_client(self, link: Link) -> mqtt.Client:
        v5 = self.cfg.protocol == "5"
        client_id = self.client_id if link.name == JSON_LINK else f"{self.client_id}-spb"
        client = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=client_id,
            protocol=mqtt.MQTTv5 if v5 else mqtt.MQTTv311,
            clean_session=None if v5 else True,
        )
        client.max_inflight_messages_set(self.cfg.max_inflight + 16)
        if self.cfg.username:
            client.username_pw_set(self.cfg.username, self.credentials.password)
        tls = self.cfg.tls
        if tls is not None:
            client.tls_set(
                ca_certs=str(tls.ca_file) if tls.ca_file else None,
                certfile=str(tls.cert_file) if tls.cert_file else None,
                keyfile=str(tls.key_file) if tls.key_file else None,
                keyfile_password=self.credentials.key_password,
            )
        if not self.by_hand:
            self._arm_will(link, client)
        client.on_connect = lambda c, u, f, rc, p: self._on_connect(link, rc, p)
        client.on_disconnect = lambda c, u, f, rc, p: self._on_disconnect(link, rc)
        client.on_publish = lambda c, u, mid, rc, p: self.pump.acknowledged(link, mid, rc)
        client.on_subscribe = lambda c, u, mid, rcs, p: self._on_subscribe(link, rcs)
        client.on_message = lambda c, u, msg: self.on_message(link, msg)
        return client

    def _arm_will(self, link: Link, client: mqtt.Client) -> None:
        """`P/status` = offline with a seq above all the session will send, or NDEATH with
        the session's bdSeq."""
        if link.name == JSON_LINK:
            link.will_seq = self.outbox.will_seq()
            will = self.session.status("offline", Envelope.new(link.will_seq))
            client.will_set(self.status_topic, will, qos=1, retain=True)
        else:
            link.bd_seq = self.outbox.bd_seq()
            will = sparkplug.SparkplugNode.death(link.bd_seq)
            client.will_set(self.spb_topics.node("NDEATH"), will, qos=1, retain=False)

    def _open(self, link: Link) -> None:
        link.reset_session()
        client = self._new_client(link)
        try:
            if self.cfg.protocol == "5":
                client.connect(self.cfg.host, self.cfg.port, self.cfg.keepalive_s, clean_start=True)
            else:
                client.connect(self.cfg.host, self.cfg.port, self.cfg.keepalive_s)
        except (OSError, ValueError) as exc:
            self._schedule_retry(link, f"cannot connect: {exc}")
            return
        sock = client.socket()
        if isinstance(sock, socket.socket):  # small PUBLISHes must not wait for Nagle + ACK
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        link.client = client

    def _close(self, link: Link, reason: str) -> None:
        self.pump.flush_acks(link)
        client, link.client = link.client, None
        if client is not None:
            client.disconnect()
        was_connected = link.connected
        if was_connected and link.name == JSON_LINK and not self.by_hand:
            self.outbox.pass_will()
        if was_connected and link.refused is None:  # not a reconnect of our own choosing
            self.pump.session_ended(link)
        if was_connected:
            log.warning(
                "connection to the broker lost",
                link=link.name,
                reason=reason,
                unacked=len(link.inflight),
            )
            link.delay = self.cfg.reconnect_min_s
        link.reset_session()
        self._schedule_retry(link, reason, quiet=was_connected)

    def _schedule_retry(self, link: Link, reason: str, quiet: bool = False) -> None:
        wait = link.delay * random.uniform(0.8, 1.2)
        link.retry_at = time.monotonic() + wait
        if not quiet:
            log.error(
                "MQTT connection failed, retrying",
                link=link.name,
                host=self.cfg.host,
                port=self.cfg.port,
                reason=reason,
                retry_in_s=round(wait, 2),
            )
        link.delay = min(link.delay * 2, self.cfg.reconnect_max_s)

    def _on_connect(
        self, link: Link, reason: mqtt.ReasonCode, properties: Properties | None
    ) -> None:
        if reason.is_failure:
            refused = f"broker refused the connection: {reason}"
            if reason.value in (0x86, 0x87, 4, 5):
                refused += (
                    f": authentication failed or not allowed, check mqtt.username"
                    f" ({self.cfg.username!r}) and its password"
                )
            link.refused = refused
            return
        if link.name == SPARKPLUG_LINK:  # this session has its bdSeq; the next takes bdSeq + 1
            self.outbox.advance_bd_seq()
        link.connected = True
        link.connected_at = time.time()
        link.max_packet = getattr(properties, "MaximumPacketSize", None)
        link.delay = self.cfg.reconnect_min_s
        client = link.client
        assert client is not None
        log.info("connected to the broker", link=link.name, host=self.cfg.host, port=self.cfg.port)
        if not self.by_hand:
            client.subscribe(self.subscriptions[link.name])
            self.session.connected(link)

    def _on_disconnect(self, link: Link, reason: mqtt.ReasonCode) -> None:
        if link.connected and reason.is_failure:
            log.warning("broker disconnected us", link=link.name, reason=str(reason))

    def _on_subscribe(self, link: Link, reasons: list[mqtt.ReasonCode]) -> None:
        for reason in reasons:
            if reason.is_failure:
                log.error("broker refused a subscription", link=link.name, reason=str(reason))

    def _shutdown(self) -> None:
        """`stopped` on P/status and NDEATH, each waited for briefly, then disconnect."""
        waiting: list[tuple[Link, int]] = []
        stopped: tuple[Link, int] | None = None
        for link in self.links:
            if link.client is None or not link.connected:
                continue
            if link.name == JSON_LINK and not self.by_hand:
                payload = self.session.status("stopped", self.outbox.next_envelope())
                stopped = (link, link.publish_direct(self.status_topic, payload, retain=True))
                waiting.append(stopped)
            elif link.born:
                death = sparkplug.SparkplugNode.death(link.bd_seq)
                waiting.append(
                    (link, link.publish_direct(self.spb_topics.node("NDEATH"), death, retain=False))
                )
        end = time.monotonic() + max(1.0, self.cfg.shutdown_timeout_s)
        while waiting and time.monotonic() < end:
            for link, _mid in waiting:
                if link.client is not None:
                    link.client.loop(timeout=LOOP_TIMEOUT_S)
                    self.pump.flush_acks(link)
            waiting = [(k, m) for k, m in waiting if m not in k.acked and k.client is not None]
        if stopped is not None and stopped[1] in stopped[0].acked:
            self.outbox.disarm_will()  # `stopped` is in; the clean disconnect drops the will
        for link in self.links:
            if link.client is not None:
                link.client.disconnect()
                link.client.loop(timeout=LOOP_TIMEOUT_S)
                self.pump.flush_acks(link)
                link.client = None
        log.info("MQTT stopped", pending=self.outbox.size()[0])
