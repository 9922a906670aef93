"""The daemon's pipeline on its own: a `Pipeline` on simulated cameras and a real audit cache,
publishing into a `MemoryPublisher`. The paths that end a scan early (no camera, processing
failed, a full disk, a scan given up on) in well under a second each; tests/test_agent.py and
tests/test_adversarial_input.py prove the same through `silo-agent run` and a real broker."""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import pytest

from silo_agent.config import Config, load_config
from silo_agent.service.pipeline import Pipeline, ScanAbandoned
from silo_agent.storage.audit import AuditCache
from silo_agent.telemetry.prometheus import Metrics
from silo_agent.telemetry.publisher import MemoryPublisher
from tests.support.agent import SILO, write_config
from tests.support.faults import leave_inodes, tmpfs

UNUSED_PORT = 9  # the pipeline never connects: publishing goes to memory


def _config(tmp_path: Path, extra: str = "", **sections) -> Config:
    path = write_config(tmp_path / "agent.toml", UNUSED_PORT, tmp_path, **sections)
    path.write_text(path.read_text() + extra)
    return load_config(path, service=True)


def _scans(config: Config) -> list[Path]:
    """The scan directories in the cache."""
    found = config.audit.directory.iterdir() if config.audit.directory.exists() else []
    return [p for p in found if p.is_dir() and not p.name.startswith(".")]


def _pipeline(config: Config) -> tuple[Pipeline, MemoryPublisher]:
    publisher = MemoryPublisher()
    cache = AuditCache(config.audit, config.silo.id)
    return Pipeline(config, publisher, cache, Metrics()), publisher


def _run(pipeline: Pipeline, abandoned: threading.Event | None = None, n: int = 0):
    started = datetime(2026, 11, 22, 2, 0, n, tzinfo=UTC)
    scan_id = f"{SILO}-{started:%Y%m%dT%H%M%SZ}"
    return pipeline.run(scan_id, started, time.monotonic() + 60, abandoned or threading.Event())


def test_a_scan_publishes_the_summary_it_keeps(tmp_path: Path) -> None:
    pipeline, publisher = _pipeline(_config(tmp_path))
    outcome = _run(pipeline)
    assert outcome.outcome == "ok" and outcome.directory is not None
    (result,) = publisher.of("result")
    assert result.summary is not None and result.heightmap is not None
    kept = json.loads((outcome.directory / "result.json").read_text())
    published = result.summary.to_json()
    # kept before the alarms: the published timings have the alarms stage too
    assert {k: v for k, v in published.items() if k != "timings"} == {
        k: v for k, v in kept.items() if k != "timings"
    }
    assert set(published["timings"]) == {"capture_s", "audit_s", "reconstruct_s", "alarms_s"}
    assert publisher.cameras == {"sim-A2": ("ok", None), "sim-A6": ("ok", None)}
    assert publisher.of("failure") == [] and publisher.alarms() == []


def test_no_camera_is_a_failed_scan_with_its_reason_and_the_camera_alarm(tmp_path: Path) -> None:
    config = _config(tmp_path, cameras=(("sim-X", None),))  # looks at the sky: it fails
    pipeline, publisher = _pipeline(config)
    outcome = _run(pipeline)
    assert outcome.outcome == "failed"
    assert outcome.error == "capture: no camera delivered a cloud"
    (failure,) = publisher.of("failure")
    assert failure.summary is not None and failure.summary.invalid_reason == outcome.error
    assert failure.summary.degraded and failure.summary.cameras.failed[0].serial == "sim-X"
    assert [(e.type, e.state) for e in publisher.alarms()] == [("camera", "raised")]
    assert publisher.cameras["sim-X"][0] == "failed"
    assert publisher.of("result") == [] and _scans(config) == []


def test_a_failure_in_processing_is_reported_and_the_raw_scan_kept(tmp_path: Path) -> None:
    model = tmp_path / "model.onnx"
    model.write_text("not a model")
    config = _config(tmp_path, f'\n[detection.onnx]\nmodel = "{model}"\n')
    pipeline, publisher = _pipeline(config)
    outcome = _run(pipeline)
    assert outcome.outcome == "failed" and outcome.error is not None
    assert outcome.error.startswith("processing: ") and "model.onnx" in outcome.error
    (failure,) = publisher.of("failure")
    assert failure.summary is not None and failure.summary.invalid_reason == outcome.error
    (kept,) = _scans(config)
    assert (kept / "scan.json").is_file() and not (kept / "result.json").exists()


def test_a_scan_given_up_on_publishes_nothing(tmp_path: Path) -> None:
    pipeline, publisher = _pipeline(_config(tmp_path))
    abandoned = threading.Event()
    abandoned.set()
    with pytest.raises(ScanAbandoned, match="gave up"):
        _run(pipeline, abandoned)
    assert publisher.published == []


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    """A real tmpfs with 64 inodes (a test takes all but a few: `leave_inodes`)."""
    with tmpfs(tmp_path / "disk", "20m,nr_inodes=64") as disk:
        yield disk


def test_a_full_disk_publishes_uncached_and_raises_the_cache_alarm(
    tmp_path: Path, tiny_disk: Path
) -> None:
    scans = tiny_disk / "scans"
    scans.mkdir()
    config = _config(tmp_path, audit={"directory": str(scans)})
    leave_inodes(tiny_disk, 0)
    pipeline, publisher = _pipeline(config)
    outcome = _run(pipeline)
    assert outcome.outcome == "ok" and outcome.directory is None  # published, not kept
    (result,) = publisher.of("result")
    assert result.summary is not None and result.summary.volume_m3 is not None
    assert [(e.type, e.state) for e in publisher.alarms()] == [("cache", "raised")]


def test_a_result_lost_to_a_full_disk_raises_the_cache_alarm(
    tmp_path: Path, tiny_disk: Path
) -> None:
    scans = tiny_disk / "scans"
    scans.mkdir()
    config = _config(tmp_path, audit={"directory": str(scans)})
    leave_inodes(tiny_disk, 4)  # the raw scan fits (staging, 2 clouds, scan.json), not its result
    pipeline, publisher = _pipeline(config)
    outcome = _run(pipeline)
    assert outcome.outcome == "ok" and outcome.directory is not None
    assert not (outcome.directory / "result.json").exists()
    assert len(publisher.of("result")) == 1
    assert [(e.type, e.state) for e in publisher.alarms()] == [("cache", "raised")]


def test_the_alarm_state_is_saved_on_a_full_disk_by_evicting_an_old_scan(
    tmp_path: Path, tiny_disk: Path
) -> None:
    """The alarm state (the collapse baseline, raised alarms) is saved next to the scans: on
    a disk that stayed full it was never saved again, and after a restart the baseline it
    named was gone. Now an older scan, never the baseline, is evicted to make room."""
    scans = tiny_disk / "scans"
    scans.mkdir()
    config = _config(tmp_path, audit={"directory": str(scans)})
    pipeline, _publisher = _pipeline(config)
    old, new = _run(pipeline, n=0), _run(pipeline, n=1)
    assert old.directory is not None and new.directory is not None
    baseline = pipeline.state.baseline_scan_id
    assert baseline is not None and baseline != old.scan_id  # the newer scan is the baseline
    pipeline.state = dataclasses.replace(pipeline.state, baseline_scan_id=new.scan_id)
    (scans / "alarm-state.json").unlink()  # the state as it must be saved again
    leave_inodes(tiny_disk, 0)
    pipeline._save_state()
    saved = json.loads((scans / "alarm-state.json").read_text())
    assert saved == json.loads(json.dumps(pipeline.state.to_json()))
    assert not old.directory.exists() and new.directory.exists()
