"""From the durable outbox onto a connected link: rows oldest first, at most `max_inflight`
unacknowledged, deleted on the broker's PUBACK; the rows that can never be published are
dead-lettered so that the rows behind them go out.

A row can never be published when its packet is over the broker's announced Maximum Packet
Size, when paho refuses it (a wildcard topic), or when the broker closed the connection each
time it was the one in flight: after a session that ended within POISON_SESSION_S of
connecting with messages unacknowledged, the next sessions send one message at a time
("probing"); the message in flight when POISON_STRIKES probing sessions in a row ended is one
the broker will not take (a limit it does not announce, e.g. its maximum packet size under
MQTT 3.1.1).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import paho.mqtt.client as mqtt
import structlog
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from silo_agent.config import MqttConfig
from silo_agent.telemetry import sparkplug
from silo_agent.telemetry.link import (
    HEIGHTMAP_CONTENT_TYPE,
    KIND_BINARY,
    KIND_SPARKPLUG,
    Link,
)
from silo_agent.telemetry.outbox import Outbox, Row

log = structlog.get_logger(__name__)

POISON_STRIKES = 3
POISON_SESSION_S = 10.0


def publish_packet_size(
    topic: str, payload: bytes, qos: int, props: Properties | None, v5: bool
) -> int:
    """Bytes of the PUBLISH packet paho will send, to compare with the broker's maximum."""
    body = 2 + len(topic.encode("utf-8")) + (2 if qos else 0) + len(payload)
    if v5:
        body += len(props.pack()) if props is not None else 1
    length_bytes = 1 + sum(body >= limit for limit in (128, 16384, 2097152))
    return 1 + length_bytes + body


class Pump:
    """Sends outbox rows on a link and settles them when the broker answers.
    `outbox_changed` is called when a row left the outbox unsent (rejected or dead-lettered):
    the counters `P/status` reports moved."""

    def __init__(self, cfg: MqttConfig, outbox: Outbox, outbox_changed: Callable[[], None]):
        self.cfg = cfg
        self.outbox = outbox
        self.outbox_changed = outbox_changed

    def send(self, link: Link) -> None:
        """Hand the next outbox rows to paho, keeping at most max_inflight unacknowledged."""
        if link.probing and time.time() - link.connected_at > POISON_SESSION_S:
            link.probing, link.suspect = False, (0, 0)  # the link holds: full speed again
        room = (1 if link.probing else self.cfg.max_inflight) - len(link.inflight)
        if room <= 0:
            return
        assert link.client is not None
        for row in self.outbox.pending(link.last_id, room, link.kinds):
            prepared = self._prepare(link, row)
            if prepared is None:  # nothing in it this session declared: settled, not sent
                link.last_id = row.id
                link.acked_rows.append(row.id)
                continue
            topic, payload, props = prepared
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

    def drained(self, link: Link) -> bool:
        """Nothing of the outbox is in flight or left to send on this link."""
        return not link.inflight and not self.outbox.pending(link.last_id, 1, link.kinds)

    def acknowledged(self, link: Link, mid: int, reason: mqtt.ReasonCode) -> None:
        """The broker's answer to a publish: an outbox row to delete (or drop, if refused), or
        a message sent directly."""
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
            self.outbox_changed()
        else:
            link.acked_rows.append(row_id)

    def flush_acks(self, link: Link) -> None:
        """Delete acknowledged rows: one fsync'ed transaction per loop turn, not per PUBACK."""
        if link.acked_rows:
            self.outbox.ack(link.acked_rows)
            link.acked_rows.clear()

    def session_ended(self, link: Link) -> None:
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
                        link,
                        row,
                        f"the broker closed the connection each time it was sent"
                        f" ({strikes} sessions in a row)",
                    )
                link.suspect = (0, 0)
        link.probing = True

    def _dead_letter(self, link: Link, row: Row, reason: str) -> None:
        """Set aside a row that can never be published, so the rows behind it go out."""
        self.outbox.dead_letter(row.id, reason)
        link.last_id = row.id
        log.error(
            "message can never be published: dead-lettered",
            topic=row.topic[:200],
            msg_id=row.msg_id,
            reason=reason,
            outbox=str(self.outbox.path),
        )
        self.outbox_changed()

    def _prepare(self, link: Link, row: Row) -> tuple[str, bytes, Properties | None] | None:
        """Topic, payload and MQTT 5 properties of a row; None for a Sparkplug NDATA none of
        whose metrics the session's NBIRTH declared."""
        payload = row.payload
        if row.kind == KIND_SPARKPLUG:
            finalized, left_out = sparkplug.finalize(
                payload,
                (link.spb_seq + 1) % 256,
                historical=row.created < link.connected_at,
                declared=link.declared,
            )
            if left_out:
                log.info(
                    "Sparkplug metrics the NBIRTH did not declare left out of an NDATA",
                    metrics=left_out,
                    sent=finalized is not None,
                )
            if finalized is None:
                return None
            link.spb_seq = (link.spb_seq + 1) % 256
            payload = finalized
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
