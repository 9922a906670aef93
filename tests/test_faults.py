"""Fault injection against the running daemon, as a matrix: each case is one line of a
parametrize, and docs/limits.md ("Faults while running") says what the user sees for each.

One agent (a real `silo-agent run` subprocess on simulated cameras, the test's mosquitto, a
socket standing in for systemd) serves all the directory cases in turn: its outbox and its
audit cache live on two small ext4 images, each case breaks one or both file systems (full,
forced read-only by the kernel, the directory deleted), asks for a scan, mends the file
system and asks for another. Every case checks that the scans' results reached the broker,
what was raised and cleared, that the watchdog kept being pinged, and that nothing logged a
traceback."""

from __future__ import annotations

import itertools
import json
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from tests.support.agent import BASE, Daemon, NotifySocket, write_config
from tests.support.faults import delete, fill, force_read_only
from tests.support.mqtt import validate_json
from tests.support.mqtt_broker import Broker, Collector

pytestmark = [pytest.mark.slow, pytest.mark.broker]

REPLIES = "test/fault-replies"
counter = itertools.count()


@dataclass
class Disk:
    """An ext4 image mounted at `mount`; the agent's directory lives at `mount/sub`."""

    mount: Path
    image: Path
    sub: str
    filler: Path | None = None

    @property
    def directory(self) -> Path:
        return self.mount / self.sub

    def mkfs_and_mount(self) -> None:
        """A fresh image each time: the lazily unmounted one may still be in use."""
        self.image = self.image.with_name(f"{self.image.stem}-{next(counter)}.img")
        subprocess.run(["truncate", "-s", "24M", str(self.image)], check=True)
        subprocess.run(["mkfs.ext4", "-q", "-F", str(self.image)], check=True)
        self.mount.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            ["mount", "-o", "loop,errors=remount-ro", str(self.image), str(self.mount)],
            check=True,
        )

    def umount(self) -> None:
        subprocess.run(["umount", "-l", str(self.mount)], check=True)

    def break_it(self, fault: str) -> None:
        if fault == "full":
            self.filler = fill(self.mount)
        elif fault == "read-only":
            force_read_only(self.mount)
        else:
            delete(self.directory)

    def mend(self, fault: str) -> None:
        """Space freed; a fresh file system where the failed one was (what an operator's
        fsck and remount gives); nothing for a deleted directory: the agent recreates it."""
        if fault == "full":
            assert self.filler is not None
            self.filler.unlink()
        elif fault == "read-only":
            self.umount()
            self.mkfs_and_mount()


@dataclass
class Rig:
    agent: Daemon
    col: Collector
    notify: NotifySocket
    disks: dict[str, Disk]
    seen: dict[str, int] = field(default_factory=dict)

    def scan(self) -> dict:
        """Ask for a scan and wait for its final reply."""
        correlation = f"fault-{next(counter)}".encode()
        props = Properties(PacketTypes.PUBLISH)
        props.ResponseTopic = REPLIES
        props.CorrelationData = correlation
        self.col.publish(f"{BASE}/cmd/scan", b'{"request_id": "fault"}', props)

        def final(ms: list) -> list[dict]:
            return [
                json.loads(m.payload)
                for m in ms
                if m.topic == REPLIES
                and m.properties.CorrelationData == correlation
                and json.loads(m.payload)["status"] != "accepted"
            ]

        self.col.wait_for(lambda ms: bool(final(ms)), 60)
        (reply,) = final(self.col.messages)
        assert reply["status"] == "done", reply
        self.col.wait_for(lambda ms: reply["scan_id"] in self.published_scans(), 30)
        return reply

    def published_scans(self) -> list[str]:
        return [validate_json(m.payload)["scan_id"] for m in self.col.on(f"{BASE}/scan")]

    def alarms(self, since: int) -> list[tuple[str, str]]:
        return [
            (a["type"], a["state"])
            for a in (validate_json(m.payload) for m in self.col.on(f"{BASE}/alarm")[since:])
        ]

    def wait_alarm(self, since: int, alarm: tuple[str, str], timeout: float = 20) -> None:
        self.col.wait_for(lambda _ms: alarm in self.alarms(since), timeout)

    def healthy_since(self, log_lines: int) -> None:
        """Alive, pinged the watchdog within the last second and a half, no traceback."""
        assert self.agent.proc.poll() is None
        last_ping = max(t for t, m in self.notify.messages if m == "WATCHDOG=1")
        assert time.monotonic() - last_ping < 1.5
        new = self.agent.log()[log_lines:]
        assert not [e for e in new if "exception" in e or "Traceback" in e.get("event", "")]


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Iterator[Rig]:
    root = tmp_path_factory.mktemp("faults")
    broker = Broker(root / "broker").start()
    disks = {
        "outbox": Disk(root / "outbox-fs", root / "outbox.img", "state"),
        "audit": Disk(root / "audit-fs", root / "audit.img", "scans"),
    }
    for disk in disks.values():
        disk.mkfs_and_mount()
    notify = NotifySocket(root / "notify.sock")
    config = write_config(
        root / "agent.toml",
        broker.port,
        root,
        schedule={"scan_at_start": False},
        simulation={"capture_s": 0.05},
        # retention keeps only the collapse baseline: a full disk has nothing to evict
        audit={"directory": str(disks["audit"].directory), "max_bytes": 1},
        mqtt={"outbox_path": str(disks["outbox"].directory / "outbox.sqlite")},
    )
    col = Collector(broker, [f"{BASE}/#", REPLIES], client_id="fault-collector")
    agent = Daemon(
        config, root, env={"NOTIFY_SOCKET": str(notify.path), "WATCHDOG_USEC": "2000000"}
    )
    rig = Rig(agent, col, notify, disks)
    try:
        col.wait_topic(f"{BASE}/status")  # connected and subscribed
        rig.scan()  # the baseline, and the simulated world built
        yield rig
    finally:
        agent.kill()
        col.close()
        notify.close()
        broker.stop()
        for disk in disks.values():
            disk.umount()


# What each broken directory raises while broken (and clears once mended): the outbox's
# database holds the queue in memory (`outbox`), the cache publishes uncached (`cache`); a
# deleted directory is recreated at once (`outbox` raised and cleared; the cache says nothing,
# it makes the directory again for the next scan).
RAISED: dict[tuple[str, str], set[str]] = {
    ("outbox", "full"): {"outbox"},
    ("outbox", "read-only"): {"outbox"},
    ("outbox", "deleted"): {"outbox"},
    ("audit", "full"): {"cache"},
    ("audit", "read-only"): {"cache"},
    ("audit", "deleted"): set(),
}


@pytest.mark.parametrize("fault", ["full", "read-only", "deleted"])
@pytest.mark.parametrize("where", ["outbox", "audit", "state"])
def test_a_broken_directory_never_silences_the_agent(rig: Rig, where: str, fault: str):
    disks = [rig.disks[where]] if where != "state" else list(rig.disks.values())
    names = [name for name, disk in rig.disks.items() if disk in disks]
    expected = set().union(*(RAISED[(name, fault)] for name in names))
    log_lines = len(rig.agent.log())
    alarms_before = len(rig.col.on(f"{BASE}/alarm"))

    for disk in disks:
        disk.break_it(fault)
    broken = rig.scan()
    for alarm in expected:
        rig.wait_alarm(alarms_before, (alarm, "raised"))
    if fault == "deleted" and "outbox" in names:
        rig.wait_alarm(alarms_before, ("outbox", "cleared"))
        assert (rig.disks["outbox"].directory / "outbox.sqlite").is_file()
    rig.healthy_since(log_lines)

    for disk in disks:
        disk.mend(fault)
    mended = rig.scan()
    for alarm in expected:
        rig.wait_alarm(alarms_before, (alarm, "cleared"))
    raised = {t for t, state in rig.alarms(alarms_before) if state == "raised"}
    assert raised == expected | ({"outbox"} if fault == "deleted" and "outbox" in names else set())
    assert broken["scan_id"] in rig.published_scans()
    assert mended["scan_id"] in rig.published_scans()
    if "audit" in names:  # the cache takes scans again
        assert (rig.disks["audit"].directory / mended["scan_id"] / "result.json").is_file()
    rig.healthy_since(log_lines)


# ---------------------------------------------------------------- helpers for other cases

Check = Callable[[Rig], None]
