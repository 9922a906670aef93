"""What the agent is told over MQTT: the topics it subscribes to, and for each message that
arrives the handler it goes to.

`P/cmd/scan` and `P/cmd/live` are validated here (payload, retained copies, the requested
MQTT 5 Response Topic) and answered through the outbox; the accepted ones go to the agent's
callbacks. Home Assistant's `online`, a Sparkplug NCMD rebirth and the primary host's STATE
are parsed here and handed to the callbacks of the session layer.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import paho.mqtt.client as mqtt
import structlog
from pydantic import ValidationError

from silo_agent.base.limits import MAX_COMMAND_BYTES, MAX_REQUEST_ID_CHARS
from silo_agent.config import MqttConfig
from silo_agent.telemetry import homeassistant, sparkplug
from silo_agent.telemetry.link import JSON_LINK, KIND_JSON, SPARKPLUG_LINK, Link
from silo_agent.telemetry.live_command import LiveCommand, parse_live_request
from silo_agent.telemetry.outbox import Outbox
from silo_agent.telemetry.payloads import (
    CommandReplyPayload,
    Envelope,
    ReplyStatus,
    ScanRequest,
    describe_errors,
)

log = structlog.get_logger(__name__)

MAX_TOPIC_BYTES = 65535  # MQTT's two-byte string length


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


def readable_request_id(payload: bytes) -> str | None:
    """The `request_id` of a command body that did not validate, if it can be read (a JSON
    object with a string id of 1-128 characters): a refusal names the request it answers."""
    if len(payload) > MAX_COMMAND_BYTES:
        return None
    try:
        body = json.loads(payload.decode("utf-8"))
    except (ValueError, RecursionError):
        return None
    return _request_id_in(body)


def _request_id_in(body: object) -> str | None:
    """A command body's `request_id` if it is one a reply can echo (a string, 1-128 chars)."""
    rid = body.get("request_id") if isinstance(body, dict) else None
    return rid if isinstance(rid, str) and 0 < len(rid) <= MAX_REQUEST_ID_CHARS else None


def parse_scan_request(payload: bytes) -> tuple[ScanRequest | None, str | None, str | None]:
    """(request, its request_id as far as it could be read, error) of a `P/cmd/scan` body:
    the request_id lets even a refusal name the request it answers."""
    if len(payload) > MAX_COMMAND_BYTES:
        return None, None, f"payload too large: {len(payload)} bytes, limit {MAX_COMMAND_BYTES}"
    try:
        body = json.loads(payload.decode("utf-8"))
    except UnicodeDecodeError as exc:
        return None, None, f"payload is not UTF-8: {exc.reason} at byte {exc.start}"
    except ValueError as exc:
        return None, None, f"invalid JSON: {exc}"
    except RecursionError:  # json's decoder recurses per level: [[[[...]]]] of a few thousand
        return None, None, "invalid JSON: nested too deeply"
    if not isinstance(body, dict):
        return None, None, f"payload must be a JSON object, got {type(body).__name__}"
    request_id = _request_id_in(body)
    try:
        return ScanRequest.model_validate(body), request_id, None
    except ValidationError as exc:
        return None, request_id, f"invalid request: {describe_errors(exc)}"


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


@dataclass(frozen=True)
class SessionCallbacks:
    """Where the messages for the session layer go (called in the network thread)."""

    homeassistant_online: Callable[[], None]
    rebirth_requested: Callable[[], None]
    host_state: Callable[[Link, bool, int], None]  # link, online, timestamp


class Commands:
    """Routes each incoming message by topic and answers the scan and live commands."""

    def __init__(
        self,
        cfg: MqttConfig,
        base: str,
        spb_topics: sparkplug.Topics,
        outbox: Outbox,
        session: SessionCallbacks,
    ) -> None:
        self.cfg = cfg
        self.base = base
        self.spb_topics = spb_topics
        self.outbox = outbox
        self.session = session
        self._scan_callback: Callable[[ScanCommand], None] | None = None
        self._live_callback: Callable[[LiveCommand], str] | None = None

    def subscriptions(self) -> dict[str, list[tuple[str, int]]]:
        """Link name -> the (topic filter, QoS) it subscribes to at every connect."""
        json_subs = [(f"{self.base}/cmd/scan", 1), (f"{self.base}/cmd/live", 1)]
        ha = self.cfg.homeassistant
        if ha.enabled:
            json_subs.append((homeassistant.status_topic(ha.discovery_prefix), 1))
        spb_subs = [(self.spb_topics.node("NCMD"), 0)]
        if self.cfg.sparkplug.primary_host_id:
            spb_subs.append((sparkplug.Topics.state(self.cfg.sparkplug.primary_host_id), 1))
        return {JSON_LINK: json_subs, SPARKPLUG_LINK: spb_subs}

    def on_scan_request(self, callback: Callable[[ScanCommand], None]) -> None:
        self._scan_callback = callback

    def on_live_command(self, callback: Callable[[LiveCommand], str]) -> None:
        self._live_callback = callback

    def finish_scan_request(
        self, command: ScanCommand, scan_id: str | None = None, error: str | None = None
    ) -> None:
        self._finished(command.reply_topic, command.correlation, command.request_id, scan_id, error)

    def finish_live(self, command: LiveCommand, session_id: str, error: str | None) -> None:
        request_id = command.request.request_id
        self._finished(command.reply_topic, command.correlation, request_id, session_id, error)

    def dispatch(self, link: Link, msg: mqtt.MQTTMessage) -> None:
        """One incoming message, to the handler of its topic."""
        ha = self.cfg.homeassistant
        primary_host = self.cfg.sparkplug.primary_host_id
        commands = (f"{self.base}/cmd/scan", f"{self.base}/cmd/live")
        if msg.topic in commands and msg.retain:
            # the broker replays a retained command at every subscribe: it would act at every
            # start; the live delivery (retain flag clear) was already answered
            log.warning(
                "ignoring a retained command; clear it with an empty retained message",
                topic=msg.topic,
            )
        elif msg.topic in commands and not msg.payload:
            # an empty message is how a retained command is cleared (as the warning above says):
            # its live delivery is no command, and an error reply would only confuse
            log.info("ignoring an empty command message (a retained one cleared)", topic=msg.topic)
        elif msg.topic == f"{self.base}/cmd/scan":
            self._scan_command(msg)
        elif msg.topic == f"{self.base}/cmd/live":
            self._live_command(msg)
        elif ha.enabled and msg.topic == homeassistant.status_topic(ha.discovery_prefix):
            if msg.payload.strip() == b"online":
                self.session.homeassistant_online()
        elif msg.topic == self.spb_topics.node("NCMD"):
            if sparkplug.is_rebirth_request(bytes(msg.payload)):
                log.info("Sparkplug rebirth requested")
                self.session.rebirth_requested()
        elif primary_host and msg.topic == sparkplug.Topics.state(primary_host):
            self._host_state(link, msg.payload)

    def _host_state(self, link: Link, payload: bytes | bytearray) -> None:
        try:
            state = json.loads(payload)
            online, stamp = bool(state["online"]), int(state["timestamp"])
        except (ValueError, KeyError, TypeError, RecursionError):
            log.warning("ignoring a malformed Sparkplug STATE message")
            return
        self.session.host_state(link, online, stamp)

    def _reply_namespaces(self) -> list[str]:
        """Where replies must not go: every topic the agent (or a sibling agent) publishes."""
        spaces = [self.cfg.topic_prefix.rstrip("/") or self.base, sparkplug.NAMESPACE]
        if self.cfg.homeassistant.enabled:
            spaces.append(self.cfg.homeassistant.discovery_prefix.rstrip("/"))
        return spaces

    def _reply_route(
        self, msg: mqtt.MQTTMessage, command: str
    ) -> tuple[str, bytes | None, str | None]:
        """(reply topic, correlation data, why the requested Response Topic was refused) of a
        command: a refused one is answered on the documented `P/cmd/<command>/reply`, where the
        requester can always listen."""
        props = getattr(msg, "properties", None)
        fallback = f"{self.base}/cmd/{command}/reply"
        reply_topic = getattr(props, "ResponseTopic", None) or fallback
        correlation = getattr(props, "CorrelationData", None)
        problem = reply_topic_problem(reply_topic, self._reply_namespaces(), fallback)
        if problem is None:
            return reply_topic, correlation, None
        return fallback, correlation, f"response topic {reply_topic[:200]!r} refused: {problem}"

    def _scan_command(self, msg: mqtt.MQTTMessage) -> None:
        reply_topic, correlation, topic_error = self._reply_route(msg, "scan")
        about: str | None = None
        request, request_id, error = parse_scan_request(bytes(msg.payload))
        if topic_error is not None:
            error = topic_error
        if error is None and request is not None:
            callback = self._scan_callback
            if callback is None:
                error = "this agent does not take scan requests"
            else:
                try:
                    callback(ScanCommand(request.request_id, reply_topic, correlation))
                except CommandRejected as exc:
                    error = str(exc) or "rejected"
                    about = exc.scan_id
        if error is not None:
            log.warning("scan request refused", request_id=request_id, error=error)
        else:
            log.info("scan request accepted", request_id=request_id)
        self._answered(reply_topic, correlation, request_id, error, scan_id=about)

    def _live_command(self, msg: mqtt.MQTTMessage) -> None:
        reply_topic, correlation, topic_error = self._reply_route(msg, "live")
        request_id = session_id = None
        try:
            request = parse_live_request(bytes(msg.payload))
            request_id = request.request_id
            if topic_error is not None:
                raise CommandRejected(topic_error)
            if self._live_callback is None:
                raise CommandRejected("this agent does not run live sessions")
            session_id = self._live_callback(LiveCommand(request, reply_topic, correlation))
        except (ValueError, CommandRejected) as exc:
            if request_id is None:  # refused as it was parsed: the id as far as it reads
                request_id = readable_request_id(bytes(msg.payload))
            log.warning("live request refused", request_id=request_id, error=str(exc))
            self._answered(reply_topic, correlation, request_id, str(exc) or "rejected")
            return
        log.info("live request accepted", request_id=request_id, session=session_id)
        self._answered(reply_topic, correlation, request_id, None, scan_id=session_id)

    def _answered(
        self,
        topic: str,
        correlation: bytes | None,
        request_id: str | None,
        error: str | None,
        scan_id: str | None = None,
    ) -> None:
        """A command's first reply: accepted, or refused with why (`error`)."""
        status: ReplyStatus = "accepted" if error is None else "error"
        self._reply(
            topic,
            correlation,
            request_id,
            status=status,
            accepted=error is None,
            error=error,
            scan_id=scan_id,
        )

    def _finished(
        self,
        topic: str,
        correlation: bytes | None,
        request_id: str | None,
        scan_id: str | None,
        error: str | None,
    ) -> None:
        """An accepted command's last reply: done, or the error that ended it."""
        status: ReplyStatus = "error" if error else "done"
        self._reply(
            topic,
            correlation,
            request_id,
            status=status,
            accepted=True,
            error=error,
            scan_id=scan_id,
        )

    def _reply(
        self,
        topic: str,
        correlation: bytes | None,
        request_id: str | None,
        *,
        status: ReplyStatus,
        accepted: bool,
        error: str | None = None,
        scan_id: str | None = None,
    ) -> None:
        def build(env: Envelope | None) -> bytes:
            assert env is not None
            return CommandReplyPayload(
                **env.model_dump(),
                request_id=request_id,
                status=status,
                accepted=accepted,
                error=error,
                scan_id=scan_id,
            ).to_bytes()

        self.outbox.enqueue(topic, build, qos=1, kind=KIND_JSON, correlation=correlation)
