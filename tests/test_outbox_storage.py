"""The outbox on a disk that fails under it (real tmpfs and ext4, real SQLite errors): a full,
read-only or deleted database never fails a producer; the newest messages are held in memory
within bounds, the fault is announced, and the queue goes back to disk when it can."""

from __future__ import annotations

import json

import pytest

from silo_agent.telemetry.outbox import Outbox
from tests.support.faults import delete, ext4, fill, force_read_only, tmpfs


def _watch(box: Outbox) -> list[tuple[str, str]]:
    events: list[tuple[str, str]] = []
    box.on_fault = lambda change, message: events.append((change, message))
    box.announce()
    return events


def _enqueue(box: Outbox, topic: str, size: int = 100) -> None:
    box.enqueue(topic, lambda env: json.dumps({"seq": env.seq, "pad": "x" * size}).encode())


def test_a_full_disk_keeps_the_newest_in_memory_and_writes_them_back(tmp_path, monkeypatch):
    monkeypatch.setattr("silo_agent.telemetry.outbox.MEMORY_MAX_BYTES", 200_000)
    with tmpfs(tmp_path / "disk", "1m") as disk:
        box = Outbox(disk / "outbox.sqlite")
        events = _watch(box)
        for k in range(3):
            _enqueue(box, f"early/{k}")
        filler = fill(disk)
        for k in range(40):  # 800 kB: more than the disk had, more than memory keeps
            _enqueue(box, f"late/{k}", 20_000)
        assert [e[0] for e in events] == ["raised"]
        assert "database or disk is full" in events[0][1]
        topics = [r.topic for r in box.pending(limit=1000)]
        assert topics == [f"late/{k}" for k in range(31, 40)]  # the newest, within 200 kB
        assert box.counter("dropped") == 34
        seqs = [r.seq for r in box.pending(limit=1000)]
        assert seqs == sorted(seqs) and seqs[-1] == 43

        filler.unlink()
        box.tend()
        assert [e[0] for e in events] == ["raised", "cleared"] and box.fault is None
        _enqueue(box, "after")
        box.close()
        again = Outbox(disk / "outbox.sqlite")
        assert [r.topic for r in again.pending(limit=1000)] == [*topics, "after"]
        assert again.last_seq == 44 and again.counter("dropped") == 34
        again.close()


def test_a_database_deleted_while_open_is_recreated_with_its_queue(tmp_path):
    box = Outbox(tmp_path / "state" / "outbox.sqlite")
    events = _watch(box)
    _enqueue(box, "before")
    delete(tmp_path / "state")
    _enqueue(box, "meanwhile")  # SQLite writes on into the deleted file without a word
    box.tend()
    assert [e[0] for e in events] == ["raised", "cleared"]
    assert "deleted" in events[0][1]
    assert (tmp_path / "state" / "outbox.sqlite").is_file()
    _enqueue(box, "after")
    box.close()
    again = Outbox(tmp_path / "state" / "outbox.sqlite")
    assert [r.topic for r in again.pending()] == ["before", "meanwhile", "after"]
    assert [r.seq for r in again.pending()] == [1, 2, 3]
    again.close()


def test_a_disk_forced_read_only_holds_the_queue_in_memory(tmp_path):
    with ext4(tmp_path / "disk", tmp_path / "disk.img") as disk:
        box = Outbox(disk / "outbox.sqlite")
        events = _watch(box)
        _enqueue(box, "before")
        force_read_only(disk)
        _enqueue(box, "after")
        assert [e[0] for e in events] == ["raised"]
        assert [r.topic for r in box.pending()] == ["before", "after"]
        box.ack([box.pending()[0].id])
        assert [r.topic for r in box.pending()] == ["after"]
        box.close()  # logs the message it could not keep


@pytest.mark.parametrize("fault", ["full", "missing directory"])
def test_an_outbox_that_cannot_be_opened_starts_in_memory(tmp_path, fault):
    with tmpfs(tmp_path / "disk", "256k") as disk:
        if fault == "full":
            fill(disk)
            path = disk / "outbox.sqlite"
        else:
            (disk / "a-file").write_text("")
            path = disk / "a-file" / "outbox.sqlite"
        box = Outbox(path)
        events = _watch(box)
        assert [e[0] for e in events] == ["raised"]
        _enqueue(box, "held")
        assert [r.topic for r in box.pending()] == ["held"]
        box.close()  # logs the message it could not keep
