"""The page's reading of the audit cache and its server, in process (no daemon, no broker): the
scan list and history ranges, what counts as a scan of this silo, the page without a token on
loopback, the picture's layout promise on a real reconstruction, and clean stops."""

from __future__ import annotations

import io
import json
import re
import time
import urllib.error
import urllib.request
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from silo_agent.config import AuditConfig, WebConfig, parse_config
from silo_agent.scan import Scan
from silo_agent.service.scan_path import analyse_with, settings_of, summary_of
from silo_agent.storage.audit import AuditCache
from silo_agent.web.archive import Archive, ScanNotFound
from silo_agent.web.pictures import colour_cells, layout_of
from silo_agent.web.server import LiveFeed, Sources, WebServer
from tests.support.mqtt_broker import free_port

SILO = "t"
NOW = datetime.now(UTC).replace(microsecond=0)
AGES = (timedelta(days=3), timedelta(hours=2), timedelta(0))


@pytest.fixture(scope="module")
def analysed(cone_scan_2: Scan):
    return analyse_with(cone_scan_2, settings_of(cone_scan_2), [])


def cache_with_scans(directory: Path, scan: Scan, analysed) -> tuple[AuditCache, list[str]]:
    """Three kept scans of silo `t` (3 days, 2 hours and 0 s old) and one without a result."""
    cache = AuditCache(AuditConfig(directory=directory), SILO)
    ids = []
    for k, age in enumerate((*AGES, timedelta(minutes=1))):
        when = NOW - age
        scan_id = f"{SILO}-{when:%Y%m%dT%H%M%SZ}"
        copy = replace(
            scan, scan_id=scan_id, captured_at=f"{when:%Y-%m-%dT%H:%M:%SZ}", silo_id=SILO
        )
        path = cache.write_scan(copy, {})
        if k < len(AGES):  # the last one failed before a result
            summary = {**summary_of(analysed, copy, {}).to_json(), "scan_id": scan_id}
            cache.add_result(path, summary, analysed.reconstruction.heightmap, {})
        ids.append(scan_id)
    (directory / "not-a-scan").mkdir()
    (directory / "other-20260101T000000Z").mkdir()
    return cache, ids


def test_scan_list_history_ranges_and_lookups(tmp_path: Path, cone_scan_2: Scan, analysed):
    cache, ids = cache_with_scans(tmp_path / "scans", cone_scan_2, analysed)
    archive = Archive(cache)
    records = archive.records()
    assert [r.scan_id for r in records] == sorted(ids)  # oldest first, strays left out
    kept = [r for r in records if r.has_result]
    assert len(kept) == 3 and all(r.volume_m3 == analysed.reconstruction.volume_m3 for r in kept)
    assert archive.latest() is not None and archive.latest().scan_id == ids[2]
    assert len(archive.history("day")) == 2
    assert len(archive.history("week")) == len(archive.history("all")) == 3
    for bad in ("../scans", "not-a-scan", "other-20260101T000000Z", ids[0] + "/scan.json", ""):
        with pytest.raises(ScanNotFound):
            archive.directory(bad)
    with pytest.raises(ScanNotFound):
        archive.view(ids[3])  # no result: no picture
    view = archive.view(ids[2])
    assert view.published["volume_m3"] == analysed.reconstruction.volume_m3
    assert {c.serial for c in view.cameras} == {c.serial for c in cone_scan_2.cameras}
    assert all(0 < c.coverage <= 1 for c in view.cameras)

    # a scan that arrives is listed at the next look, its result once it is kept
    when = NOW + timedelta(seconds=1)
    late = replace(
        cone_scan_2,
        scan_id=f"{SILO}-{when:%Y%m%dT%H%M%SZ}",
        captured_at=f"{when:%Y-%m-%dT%H:%M:%SZ}",
        silo_id=SILO,
    )
    path = cache.write_scan(late, {})
    assert archive.records()[-1].has_result is False
    summary = {**summary_of(analysed, late, {}).to_json(), "scan_id": late.scan_id}
    cache.add_result(path, summary, analysed.reconstruction.heightmap, {})
    assert archive.records()[-1].has_result is True
    assert archive.latest().scan_id == late.scan_id


def test_the_scan_list_pages_from_a_scan_id(tmp_path: Path, cone_scan_2: Scan, analysed):
    """A page starts just older than a scan id, not at a position: a scan that lands between
    two pages shifts nothing (an offset would give the first page's last scan again)."""
    cache, _ids = cache_with_scans(tmp_path / "scans", cone_scan_2, analysed)
    archive = Archive(cache)
    newest_first = [r.scan_id for r in reversed(archive.records())]
    first, more = archive.page(2)
    assert [r.scan_id for r in first] == newest_first[:2] and more
    when = NOW + timedelta(minutes=1)
    landed = cache.write_scan(
        replace(
            cone_scan_2,
            scan_id=f"{SILO}-{when:%Y%m%dT%H%M%SZ}",
            captured_at=f"{when:%Y-%m-%dT%H:%M:%SZ}",
            silo_id=SILO,
        ),
        {},
    )
    second, more = archive.page(2, before=first[-1].scan_id)
    assert [r.scan_id for r in second] == newest_first[2:4] and not more
    assert [r.scan_id for r in archive.page(1)[0]] == [landed.name]
    assert archive.page(10, before=newest_first[-1]) == ([], False)
    with pytest.raises(ScanNotFound):
        archive.page(2, before=f"{SILO}-20000101T000000Z")  # removed by retention, say


def test_colours_follow_the_layout(analysed):
    """The picture's promise (docs/web.md): its lookup table gives what calling matplotlib's
    colormap on the heights gives, filled cells blended, outside grey."""
    from matplotlib import colormaps

    hm = analysed.reconstruction.heightmap
    layout = layout_of(hm, 0.0)
    cells = colour_cells(hm, layout).astype(float)
    known = np.isfinite(hm.heights)
    scaled = np.clip(
        (np.where(known, hm.heights, 0) - layout.vmin) / (layout.vmax - layout.vmin), 0, 1
    )
    expected = colormaps["viridis"](scaled, bytes=True)[..., :3].astype(float)
    filled = known & ~hm.observed
    expected[filled] += (255 - expected[filled]) * layout.filled_blend
    expected[~known] = layout.outside_rgb
    assert filled.any() and hm.observed.any()
    assert np.array_equal(cells, np.rint(expected))


def get(url: str, token: str | None = None) -> tuple[int, bytes, str]:
    request = urllib.request.Request(url)
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, response.read(), response.headers.get("content-type", "")
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read(), exc.headers.get("content-type", "")


def test_the_server_on_loopback_without_a_token(tmp_path: Path, cone_scan_2: Scan, analysed):
    from PIL import Image

    cache, ids = cache_with_scans(tmp_path / "scans", cone_scan_2, analysed)
    config = parse_config(
        {
            "silo": {
                "id": SILO,
                "region": cone_scan_2.site.region.tolist(),
                "floor_z": 0.0,
                "bulk_density_t_m3": 0.77,
            },
            "cameras": [
                {"serial": c.serial, "source": "sim", "view": "A1"} for c in cone_scan_2.cameras
            ],
        },
        "test",
    )
    status = {"cameras": [], "alarms": {}, "events": []}
    server = WebServer.bind(WebConfig(enabled=True, port=free_port()))
    server.serve(Sources(Archive(cache), lambda: config, lambda: status, LiveFeed()))
    base = f"http://127.0.0.1:{server.port}"
    try:
        code, body, kind = get(base + "/api/state")
        assert code == 200 and kind.startswith("application/json")
        state = json.loads(body)
        assert state["latest"]["published"]["scan_id"] == ids[2]
        assert state["latest"]["published"]["volume_m3"] == analysed.reconstruction.volume_m3
        assert state["scans"] == 4 and state["live"] == {"count": 0}
        code, body, kind = get(f"{base}/api/map/{ids[1]}.png")
        assert code == 200 and kind == "image/png"
        layout = json.loads(get(f"{base}/api/map/{ids[1]}.json")[1])
        with Image.open(io.BytesIO(body)) as picture:
            assert picture.size == (layout["width_px"], layout["height_px"])
        for span, count in (("day", 2), ("week", 3), ("all", 3)):
            svg = get(f"{base}/api/history.svg?range={span}")[1].decode()
            group = re.search(r'<g id="history-valid">(.*?)</g>\s*</g>', svg, re.S)
            assert group is not None and group.group(1).count("<use ") == count, span
        assert get(base + "/api/live.png")[0] == 404  # no live session yet
        code, body, _ = get(f"{base}/scans/{ids[3]}/report.html")
        assert code == 404 and b"Traceback" not in body
        assert get(f"{base}/scans/{ids[3]}/export.tar.gz")[0] == 200  # a raw scan exports
    finally:
        server.stop()
    with pytest.raises(OSError):
        get(base + "/api/state")


def test_the_latest_scan_is_drawn_before_anyone_asks(tmp_path: Path, cone_scan_2: Scan, analysed):
    """The server draws each new latest scan's map on its own, so a first visit after a scan
    finds the picture drawn: the picture it then serves is the one drawn ahead."""
    cache, ids = cache_with_scans(tmp_path / "scans", cone_scan_2, analysed)
    config = parse_config(
        {
            "silo": {"id": SILO, "region": cone_scan_2.site.region.tolist()},
            "cameras": [{"serial": "A1", "source": "sim", "view": "A1"}],
        },
        "t",
    )
    status = {"cameras": [], "alarms": {}, "events": []}
    server = WebServer.bind(WebConfig(enabled=True, port=free_port()))
    server.serve(Sources(Archive(cache), lambda: config, lambda: status, LiveFeed()))
    assert server._pages is not None
    kept = server._pages._pictures

    def drawn(scan_id: str) -> bytes:
        end = time.monotonic() + 60
        while ("map", scan_id) not in kept:
            assert time.monotonic() < end, f"{scan_id}'s map not drawn ahead"
            time.sleep(0.05)
        return kept[("map", scan_id)][0]

    try:
        assert drawn(ids[2]) == get(f"http://127.0.0.1:{server.port}/api/map/{ids[2]}.png")[1]
        assert ("map", ids[0]) not in kept  # only the latest: older scans wait for a visit
        # a scan lands while the server runs: it is drawn too, without a request
        later = NOW + timedelta(minutes=5)
        scan_id = f"{SILO}-{later:%Y%m%dT%H%M%SZ}"
        copy = replace(cone_scan_2, scan_id=scan_id, captured_at=f"{later:%Y-%m-%dT%H:%M:%SZ}")
        path = cache.write_scan(replace(copy, silo_id=SILO), {})
        summary = {**summary_of(analysed, copy, {}).to_json(), "scan_id": scan_id}
        cache.add_result(path, summary, analysed.reconstruction.heightmap, {})
        assert drawn(scan_id).startswith(b"\x89PNG")
    finally:
        server.stop()


def test_a_damaged_newest_result_is_listed_without_one_and_the_older_one_is_latest(
    tmp_path: Path, cone_scan_2: Scan, analysed
):
    """A kept result.json with a NaN volume (hand-edited, damaged) had made the scan list a
    500 (NaN is no JSON) and left the page without a latest scan. Read as every output reads a
    result (`read_result`), it is no result: the scan is listed without one, the scan before it
    is the latest, and the whole list serialises."""
    cache, ids = cache_with_scans(tmp_path / "scans", cone_scan_2, analysed)
    newest = tmp_path / "scans" / ids[2] / "result.json"
    newest.write_text(json.dumps({**json.loads(newest.read_text()), "volume_m3": float("nan")}))
    archive = Archive(cache)
    records = {r.scan_id: r for r in archive.records()}
    assert records[ids[2]].has_result is False and records[ids[2]].volume_m3 is None
    assert records[ids[1]].has_result is True
    assert archive.latest() is not None and archive.latest().scan_id == ids[1]
    json.dumps([r.volume_m3 for r in archive.records()], allow_nan=False)
    with pytest.raises(ScanNotFound):
        archive.summary(ids[2])


def test_the_history_axis_covers_the_range_asked_for() -> None:
    """A day or a week is the whole day or week up to now, whatever scans fall in it; `all`
    is the scans' own span, an hour either side when they are closer than that (one scan's
    week had been autoscaled to four years, scans seconds apart labelled bare seconds)."""
    from datetime import UTC, datetime, timedelta

    from silo_agent.web.pictures import history_limits

    now = datetime(2026, 12, 4, 12, 0, tzinfo=UTC)
    one = now - timedelta(hours=3)
    for window in (timedelta(days=7), timedelta(days=1)):
        low, high = history_limits(one, one, window, now)
        assert low == now - window and now < high <= now + window / 20
    hour = timedelta(hours=1)
    assert history_limits(one, one + timedelta(seconds=3), None, now) == (
        one - hour,
        one + timedelta(seconds=3) + hour,
    )
    early = now - timedelta(days=30)
    assert history_limits(early, one, None, now) == (early, one)
