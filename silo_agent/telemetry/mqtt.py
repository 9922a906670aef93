"""MQTT telemetry: the topic contract of docs/mqtt.md over paho-mqtt 2.x.

Producers (the scan pipeline, alarms) call `publish_*` from any thread; those calls only commit
to the durable outbox. One network thread owns the paho clients and does everything else:
connecting with back-off, sending outbox rows oldest first, deleting them on the broker's
PUBACK, answering commands, status, Sparkplug and Home Assistant.

The paho client is recreated for every connection attempt: paho would otherwise re-send its
own in-flight copies after a reconnect, out of step with the outbox (which re-sends every
unacknowledged row itself, oldest first, with its original msg_id, seq and ts).

Sparkplug runs on a second MQTT connection because MQTT allows one Last Will per connection
and both `P/status` = offline and the Sparkplug NDEATH must be wills.
"""

from __future__ import annotations

import json
import os
import random
import socket
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import paho.mqtt.client as mqtt
import structlog
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from pydantic import ValidationError

from silo_agent import __version__
from silo_agent.config import Config, ConfigError, MqttConfig, stale_after_s
from silo_agent.heightmap import HeightMap
from silo_agent.telemetry import homeassistant, sparkplug
from silo_agent.telemetry.heightmap_codec import encode_heightmap
from silo_agent.telemetry.live_command import LiveCommand, parse_live_request
from silo_agent.telemetry.outbox import WILL_SEQ_HEADROOM, Outbox, OutboxLimits, Row
from silo_agent.telemetry.payloads import (
    ALARM_TYPES,
    MAX_COMMAND_BYTES,
    CameraState,
    CommandReplyPayload,
    Envelope,
    OutboxState,
    ScanRequest,
    StatusPayload,
    alarm_payload,
    check_summary,
    describe_errors,
    idle_alarm,
    scan_payload,
    volume_payload,
)

log = structlog.get_logger(__name__)

KIND_JSON = "json"
KIND_BINARY = "binary"
KIND_SPARKPLUG = "sparkplug"
HEIGHTMAP_CONTENT_TYPE = "application/vnd.silo-agent.heightmap;version=2"
LOOP_TIMEOUT_S = 0.01
MAX_TOPIC_BYTES = 65535  # MQTT's two-byte string length
# After a session that ended within POISON_SESSION_S of connecting with messages unacknowledged,
# the next sessions send one message at a time ("probing"); a message that was the one in
# flight when POISON_STRIKES probing sessions in a row ended is one the broker will not take
# (a limit it does not announce, e.g. its maximum packet size under MQTT 3.1.1): dead-lettered.
POISON_STRIKES = 3
POISON_SESSION_S = 10.0


def reply_topic_problem(topic: str, reserved: Iterable[str], allowed: str) -> str | None:
    """Why a requested MQTT 5 Response Topic must not be published to, or None if it may.

    A topic paho or the broker refuses would sit at the head of the outbox; one among the
    agent's own (or Sparkplug / Home Assistant) topics would put reply JSON where consumers
    expect something else. `allowed`, the documented reply topic, is always fine."""
    if topic == allowed:
        return None
    if not topic:
        return "it is empty"
    if "+" in topic or "#" in topic:
        return "it contains a wildcard (+ or #)"
    if topic.startswith("$"):
        return "it starts with $ (reserved for the broker)"
    if "\x00" in topic:
        return "it contains a NUL character"
    try:
        size = len(topic.encode("utf-8"))
    except UnicodeEncodeError:
        return "it is not valid UTF-8"
    if size > MAX_TOPIC_BYTES:
        return f"it is {size} bytes long, MQTT allows {MAX_TOPIC_BYTES}"
    for space in reserved:
        if topic == space or topic.startswith(space + "/"):
            return f"it is under {space}/, where the agent publishes"
    return None


def publish_packet_size(topic: str, payload: bytes, qos: int, props: Properties | None,
                        v5: bool) -> int:
    """Bytes of the PUBLISH packet paho will send, to compare with the broker's maximum."""
    body = 2 + len(topic.encode("utf-8")) + (2 if qos else 0) + len(payload)
    if v5:
        body += len(props.pack()) if props is not None else 1
    length_bytes = 1 + sum(body >= limit for limit in (128, 16384, 2097152))
    return 1 + length_bytes + body


class CommandRejected(Exception):
    """Raised by a scan-request callback to answer the request with an error; `scan_id` names
    the scan it is about (e.g. the one running when the agent is busy)."""

    def __init__(self, message: str, scan_id: str | None = None) -> None:
        super().__init__(message)
        self.scan_id = scan_id


@dataclass(frozen=True)
class ScanCommand:
    """An accepted `P/cmd/scan` request, kept to send the final reply with the scan id."""

    request_id: str
    reply_topic: str
    correlation: bytes | None


@dataclass
class _Link:
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
        self.spb_seq = 0


def read_secret(file: Path | None, env: str | None, key: str) -> str | None:
    """A password from a file (first line) or an environment variable, never from the TOML."""
    if file is not None:
        try:
            return file.read_text(encoding="utf-8").splitlines()[0].strip()
        except (OSError, IndexError) as exc:
            raise ConfigError(f"{key}_file: cannot read a password from {file}: {exc}") from None
    if env is not None:
        value = os.environ.get(env)
        if value is None:
            raise ConfigError(f"{key}_env: environment variable {env} is not set")
        return value
    return None


class Telemetry:
    """The agent's MQTT side. `start()`, `publish_*`, `stop()`; see the module docstring."""

    def __init__(
        self,
        cfg: MqttConfig,
        silo_id: str,
        camera_serials: Iterable[str] = (),
        *,
        version: str = __version__,
        expire_after_s: int | None = None,
    ) -> None:
        """`expire_after_s`: how long HA keeps showing a reading without a new one."""
        self.cfg = cfg
        self.expire_after_s = expire_after_s
        self.silo_id = silo_id
        self.version = version
        self.base = f"{cfg.topic_prefix}/{silo_id}"
        self.client_id = cfg.client_id or f"silo-agent-{silo_id}"
        self.password = read_secret(cfg.password_file, cfg.password_env, "mqtt.password")
        tls = cfg.tls
        self.key_password = (
            read_secret(tls.key_password_file, tls.key_password_env, "mqtt.tls.key_password")
            if tls
            else None
        )
        self.outbox = Outbox(
            cfg.outbox_path,
            OutboxLimits(
                max_messages=cfg.outbox_max_messages,
                max_bytes=cfg.outbox_max_bytes,
                max_age_s=cfg.outbox_max_age_days * 86400.0,
            ),
        )
        self._lock = threading.Lock()
        self._cameras: dict[str, CameraState] = {
            s: CameraState(serial=s, state="unknown") for s in camera_serials
        }
        self._last_scan_id: str | None = None
        self._alarm_types: list[str] = list(ALARM_TYPES)
        self._alarm_states: dict[str, dict] = {t: idle_alarm(t) for t in ALARM_TYPES}
        self._status_dirty = False
        self._alarms_dirty = False
        self._ha_dirty = False
        self._rebirth = False
        self._host_online = False
        self._host_ts = -1
        self._scan_callback: Callable[[ScanCommand], None] | None = None
        self._live_callback: Callable[[LiveCommand], str] | None = None
        self._live_map: tuple[bytes, float, int] | None = None  # payload, stale after, QoS
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.spb = cfg.sparkplug
        self.spb_topics = sparkplug.Topics(self.spb.group_id, self.spb.edge_node_id or silo_id)
        self.spb_node = sparkplug.SparkplugNode(version, self._cameras)
        self._links = [_Link("json", (KIND_JSON, KIND_BINARY))]
        if self.spb.enabled:
            self._links.append(_Link("sparkplug", (KIND_SPARKPLUG,)))
        else:  # left over from a run with Sparkplug on: nobody would ever send them
            self.outbox.discard_kind(KIND_SPARKPLUG)
        for link in self._links:
            link.delay = cfg.reconnect_min_s
        self._report_outbox_damage()

    def _report_outbox_damage(self) -> None:
        """The `outbox` alarm: raised when a corrupt outbox was moved aside at open (what it
        held is lost), cleared at a later start once no moved-aside copy is left."""
        change = self.outbox.corrupt_alarm_change()
        if change is None:
            return
        aside = self.outbox.moved_aside
        message = (
            f"outbox database {self.outbox.path} was corrupt: moved aside to {aside.name},"
            " the messages queued in it were not sent; remove it once inspected"
            if aside is not None else "no corrupt outbox copy left"
        )
        self.publish_alarm({"type": "outbox", "state": change, "scan_id": None,
                            "severity": "warning", "message": message})

    @classmethod
    def from_config(cls, config: Config) -> Telemetry:
        return cls(config.mqtt, config.silo.id, [c.serial for c in config.cameras],
                   expire_after_s=stale_after_s(config.schedule, config.silo.timezone))

    # ------------------------------------------------------------ topics

    def topic(self, suffix: str) -> str:
        return f"{self.base}/{suffix}"

    # ------------------------------------------------------------ producer API

    def publish_result(self, summary: dict, heightmap: HeightMap | None = None) -> list[Envelope]:
        """Queue `P/scan`, `P/volume` (retained) and `P/heightmap` (retained) for one result."""
        check_summary(summary)
        blob = encode_heightmap(heightmap, summary["scan_id"]) if heightmap is not None else None
        envs = [
            self._enqueue_json("scan", lambda e: scan_payload(e, summary).to_bytes()),
            self._enqueue_json(
                "volume", lambda e: volume_payload(e, summary).to_bytes(), retain=True
            ),
        ]
        if blob is not None:
            envs.append(
                self._enqueue(
                    self.topic("heightmap"), lambda _e: blob, retain=True, kind=KIND_BINARY
                )
            )
        with self._lock:
            self._last_scan_id = summary["scan_id"]
            self._status_dirty = True
        if self.spb.enabled:
            with self._lock:
                raw, new_metric = self.spb_node.data_from_result(summary)
            self._enqueue_sparkplug(raw, new_metric)
        return envs

    def publish_scan_failure(self, summary: dict) -> Envelope:
        """Queue `P/scan` alone for a scan that produced no usable result (its
        `invalid_reason` says why): the retained `P/volume` and `P/heightmap` keep the last
        good values."""
        check_summary(summary)
        env = self._enqueue_json("scan", lambda e: scan_payload(e, summary).to_bytes())
        with self._lock:
            self._last_scan_id = summary["scan_id"]
            self._status_dirty = True
        return env

    def publish_alarm(self, event: dict) -> Envelope:
        """Queue an alarm event on `P/alarm` and the current state on `P/alarm/<type>`."""
        alarm_payload(Envelope.new(1), event)  # validate before anything is committed
        with self._lock:  # before the queue: a state snapshot must never be older than it
            self._alarm_states[event["type"]] = dict(event)
            if event["type"] not in self._alarm_types:
                self._alarm_types.append(event["type"])
                self._ha_dirty = True
        env = self._enqueue_json("alarm", lambda e: alarm_payload(e, event).to_bytes())
        self._enqueue_json(
            f"alarm/{event['type']}", lambda e: alarm_payload(e, event).to_bytes(), retain=True
        )
        if self.spb.enabled:
            with self._lock:
                raw, new_metric = self.spb_node.data_from_alarm(event)
            self._enqueue_sparkplug(raw, new_metric)
        return env

    def restore_alarms(self, active: Mapping[str, Mapping]) -> None:
        """The raised alarms persisted by the last run (type -> its `raised` event): every
        birth and state snapshot from now on carries them instead of `cleared`."""
        with self._lock:
            for alarm_type, event in active.items():
                self._alarm_states[alarm_type] = dict(event)
                if alarm_type not in self._alarm_types:
                    self._alarm_types.append(alarm_type)
                    self._ha_dirty = True
            self.spb_node.restore_alarms(active)
            self._alarms_dirty = True
            self._rebirth = True

    def set_expire_after(self, seconds: int | None) -> None:
        """A new schedule, a new staleness limit: HA gets the discovery config again."""
        with self._lock:
            if seconds != self.expire_after_s:
                self.expire_after_s = seconds
                self._ha_dirty = self.cfg.homeassistant.enabled

    def set_status(
        self,
        cameras: dict[str, tuple[str, str | None]] | None = None,
        last_scan_id: str | None = None,
    ) -> None:
        """Update what `P/status` reports: camera serial -> (state, error), last scan id."""
        changed: dict[str, str] = {}
        with self._lock:
            for serial, (state, error) in (cameras or {}).items():
                old = self._cameras.get(serial)
                self._cameras[serial] = CameraState(serial=serial, state=state, error=error)
                if old is None or old.state != state:
                    changed[serial] = state
            if last_scan_id is not None:
                self._last_scan_id = last_scan_id
            self._status_dirty = True
            if changed and self.spb.enabled:
                raw, new_metric = self.spb_node.data_from_cameras(changed)
            else:
                raw = None
        if raw is not None:
            self._enqueue_sparkplug(raw, new_metric)

    def on_scan_request(self, callback: Callable[[ScanCommand], None]) -> None:
        """Call `callback` (in the network thread: it must not block) for each valid request.

        Returning accepts the request; raising CommandRejected answers with its message.
        """
        self._scan_callback = callback

    def finish_scan_request(
        self, command: ScanCommand, scan_id: str | None = None, error: str | None = None
    ) -> None:
        """The later reply: the scan id of the requested scan, or why it failed."""
        self._reply(
            command.reply_topic, command.correlation, command.request_id,
            status="error" if error else "done", accepted=True, error=error, scan_id=scan_id,
        )

    def on_live_command(self, callback: Callable[[LiveCommand], str]) -> None:
        """Call `callback` (network thread, must not block) for each valid `P/cmd/live`; it
        returns the live session's id, or raises CommandRejected."""
        self._live_callback = callback

    def finish_live(self, command: LiveCommand, session_id: str, error: str | None) -> None:
        """The later reply: the live session ended (`error` if not as asked)."""
        self._reply(
            command.reply_topic, command.correlation, command.request.request_id,
            status="error" if error else "done", accepted=True, error=error, scan_id=session_id,
        )

    def publish_live(self, payload: bytes, max_age_s: float, qos: int = 0) -> None:
        """Send a live map on `P/heightmap/live` (not retained, not through the outbox): it
        replaces an unsent one, and is dropped if no connection takes it within max_age_s."""
        with self._lock:
            self._live_map = (payload, time.monotonic() + max_age_s, qos)

    def status(self) -> StatusPayload:
        """What `P/status` would say now (state online), e.g. for a health check."""
        return self._status_payload("online", Envelope.new(1))

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="mqtt", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Send what is pending (up to shutdown_timeout_s), `stopped`, NDEATH; disconnect."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.outbox.close()

    # ------------------------------------------------------------ enqueueing

    def _enqueue(
        self,
        topic: str,
        build: Callable[[Envelope | None], bytes],
        *,
        retain: bool = False,
        kind: str = KIND_JSON,
        correlation: bytes | None = None,
    ) -> Envelope:
        env = self.outbox.enqueue(
            topic, build, qos=1, retain=retain, latest=retain, kind=kind, correlation=correlation
        )
        assert env is not None
        return env

    def _enqueue_json(
        self, suffix: str, build: Callable[[Envelope], bytes], *, retain: bool = False
    ) -> Envelope:
        def build_env(env: Envelope | None) -> bytes:
            assert env is not None
            return build(env)

        return self._enqueue(self.topic(suffix), build_env, retain=retain)

    def _enqueue_sparkplug(self, raw: bytes, new_metric: bool) -> None:
        self.outbox.enqueue(
            self.spb_topics.node("NDATA"), lambda _e: raw, qos=0, kind=KIND_SPARKPLUG,
            with_envelope=False,
        )
        if new_metric:
            with self._lock:
                self._rebirth = True

    def _reply(
        self,
        topic: str,
        correlation: bytes | None,
        request_id: str | None,
        *,
        status: str,
        accepted: bool,
        error: str | None = None,
        scan_id: str | None = None,
    ) -> None:
        def build(env: Envelope | None) -> bytes:
            assert env is not None
            return CommandReplyPayload(
                **env.model_dump(), request_id=request_id, status=status, accepted=accepted,
                error=error, scan_id=scan_id,
            ).to_bytes()

        self._enqueue(topic, build, correlation=correlation)

    # ------------------------------------------------------------ network thread

    def _run(self) -> None:
        deadline: float | None = None
        while True:
            if self._stop.is_set():
                if deadline is None:
                    deadline = time.monotonic() + self.cfg.shutdown_timeout_s
                if self._drained() or time.monotonic() >= deadline:
                    break
            for link in self._links:
                try:
                    self._step(link)
                except Exception:  # a bug must not end publishing: log, reconnect, go on
                    log.exception("MQTT loop error", link=link.name)
                    self._close(link, "internal error")
            if not any(link.client for link in self._links):
                time.sleep(0.05)
        self._shutdown()

    def _drained(self) -> bool:
        json_link = self._links[0]
        if not json_link.connected:
            return True
        return not json_link.inflight and not self.outbox.pending(
            json_link.last_id, 1, json_link.kinds
        )

    def _step(self, link: _Link) -> None:
        now = time.monotonic()
        if link.client is None:
            if now >= link.retry_at and not self._stop.is_set():
                self._open(link)
            return
        rc = link.client.loop(timeout=LOOP_TIMEOUT_S)
        self._flush_acks(link)
        if link.refused is not None or rc != mqtt.MQTT_ERR_SUCCESS:
            reason = link.refused or mqtt.error_string(rc)
            self._close(link, reason)
            return
        if link.connected:
            self._serve(link)

    def _new_client(self, link: _Link) -> mqtt.Client:
        v5 = self.cfg.protocol == "5"
        client_id = self.client_id if link.name == "json" else f"{self.client_id}-spb"
        client = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=client_id,
            protocol=mqtt.MQTTv5 if v5 else mqtt.MQTTv311,
            clean_session=None if v5 else True,
        )
        client.max_inflight_messages_set(self.cfg.max_inflight + 16)
        if self.cfg.username:
            client.username_pw_set(self.cfg.username, self.password)
        tls = self.cfg.tls
        if tls is not None:
            client.tls_set(
                ca_certs=str(tls.ca_file) if tls.ca_file else None,
                certfile=str(tls.cert_file) if tls.cert_file else None,
                keyfile=str(tls.key_file) if tls.key_file else None,
                keyfile_password=self.key_password,
            )
        if link.name == "json":
            link.will_seq = self.outbox.will_seq()
            will = self._status_payload("offline", Envelope.new(link.will_seq)).to_bytes()
            client.will_set(self.topic("status"), will, qos=1, retain=True)
        else:
            link.bd_seq = self.outbox.next_bd_seq()
            will = sparkplug.SparkplugNode.death(link.bd_seq)
            client.will_set(self.spb_topics.node("NDEATH"), will, qos=1, retain=False)
        client.on_connect = lambda c, u, f, rc, p: self._on_connect(link, rc, p)
        client.on_disconnect = lambda c, u, f, rc, p: self._on_disconnect(link, rc)
        client.on_publish = lambda c, u, mid, rc, p: self._on_publish(link, mid, rc)
        client.on_subscribe = lambda c, u, mid, rcs, p: self._on_subscribe(link, rcs)
        client.on_message = lambda c, u, msg: self._on_message(link, msg)
        return client

    def _open(self, link: _Link) -> None:
        link.reset_session()
        client = self._new_client(link)
        try:
            if self.cfg.protocol == "5":
                client.connect(
                    self.cfg.host, self.cfg.port, self.cfg.keepalive_s, clean_start=True
                )
            else:
                client.connect(self.cfg.host, self.cfg.port, self.cfg.keepalive_s)
        except (OSError, ValueError) as exc:
            self._schedule_retry(link, f"cannot connect: {exc}")
            return
        sock = client.socket()
        if sock is not None:  # small PUBLISH packets must not wait for Nagle + delayed ACK
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        link.client = client

    def _flush_acks(self, link: _Link) -> None:
        """Delete acknowledged rows: one fsync'ed transaction per loop turn, not per PUBACK."""
        if link.acked_rows:
            self.outbox.ack(link.acked_rows)
            link.acked_rows.clear()

    def _close(self, link: _Link, reason: str) -> None:
        self._flush_acks(link)
        client, link.client = link.client, None
        if client is not None:
            client.disconnect()
        was_connected = link.connected
        if was_connected and link.name == "json":
            self.outbox.pass_will()
        if was_connected and link.refused is None:  # not a reconnect of our own choosing
            self._strike_head_row(link)
        if was_connected:
            log.warning(
                "connection to the broker lost", link=link.name, reason=reason,
                unacked=len(link.inflight),
            )
            link.delay = self.cfg.reconnect_min_s
        link.reset_session()
        self._schedule_retry(link, reason, quiet=was_connected)

    def _strike_head_row(self, link: _Link) -> None:
        """After a short session with messages unacknowledged, probe: send one at a time.
        A message that was the one in flight when POISON_STRIKES probing sessions in a row
        ended is dead-lettered, so that it cannot hold up the outbox for ever."""
        short = time.time() - link.connected_at <= POISON_SESSION_S
        if not link.inflight or not short:
            link.probing, link.suspect = False, (0, 0)
            return
        if link.probing:
            head = min(row_id for row_id, _topic in link.inflight.values())
            strikes = link.suspect[1] + 1 if link.suspect[0] == head else 1
            link.suspect = (head, strikes)
            if strikes >= POISON_STRIKES:
                row = self.outbox.row(head)
                if row is not None:
                    self._dead_letter(
                        link, row, f"the broker closed the connection each time it was sent"
                        f" ({strikes} sessions in a row)",
                    )
                link.suspect = (0, 0)
        link.probing = True

    def _schedule_retry(self, link: _Link, reason: str, quiet: bool = False) -> None:
        wait = link.delay * random.uniform(0.8, 1.2)
        link.retry_at = time.monotonic() + wait
        if not quiet:
            log.error(
                "MQTT connection failed, retrying", link=link.name, host=self.cfg.host,
                port=self.cfg.port, reason=reason, retry_in_s=round(wait, 2),
            )
        link.delay = min(link.delay * 2, self.cfg.reconnect_max_s)

    # ------------------------------------------------------------ callbacks

    def _on_connect(
        self, link: _Link, reason: mqtt.ReasonCode, properties: Properties | None
    ) -> None:
        if reason.is_failure:
            link.refused = f"broker refused the connection: {reason}"
            if reason.value in (0x86, 0x87, 4, 5):
                link.refused += (
                    f": authentication failed or not allowed, check mqtt.username"
                    f" ({self.cfg.username!r}) and its password"
                )
            return
        link.connected = True
        link.connected_at = time.time()
        link.max_packet = getattr(properties, "MaximumPacketSize", None)
        link.delay = self.cfg.reconnect_min_s
        client = link.client
        assert client is not None
        log.info("connected to the broker", link=link.name, host=self.cfg.host, port=self.cfg.port)
        if link.name == "json":
            subs = [(self.topic("cmd/scan"), 1), (self.topic("cmd/live"), 1)]
            ha = self.cfg.homeassistant
            if ha.enabled:
                subs.append((homeassistant.status_topic(ha.discovery_prefix), 1))
            client.subscribe(subs)
            with self._lock:
                self._status_dirty = True
                self._alarms_dirty = True
                self._ha_dirty = self.cfg.homeassistant.enabled
        else:
            subs = [(self.spb_topics.node("NCMD"), 0)]
            if self.spb.primary_host_id:
                subs.append((sparkplug.Topics.state(self.spb.primary_host_id), 1))
            client.subscribe(subs)

    def _on_disconnect(self, link: _Link, reason: mqtt.ReasonCode) -> None:
        if link.connected and reason.is_failure:
            log.warning("broker disconnected us", link=link.name, reason=str(reason))

    def _on_publish(self, link: _Link, mid: int, reason: mqtt.ReasonCode) -> None:
        queued = link.inflight.pop(mid, None)
        if queued is None:
            topic = link.direct.pop(mid, None)
            link.acked.add(mid)
            if topic is not None and reason.is_failure:
                log.error("broker refused a message", topic=topic, reason=str(reason))
            return
        row_id, topic = queued
        if reason.is_failure:
            log.error("broker refused a message, dropped", topic=topic, reason=str(reason))
            self.outbox.reject(row_id)
            with self._lock:
                self._status_dirty = True
        else:
            link.acked_rows.append(row_id)

    def _on_subscribe(self, link: _Link, reasons: list[mqtt.ReasonCode]) -> None:
        for reason in reasons:
            if reason.is_failure:
                log.error("broker refused a subscription", link=link.name, reason=str(reason))

    def _on_message(self, link: _Link, msg: mqtt.MQTTMessage) -> None:
        if msg.topic == self.topic("cmd/scan"):
            self._handle_scan_command(msg)
        elif msg.topic == self.topic("cmd/live"):
            self._handle_live_command(msg)
        elif self.cfg.homeassistant.enabled and msg.topic == homeassistant.status_topic(
            self.cfg.homeassistant.discovery_prefix
        ):
            if msg.payload.strip() == b"online":
                with self._lock:
                    self._ha_dirty = True
                    self._alarms_dirty = True
        elif msg.topic == self.spb_topics.node("NCMD"):
            if sparkplug.is_rebirth_request(msg.payload):
                log.info("Sparkplug rebirth requested")
                with self._lock:
                    self._rebirth = True
        elif self.spb.primary_host_id and msg.topic == sparkplug.Topics.state(
            self.spb.primary_host_id
        ):
            self._handle_host_state(link, msg.payload)

    def _handle_host_state(self, link: _Link, payload: bytes) -> None:
        try:
            state = json.loads(payload)
            online, stamp = bool(state["online"]), int(state["timestamp"])
        except (ValueError, KeyError, TypeError):
            log.warning("ignoring a malformed Sparkplug STATE message")
            return
        if stamp < self._host_ts:
            return
        self._host_ts = stamp
        self._host_online = online
        if not online and link.born and link.client is not None:
            # Sparkplug 3.0: when the primary host goes offline the edge node says NDEATH and
            # reconnects; the next session (new bdSeq) births when the host is back.
            log.warning("Sparkplug primary host offline, NDEATH and reconnect")
            link.client.publish(
                self.spb_topics.node("NDEATH"), sparkplug.SparkplugNode.death(link.bd_seq), qos=1
            )
            link.refused = "primary host went offline"

    def _reply_namespaces(self) -> list[str]:
        """Where replies must not go: every topic the agent (or a sibling agent) publishes."""
        spaces = [self.cfg.topic_prefix.rstrip("/") or self.base, sparkplug.NAMESPACE]
        if self.cfg.homeassistant.enabled:
            spaces.append(self.cfg.homeassistant.discovery_prefix.rstrip("/"))
        return spaces

    def _handle_scan_command(self, msg: mqtt.MQTTMessage) -> None:
        if msg.retain:
            # the broker replays a retained command at every subscribe: it would scan at
            # every start; the live delivery (retain flag clear) was already answered
            log.warning(
                "ignoring a retained scan request; clear it with an empty retained message",
                topic=msg.topic,
            )
            return
        props = getattr(msg, "properties", None)
        fallback = self.topic("cmd/scan/reply")
        reply_topic = getattr(props, "ResponseTopic", None) or fallback
        correlation = getattr(props, "CorrelationData", None)
        request_id: str | None = None
        error: str | None = None
        about: str | None = None
        if len(msg.payload) > MAX_COMMAND_BYTES:
            error = f"payload too large: {len(msg.payload)} bytes, limit {MAX_COMMAND_BYTES}"
        else:
            try:
                body = json.loads(msg.payload.decode("utf-8"))
            except UnicodeDecodeError as exc:
                error = f"payload is not UTF-8: {exc.reason} at byte {exc.start}"
            except ValueError as exc:
                error = f"invalid JSON: {exc}"
            else:
                if not isinstance(body, dict):
                    error = f"payload must be a JSON object, got {type(body).__name__}"
                else:
                    rid = body.get("request_id")
                    request_id = rid if isinstance(rid, str) and len(rid) <= 128 else None
                    try:
                        request = ScanRequest.model_validate(body)
                    except ValidationError as exc:
                        error = f"invalid request: {describe_errors(exc)}"
        topic_problem = reply_topic_problem(reply_topic, self._reply_namespaces(), fallback)
        if topic_problem is not None:  # answered where the requester can always listen
            error = f"response topic {reply_topic[:200]!r} refused: {topic_problem}"
            reply_topic = fallback
        if error is None:
            command = ScanCommand(request.request_id, reply_topic, correlation)
            callback = self._scan_callback
            if callback is None:
                error = "this agent does not take scan requests"
            else:
                try:
                    callback(command)
                except CommandRejected as exc:
                    error = str(exc) or "rejected"
                    about = exc.scan_id
        if error is not None:
            log.warning("scan request refused", request_id=request_id, error=error)
            self._reply(
                reply_topic, correlation, request_id, status="error", accepted=False, error=error,
                scan_id=about,
            )
        else:
            log.info("scan request accepted", request_id=request_id)
            self._reply(reply_topic, correlation, request_id, status="accepted", accepted=True)

    def _handle_live_command(self, msg: mqtt.MQTTMessage) -> None:
        props = getattr(msg, "properties", None)
        reply_topic = getattr(props, "ResponseTopic", None) or self.topic("cmd/live/reply")
        correlation = getattr(props, "CorrelationData", None)
        request_id = session_id = None
        try:
            request = parse_live_request(msg.payload)
            request_id = request.request_id
            if self._live_callback is None:
                raise CommandRejected("this agent does not run live sessions")
            session_id = self._live_callback(LiveCommand(request, reply_topic, correlation))
        except (ValueError, CommandRejected) as exc:
            log.warning("live request refused", request_id=request_id, error=str(exc))
            self._reply(reply_topic, correlation, request_id, status="error", accepted=False,
                        error=str(exc) or "rejected")  # fmt: skip
            return
        log.info("live request accepted", request_id=request_id, session=session_id)
        self._reply(reply_topic, correlation, request_id, status="accepted", accepted=True,
                    scan_id=session_id)  # fmt: skip

    # ------------------------------------------------------------ sending

    def _send_live(self, link: _Link) -> None:
        with self._lock:
            live, self._live_map = self._live_map, None
        if live is None or time.monotonic() > live[1]:
            return
        assert link.client is not None
        props = None
        if self.cfg.protocol == "5":
            props = Properties(PacketTypes.PUBLISH)
            props.ContentType = HEIGHTMAP_CONTENT_TYPE
        link.client.publish(self.topic("heightmap/live"), live[0], qos=live[2], retain=False,
                            properties=props)  # fmt: skip

    def _serve(self, link: _Link) -> None:
        """Per loop turn on a connected link: session messages, then outbox rows."""
        if link.name == "json":
            if self.outbox.last_seq >= link.will_seq - WILL_SEQ_HEADROOM // 10:
                # the session is about to use the seq of its own Last Will: a new session
                # arms a higher one
                link.refused = "re-arming the Last Will above the seq in use"
                return
            with self._lock:
                status_dirty, self._status_dirty = self._status_dirty, False
                ha_dirty, self._ha_dirty = self._ha_dirty, False
                alarms_dirty, self._alarms_dirty = self._alarms_dirty, False
            if status_dirty:
                self._publish_status(link, "online")
            if ha_dirty and self.cfg.homeassistant.enabled:
                self._publish_discovery(link)
            if alarms_dirty:
                self._publish_alarm_states(link)
            self._send_live(link)
        else:
            with self._lock:
                rebirth, self._rebirth = self._rebirth, False
            may_birth = self.spb.primary_host_id is None or self._host_online
            if may_birth and (rebirth or not link.born):
                self._publish_birth(link)
            elif rebirth:
                with self._lock:
                    self._rebirth = True  # keep it for when the host is back
            if not link.born:
                return
        self._pump(link)

    def _direct(
        self, link: _Link, topic: str, payload: bytes, *, retain: bool, qos: int = 1
    ) -> int:
        assert link.client is not None
        info = link.client.publish(topic, payload, qos=qos, retain=retain)
        link.direct[info.mid] = topic
        return info.mid

    def _publish_status(self, link: _Link, state: str) -> int:
        payload = self._status_payload(state, self.outbox.next_envelope()).to_bytes()
        return self._direct(link, self.topic("status"), payload, retain=True)

    def _publish_alarm_states(self, link: _Link) -> None:
        """The current state of every alarm type, retained, so a fresh subscriber (HA) never
        shows an alarm as unknown; the outbox sends later changes after these."""
        with self._lock:
            states = [dict(e) for e in self._alarm_states.values()]
        for event in states:
            payload = alarm_payload(self.outbox.next_envelope(), event).to_bytes()
            self._direct(link, self.topic(f"alarm/{event['type']}"), payload, retain=True)

    def _publish_discovery(self, link: _Link) -> None:
        ha = self.cfg.homeassistant
        with self._lock:
            alarm_types = list(self._alarm_types)
        topic, payload = homeassistant.discovery_config(
            discovery_prefix=ha.discovery_prefix, base_topic=self.base, silo_id=self.silo_id,
            version=self.version, alarm_types=alarm_types, expire_after_s=self.expire_after_s,
        )
        self._direct(link, topic, payload, retain=True)
        log.info("Home Assistant discovery published", topic=topic)

    def _publish_birth(self, link: _Link) -> None:
        with self._lock:
            payload = self.spb_node.birth(link.bd_seq)
        self._direct(link, self.spb_topics.node("NBIRTH"), payload, retain=False, qos=0)
        link.born = True
        link.spb_seq = 0
        log.info("Sparkplug NBIRTH", bd_seq=link.bd_seq)

    def _status_payload(self, state: str, env: Envelope) -> StatusPayload:
        pending, _ = self.outbox.size()
        with self._lock:
            cameras = list(self._cameras.values())
            last_scan_id = self._last_scan_id
        return StatusPayload(
            **env.model_dump(),
            state=state,
            version=self.version,
            client_id=self.client_id,
            cameras=cameras,
            last_scan_id=last_scan_id,
            outbox=OutboxState(
                pending=pending,
                dropped=self.outbox.counter("dropped"),
                rejected=self.outbox.counter("rejected"),
                dead_lettered=self.outbox.counter("dead_lettered"),
            ),
        )

    def _pump(self, link: _Link) -> None:
        """Hand the next outbox rows to paho, keeping at most max_inflight unacknowledged."""
        if link.probing and time.time() - link.connected_at > POISON_SESSION_S:
            link.probing, link.suspect = False, (0, 0)  # the link holds: full speed again
        room = (1 if link.probing else self.cfg.max_inflight) - len(link.inflight)
        if room <= 0:
            return
        assert link.client is not None
        for row in self.outbox.pending(link.last_id, room, link.kinds):
            topic, payload, props = self._prepare(link, row)
            size = publish_packet_size(topic, payload, row.qos, props, self.cfg.protocol == "5")
            if link.max_packet is not None and size > link.max_packet:
                self._dead_letter(
                    link, row, f"{size}-byte packet, the broker's maximum is {link.max_packet}"
                )
                continue
            try:
                info = link.client.publish(
                    topic, payload, qos=row.qos, retain=row.retain, properties=props
                )
            except ValueError as exc:  # paho refuses it (e.g. a wildcard topic): it always will
                self._dead_letter(link, row, f"paho refused it: {exc}")
                continue
            if info.rc != mqtt.MQTT_ERR_SUCCESS:
                break  # connection gone: the next session starts again from the oldest row
            link.last_id = row.id
            if row.qos == 0 and info.is_published():
                # QoS 0 (Sparkplug NDATA) has no broker ack: paho reported it written, during
                # publish() itself, before the mid could be recorded
                link.acked_rows.append(row.id)
            else:
                link.inflight[info.mid] = (row.id, row.topic)

    def _dead_letter(self, link: _Link, row: Row, reason: str) -> None:
        """Set aside a row that can never be published, so the rows behind it go out."""
        self.outbox.dead_letter(row.id, reason)
        link.last_id = row.id
        log.error(
            "message can never be published: dead-lettered", topic=row.topic[:200],
            msg_id=row.msg_id, reason=reason, outbox=str(self.outbox.path),
        )
        with self._lock:
            self._status_dirty = True

    def _prepare(self, link: _Link, row: Row) -> tuple[str, bytes, Properties | None]:
        payload = row.payload
        if row.kind == KIND_SPARKPLUG:
            link.spb_seq = (link.spb_seq + 1) % 256
            payload = sparkplug.finalize(
                payload, link.spb_seq, historical=row.created < link.connected_at
            )
        if self.cfg.protocol != "5" or row.kind == KIND_SPARKPLUG:
            return row.topic, payload, None
        props = Properties(PacketTypes.PUBLISH)
        if row.kind == KIND_BINARY:
            props.ContentType = HEIGHTMAP_CONTENT_TYPE
        else:
            props.ContentType = "application/json"
            props.PayloadFormatIndicator = 1
        if row.msg_id is not None:
            props.UserProperty = [("msg_id", row.msg_id), ("seq", str(row.seq))]
        if row.correlation is not None:
            props.CorrelationData = row.correlation
        return row.topic, payload, props

    def _shutdown(self) -> None:
        """`stopped` on P/status and NDEATH, each waited for briefly, then disconnect."""
        waiting: list[tuple[_Link, int]] = []
        stopped: tuple[_Link, int] | None = None
        for link in self._links:
            if link.client is None or not link.connected:
                continue
            if link.name == "json":
                stopped = (link, self._publish_status(link, "stopped"))
                waiting.append(stopped)
            elif link.born:
                death = sparkplug.SparkplugNode.death(link.bd_seq)
                waiting.append(
                    (link, self._direct(link, self.spb_topics.node("NDEATH"), death, retain=False))
                )
        end = time.monotonic() + max(1.0, self.cfg.shutdown_timeout_s)
        while waiting and time.monotonic() < end:
            for link, _mid in waiting:
                if link.client is not None:
                    link.client.loop(timeout=LOOP_TIMEOUT_S)
                    self._flush_acks(link)
            waiting = [(k, m) for k, m in waiting if m not in k.acked and k.client is not None]
        if stopped is not None and stopped[1] in stopped[0].acked:
            self.outbox.disarm_will()  # `stopped` is in; the clean disconnect drops the will
        for link in self._links:
            if link.client is not None:
                link.client.disconnect()
                link.client.loop(timeout=LOOP_TIMEOUT_S)
                self._flush_acks(link)
                link.client = None
        log.info("MQTT stopped", pending=self.outbox.size()[0])

