"""MQTT telemetry: the topic contract of docs/mqtt.md over paho-mqtt 2.x.

`Telemetry` is the face the agent, the pipeline and live mode use. Producers call `publish_*`
from any thread; those calls only commit to the durable outbox (or, for what a session
announces, change `NodeState`). One network thread (`transport.Transport`) owns the paho
clients and does everything else: connecting with back-off, the session messages
(`session.Session`: status, alarm states, Home Assistant, Sparkplug births), sending outbox
rows oldest first and deleting them on the broker's PUBACK (`pump.Pump`), and handing the
messages that arrive to `commands.Commands`, which answers them.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from typing import Any

from silo_agent import __version__
from silo_agent.analysis.alarm_types import AlarmEvent, AlarmStateName
from silo_agent.analysis.summary import ScanSummary
from silo_agent.config import Config, MqttConfig, stale_after_s
from silo_agent.grid.heightmap import HeightMap
from silo_agent.telemetry import sparkplug
from silo_agent.telemetry.commands import (
    CommandRejected,
    Commands,
    ScanCommand,
    SessionCallbacks,
    reply_topic_problem,
)
from silo_agent.telemetry.heightmap_codec import encode_heightmap
from silo_agent.telemetry.link import KIND_BINARY, KIND_JSON, KIND_SPARKPLUG
from silo_agent.telemetry.live_command import LiveCommand
from silo_agent.telemetry.mqtt_session import (
    Identity,
    LiveMapSend,
    NodeState,
    Session,
    live_too_large,
)
from silo_agent.telemetry.outbox import WILL_SEQ_HEADROOM, Outbox, OutboxLimits
from silo_agent.telemetry.payloads import (
    CameraState,
    Envelope,
    StatusPayload,
    alarm_payload,
    check_summary,
    scan_payload,
    volume_payload,
)
from silo_agent.telemetry.pump import POISON_STRIKES
from silo_agent.telemetry.transport import Credentials, Transport, read_secret

RECENT_ALARM_EVENTS = 50  # alarm events the operator's page lists (since the agent started)

__all__ = [  # the names callers import from here, wherever they live
    "POISON_STRIKES",
    "WILL_SEQ_HEADROOM",
    "CommandRejected",
    "LiveMapTooLarge",
    "ScanCommand",
    "Telemetry",
    "read_secret",
    "reply_topic_problem",
]


class LiveMapTooLarge(Exception):
    """A live map the broker would not take (its Maximum Packet Size); the message says so."""


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
        by_hand: str | None = None,
    ) -> None:
        """`expire_after_s`: how long HA keeps showing a reading without a new one.
        `by_hand`: the command (`publish`, `flush`) that sends the outbox by hand, as client
        `<client_id>-<command>`, the outbox's rows only (`transport.Transport`): never the
        agent's client id, nor its status, alarm states or sessions."""
        self.cfg = cfg
        self.silo_id = silo_id
        self.version = version
        self.base = f"{cfg.topic_prefix}/{silo_id}"
        self.client_id = cfg.client_id or f"silo-agent-{silo_id}"
        if by_hand is not None:
            self.client_id += f"-{by_hand}"
        credentials = Credentials.from_config(cfg)  # a bad one fails before the outbox opens
        self.outbox = Outbox(
            cfg.outbox_path,
            OutboxLimits(
                max_messages=cfg.outbox_max_messages,
                max_bytes=cfg.outbox_max_bytes,
                max_age_s=cfg.outbox_max_age_days * 86400.0,
            ),
        )
        self.spb = cfg.sparkplug
        self.spb_topics = sparkplug.Topics(self.spb.group_id, self.spb.edge_node_id or silo_id)
        self.state = NodeState(
            cameras={s: CameraState(serial=s, state="unknown") for s in camera_serials},
            expire_after_s=expire_after_s,
        )
        self.spb_node = sparkplug.SparkplugNode(version, self.state.cameras)
        identity = Identity(self.base, silo_id, version, self.client_id, self.spb_topics)
        self.session = Session(cfg, identity, self.outbox, self.state, self.spb_node)
        self.commands = Commands(
            cfg,
            self.base,
            self.spb_topics,
            self.outbox,
            SessionCallbacks(
                homeassistant_online=self.session.homeassistant_online,
                rebirth_requested=self.session.rebirth_requested,
                host_state=self.session.host_state,
            ),
        )
        self.transport = Transport(
            cfg,
            self.client_id,
            credentials,
            self.outbox,
            status_topic=self.topic("status"),
            spb_topics=self.spb_topics,
            subscriptions=self.commands.subscriptions(),
            session=self.session,
            on_message=self.commands.dispatch,
            by_hand=by_hand is not None,
        )
        self._links = self.transport.links
        self._thread: threading.Thread | None = None
        self.alarm_events: deque[dict[str, Any]] = deque(maxlen=RECENT_ALARM_EVENTS)
        self._live_watchers: list[Callable[[bytes], None]] = []
        self._report_outbox_damage()
        self.outbox.on_fault = self._outbox_fault
        self.outbox.announce()  # a disk that could not be written at open

    def _outbox_fault(self, change: AlarmStateName, message: str) -> None:
        """The outbox could not write its database (full, read-only, deleted), or can again:
        the `outbox` alarm (its clearing waits while a corrupt copy waits for the operator)."""
        if change == "cleared" and self.outbox.corrupt_raised:
            return
        self.publish_alarm(
            AlarmEvent(
                type="outbox", state=change, scan_id=None, severity="warning", message=message
            )
        )

    def _report_outbox_damage(self) -> None:
        """The `outbox` alarm: raised when a corrupt outbox was moved aside at open (what it
        held is lost), cleared at a later start once no moved-aside copy is left; a start in
        between restores it as raised, as the scan alarms are (`restore_alarms`)."""
        change = self.outbox.corrupt_alarm_change()
        aside = self.outbox.moved_aside
        if change == "raised" and aside is not None:
            message = (
                f"outbox database {self.outbox.path} was corrupt: moved aside to {aside.name},"
                " the messages queued in it were not sent; remove it once inspected"
            )
        elif change == "cleared":
            message = "no corrupt outbox copy left"
        elif self.outbox.corrupt_alarm_raised():
            left = ", ".join(sorted(p.name for p in self.outbox.corrupt_copies()))
            message = (
                f"corrupt outbox copies left beside {self.outbox.path}: {left};"
                " remove them once inspected"
            )
            self.restore_alarms(
                {
                    "outbox": AlarmEvent(
                        type="outbox",
                        state="raised",
                        scan_id=None,
                        severity="warning",
                        message=message,
                    )
                }
            )
            return
        else:
            return
        self.publish_alarm(
            AlarmEvent(
                type="outbox", state=change, scan_id=None, severity="warning", message=message
            )
        )

    @classmethod
    def from_config(cls, config: Config, by_hand: str | None = None) -> Telemetry:
        return cls(
            config.mqtt,
            config.silo.id,
            [c.serial for c in config.cameras],
            expire_after_s=stale_after_s(config.schedule, config.silo.timezone),
            by_hand=by_hand,
        )

    def topic(self, suffix: str) -> str:
        return f"{self.base}/{suffix}"

    # ------------------------------------------------------------ producer API

    def publish_result(
        self, summary: ScanSummary, heightmap: HeightMap | None = None
    ) -> list[Envelope]:
        """Queue `P/scan`, `P/volume` (retained) and `P/heightmap` (retained) for one result."""
        check_summary(summary)
        volume = volume_payload(Envelope.new(1), summary).model_dump(mode="json")
        blob = encode_heightmap(heightmap, summary.scan_id) if heightmap is not None else None
        envs = [
            self._enqueue("scan", lambda e: scan_payload(e, summary).to_bytes()),
            self._enqueue("volume", lambda e: volume_payload(e, summary).to_bytes(), retain=True),
        ]
        if blob is not None:
            envs.append(self._enqueue("heightmap", lambda _e: blob, retain=True, kind=KIND_BINARY))
        with self.state.lock:
            self.state.last_scan_id = summary.scan_id
            self.state.last_failure = None
            self.state.status_dirty = True
        if self.spb.enabled:
            with self.state.lock:
                raw, new_metric = self.spb_node.data_from_result(volume)
            self._enqueue_sparkplug(raw, new_metric)
        return envs

    def publish_scan_failure(self, summary: ScanSummary) -> Envelope:
        """Queue `P/scan` alone for a scan that produced no usable result (its
        `invalid_reason` says why): the retained `P/volume` and `P/heightmap` keep the last
        good values."""
        check_summary(summary)
        env = self._enqueue("scan", lambda e: scan_payload(e, summary).to_bytes())
        with self.state.lock:
            self.state.last_scan_id = summary.scan_id
            self.state.last_failure = {
                "scan_id": summary.scan_id,
                "captured_at": summary.captured_at,
                "reason": summary.invalid_reason,
            }
            self.state.status_dirty = True
        return env

    def publish_alarm(self, event: AlarmEvent) -> Envelope:
        """Queue an alarm event on `P/alarm` and the current state on `P/alarm/<type>`."""
        alarm_payload(Envelope.new(1), event)  # validate before anything is committed
        with self.state.lock:  # before the queue: a state snapshot must never be older than it
            self._record_alarm(event.type, event)
        env = self._enqueue("alarm", lambda e: alarm_payload(e, event).to_bytes())
        with self.state.lock:
            self.alarm_events.append({**event.to_json(), "ts": env.ts})
        self._enqueue(
            f"alarm/{event.type}", lambda e: alarm_payload(e, event).to_bytes(), retain=True
        )
        if self.spb.enabled:
            with self.state.lock:
                raw, new_metric = self.spb_node.data_from_alarm(event)
            self._enqueue_sparkplug(raw, new_metric)
        return env

    def restore_alarms(self, active: Mapping[str, AlarmEvent]) -> None:
        """The raised alarms persisted by the last run (type -> its `raised` event): every
        birth and state snapshot from now on carries them instead of `cleared`."""
        with self.state.lock:
            for alarm_type, event in active.items():
                self._record_alarm(alarm_type, event)
            self.spb_node.restore_alarms(active)
            self.state.alarms_dirty = True
            self.state.rebirth = True

    def restore_result(self, summary: ScanSummary) -> None:
        """The last published result (from the audit cache): every birth from now on carries
        it, as the retained `P/volume` does, not nulls until the next scan. Only what
        `P/volume` says is taken, validated as for publishing; ValueError if it cannot be."""
        check_summary(summary)
        volume = volume_payload(Envelope.new(1), summary).model_dump(mode="json")
        with self.state.lock:
            self.spb_node.restore_result(volume)
            self.state.rebirth = True

    def raised_alarms(self) -> set[str]:
        """The alarm types raised now, whoever raised them (the scan's detectors, the
        outbox): what `silo_agent_alarm_active` shows."""
        with self.state.lock:
            return {t for t, e in self.state.alarm_states.items() if e.state == "raised"}

    def _record_alarm(self, alarm_type: str, event: AlarmEvent) -> None:
        """The state of `alarm_type` is now `event`; a new type is announced to HA (with the
        state lock held)."""
        self.state.alarm_states[alarm_type] = event
        if alarm_type not in self.state.alarm_types:
            self.state.alarm_types.append(alarm_type)
            self.state.ha_dirty = True

    def set_expire_after(self, seconds: int | None) -> None:
        """A new schedule, a new staleness limit: HA gets the discovery config again."""
        with self.state.lock:
            if seconds != self.state.expire_after_s:
                self.state.expire_after_s = seconds
                self.state.ha_dirty = self.cfg.homeassistant.enabled

    def set_status(
        self,
        cameras: dict[str, tuple[str, str | None]] | None = None,
        last_scan_id: str | None = None,
    ) -> None:
        """Update what `P/status` reports: camera serial -> (state, error), last scan id."""
        changed: dict[str, str] = {}
        raw: bytes | None = None
        with self.state.lock:
            for serial, (state, error) in (cameras or {}).items():
                old = self.state.cameras.get(serial)
                self.state.cameras[serial] = CameraState.model_validate(
                    {"serial": serial, "state": state, "error": error}
                )
                if old is None or old.state != state:
                    changed[serial] = state
            if last_scan_id is not None:
                self.state.last_scan_id = last_scan_id
            self.state.status_dirty = True
            if changed and self.spb.enabled:
                raw, new_metric = self.spb_node.data_from_cameras(changed)
        if raw is not None:
            self._enqueue_sparkplug(raw, new_metric)

    def on_scan_request(self, callback: Callable[[ScanCommand], None]) -> None:
        """Call `callback` (in the network thread: it must not block) for each valid request.

        Returning accepts the request; raising CommandRejected answers with its message.
        """
        self.commands.on_scan_request(callback)

    def finish_scan_request(
        self, command: ScanCommand, scan_id: str | None = None, error: str | None = None
    ) -> None:
        """The later reply: the scan id of the requested scan, or why it failed."""
        self.commands.finish_scan_request(command, scan_id, error)

    def on_live_command(self, callback: Callable[[LiveCommand], str]) -> None:
        """Call `callback` (network thread, must not block) for each valid `P/cmd/live`; it
        returns the live session's id, or raises CommandRejected."""
        self.commands.on_live_command(callback)

    def finish_live(self, command: LiveCommand, session_id: str, error: str | None) -> None:
        """The later reply: the live session ended (`error` if not as asked)."""
        self.commands.finish_live(command, session_id, error)

    def publish_live(self, payload: bytes, period_s: float, qos: int = 0) -> None:
        """Send a live map on `P/heightmap/live` (not retained, not through the outbox): it
        replaces an unsent one, is dropped if no connection takes it within a period, and
        goes no sooner than a period after the previous one.
        LiveMapTooLarge if it (or the last one) is over the broker's Maximum Packet Size:
        sent, it would only get the agent disconnected."""
        _topic, _props, size = self.session.live_packet(payload, qos)
        with self.state.lock:
            problem = live_too_large(size, self._links[0].max_packet) or self.state.live_refused
            self.state.live_refused = None
            if problem is None:
                self.state.live_map = LiveMapSend(
                    payload, time.monotonic() + period_s, qos, period_s
                )
        if problem is not None:
            raise LiveMapTooLarge(problem)
        for watch in self._live_watchers:
            watch(payload)

    def watch_live(self, callback: Callable[[bytes], None]) -> None:
        """Also hand every live map to `callback` (the session's thread: it must not block)."""
        self._live_watchers.append(callback)

    def snapshot(self) -> dict[str, Any]:
        """What the operator's page shows of the node: cameras, alarm states, recent events,
        and the last scan if it gave no result (none is kept to show: the page names it above
        the last result's figures)."""
        with self.state.lock:
            return {
                "cameras": [c.model_dump(mode="json") for c in self.state.cameras.values()],
                "alarms": {k: v.to_json() for k, v in self.state.alarm_states.items()},
                "events": list(self.alarm_events),
                "last_failure": self.state.last_failure,
            }

    def unsent(self) -> int:
        """Messages in the outbox for this process's links to send (by hand: not the
        Sparkplug rows, which wait for the agent)."""
        return self.outbox.size(tuple(k for link in self._links for k in link.kinds))[0]

    def status(self) -> StatusPayload:
        """What `P/status` would say now (state online), e.g. for a health check."""
        return self.session.status_payload("online", Envelope.new(1))

    # ------------------------------------------------------------ lifecycle

    def start(self) -> None:
        self._thread = threading.Thread(target=self.transport.run, name="mqtt", daemon=True)
        self._thread.start()

    def alive(self) -> bool:
        """The network thread runs (or has not been started, or was asked to stop)."""
        thread = self._thread
        return thread is None or thread.is_alive() or self.transport.stopping.is_set()

    def restart(self) -> None:
        """A new network thread after the last one died: its connections are dropped, the
        outbox resends what was not acknowledged."""
        for link in self.transport.links:
            self.transport.drop(link, "network thread restarted")
            link.retry_at = 0.0
        self.start()

    def stop(self) -> None:
        """Send what is pending (up to shutdown_timeout_s), `stopped`, NDEATH; disconnect."""
        self.transport.stopping.set()
        if self._thread is not None:
            self._thread.join()
        self.outbox.close()

    # ------------------------------------------------------------ enqueueing

    def _enqueue(
        self,
        suffix: str,
        build: Callable[[Envelope], bytes],
        *,
        retain: bool = False,
        kind: str = KIND_JSON,
    ) -> Envelope:
        """Commit `P/<suffix>` (QoS 1; a retained topic keeps only its latest pending row)."""

        def build_env(env: Envelope | None) -> bytes:
            assert env is not None
            return build(env)

        env = self.outbox.enqueue(
            self.topic(suffix), build_env, qos=1, retain=retain, latest=retain, kind=kind
        )
        assert env is not None
        return env

    def _enqueue_sparkplug(self, raw: bytes, new_metric: bool) -> None:
        self.outbox.enqueue(
            self.spb_topics.node("NDATA"),
            lambda _e: raw,
            qos=0,
            kind=KIND_SPARKPLUG,
            with_envelope=False,
        )
        if new_metric:
            self.session.rebirth_requested()
