"""The scan list a page at a time, on the real page (`silo-agent run` on simulated cameras, the
test's own mosquitto, headless chromium): an archive of more scans than a page shows the newest
page, the "older scans" button appends the next ones (newest first, none twice) until none are
left, and a scan that arrives goes on top without losing the pages shown. `api/scans` refuses a
bad `limit` or an unknown `before` with a 400 naming it. It had answered every scan of the
archive at once, and the page drawn a row for each (709 scans: 1.9 s to draw)."""

from __future__ import annotations

import json
import os
import shutil
from datetime import datetime, timedelta
from pathlib import Path

import pytest

from tests.support.agent import BASE, SILO, Daemon, write_config
from tests.support.mqtt_broker import free_port
from tests.test_web import fetch, wait_js

OLDER = 119  # copies of the agent's first scan before it: 120 scans, past two pages of 50
ROWS_JS = "return [...document.querySelectorAll('#scans tbody tr')].map((r) => r.dataset.scanId)"


def copy_scan(source: Path, when: datetime) -> str:
    """A scan of the same silo taken at `when`: `source` hard-linked, its scan.json and
    result.json saying the new id and time; renamed into place whole, as the agent writes."""
    scan_id = f"{SILO}-{when:%Y%m%dT%H%M%SZ}"
    staging = source.parent / f".{scan_id}.copy"
    shutil.copytree(source, staging, copy_function=os.link)
    for name in ("scan.json", "result.json"):
        data = json.loads((staging / name).read_text())
        data["scan_id"], data["captured_at"] = scan_id, f"{when:%Y-%m-%dT%H:%M:%SZ}"
        (staging / name).unlink()  # a link to the source's file: written anew, not through it
        (staging / name).write_text(json.dumps(data))
    staging.rename(source.parent / scan_id)
    return scan_id


def rows(browser) -> list[str]:
    return browser.execute_script(ROWS_JS)


@pytest.mark.slow
def test_the_scan_list_pages_and_a_new_scan_goes_on_top(
    tmp_path: Path, broker, collector_factory, browser
) -> None:
    web_port = free_port()
    config = write_config(
        tmp_path / "agent.toml",
        broker.port,
        tmp_path,
        web={"enabled": True, "port": web_port},
        audit={"max_bytes": 10**12},  # the copies count in full: none is removed for room
    )
    col = collector_factory(broker, [f"{BASE}/volume"])
    agent = Daemon(config, tmp_path)
    base = f"http://127.0.0.1:{web_port}"
    try:
        (first,) = agent.wait_log("scan finished")
        source = tmp_path / "scans" / first["scan_id"]
        taken = json.loads((source / "scan.json").read_text())["captured_at"]
        start = datetime.fromisoformat(taken.replace("Z", "+00:00"))
        newest_first = [first["scan_id"]] + [
            copy_scan(source, start - timedelta(minutes=k)) for k in range(1, OLDER + 1)
        ]

        # --- the API: a page from the newest, then from just older than a scan id
        status, body = fetch(base + "/api/scans")
        page = json.loads(body)
        size = len(page["scans"])
        assert status == 200 and 0 < size < len(newest_first) and page["more"] is True
        assert [s["scan_id"] for s in page["scans"]] == newest_first[:size]
        cursor = newest_first[size - 1]
        page = json.loads(fetch(f"{base}/api/scans?limit=3&before={cursor}")[1])
        assert [s["scan_id"] for s in page["scans"]] == newest_first[size : size + 3]
        page = json.loads(fetch(f"{base}/api/scans?limit=500")[1])
        assert len(page["scans"]) == len(newest_first) and page["more"] is False
        for bad in ("0", "501", "-1", "1.5", "abc", "", "9" * 5000):
            status, body = fetch(f"{base}/api/scans?limit={bad}")
            assert status == 400, bad
            assert body.count(b"\n") == 0 and json.loads(body)["error"].startswith("limit: ")
        status, body = fetch(f"{base}/api/scans?before={SILO}-20000101T000000Z")
        assert status == 400 and json.loads(body)["error"].startswith("before: ")

        # --- the page: the newest page, then each click the next, until none is left
        browser.get(base + "/")
        wait_js(browser, "document.querySelectorAll('#scans tbody tr').length > 0")
        assert rows(browser) == newest_first[:size]
        older = browser.find_element("id", "older-scans")
        while older.is_displayed():
            shown = len(rows(browser))
            older.click()
            wait_js(browser, f"document.querySelectorAll('#scans tbody tr').length > {shown}")
            assert rows(browser) == newest_first[: min(shown + size, len(newest_first))]
        assert rows(browser) == newest_first  # all of them, once each, newest first
        times = [td.text for td in browser.find_elements("css selector", "#scans td:nth-child(2)")]
        assert times == sorted(times, reverse=True)

        # --- a new scan: on top, the pages shown below it stay
        col.publish(f"{BASE}/cmd/scan", b'{"request_id": "paging"}')
        _, second = agent.wait_log("scan finished", 2)
        wait_js(
            browser,
            f"document.querySelector('#scans tbody tr').dataset.scanId === '{second['scan_id']}'",
        )
        assert rows(browser) == [second["scan_id"], *newest_first]
        assert not older.is_displayed()
    finally:
        agent.kill()
