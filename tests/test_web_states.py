"""The operator's page (a real headless chromium on `silo-agent run`'s page) and /metrics in
the states an operator meets: a silo without `[silo.bin]` has no fill, headspace or capacity
(both had shown 0: "fill 0.0 %", an empty silo); a scan that gave no result is named above the
figures; the agent away fades the page until it is back."""

from __future__ import annotations

import re
import urllib.request
from pathlib import Path

import pytest
from prometheus_client.parser import text_string_to_metric_families

from silo_agent.analysis.summary import ScanSummary
from silo_agent.config import MetricsConfig
from silo_agent.telemetry.prometheus import Metrics
from tests.support.agent import Daemon, write_config
from tests.support.cli import run_cli
from tests.support.mqtt_broker import free_port
from tests.test_bins import SUMMARY  # a bin's valid result
from tests.test_web import wait_js

BIN_METRICS = ("silo_agent_last_fill_ratio", "silo_agent_last_headspace_meters")
BIN_ROWS = ("fill-row", "headspace-row", "capacity-row")


def scrape(port: int) -> dict[str, list[float]]:
    """Every family's sample values, as a scraper reads them."""
    url = f"http://127.0.0.1:{port}/metrics"
    text = urllib.request.urlopen(url, timeout=5).read().decode()
    return {f.name: [s.value for s in f.samples] for f in text_string_to_metric_families(text)}


@pytest.mark.slow
def test_without_a_bin_the_page_hides_and_the_metrics_leave_out_the_bin_figures(
    tmp_path: Path, broker, browser
) -> None:
    web_port, metrics_port = free_port(), free_port()
    config = write_config(
        tmp_path / "agent.toml",
        broker.port,
        tmp_path,
        web={"enabled": True, "port": web_port},
        metrics={"enabled": True, "port": metrics_port},
    )
    assert "[silo.bin]" not in config.read_text()
    agent = Daemon(config, tmp_path)
    try:
        agent.wait_log("scan finished")
        families = scrape(metrics_port)
        assert families["silo_agent_last_volume_cubic_meters"][0] > 40  # ~43.2 m³ flat grain
        for name in BIN_METRICS:
            assert not families.get(name), f"{name} exported without a bin: {families[name]}"

        browser.get(f"http://127.0.0.1:{web_port}/")
        wait_js(browser, "document.getElementById('volume').dataset.published")
        details = browser.execute_script(
            "return fetch('api/state').then((r) => r.json()).then((s) => s.latest.details);"
        )
        assert [details[k] for k in ("fill_ratio", "headspace_m", "capacity_m3")] == [None] * 3
        for row in BIN_ROWS:
            assert browser.find_element("id", row).get_attribute("hidden") is not None, row
        shown = browser.find_element("id", "figures").text
        assert "fill" not in shown and "headspace" not in shown and "capacity" not in shown
    finally:
        agent.kill()


def test_the_bin_figures_are_exported_while_the_last_valid_result_has_them() -> None:
    """Served on a real port: a bin's result exports them, a later result without a bin (a
    reload that removed `[silo.bin]`) takes them out, an invalid one leaves them as they were."""
    port = free_port()
    metrics = Metrics()
    metrics.serve(MetricsConfig(enabled=True, port=port))
    try:
        assert not any(scrape(port).get(name) for name in BIN_METRICS)  # no result yet
        metrics.record_result(ScanSummary.from_json(SUMMARY))
        families = scrape(port)
        assert families["silo_agent_last_fill_ratio"] == [0.25]
        assert families["silo_agent_last_headspace_meters"] == [5.0]
        metrics.record_result(ScanSummary.from_json({**SUMMARY, "valid": False, "fill_ratio": 0}))
        assert scrape(port)["silo_agent_last_fill_ratio"] == [0.25]
        without_bin = {k: v for k, v in SUMMARY.items() if "fill" not in k and "head" not in k}
        metrics.record_result(ScanSummary.from_json({**without_bin, "capacity_m3": None}))
        families = scrape(port)
        assert families["silo_agent_last_volume_cubic_meters"] == [100.0]
        assert not any(families.get(name) for name in BIN_METRICS)
    finally:
        metrics.close()


@pytest.mark.slow
def test_a_scan_that_gave_no_result_is_named_above_the_last_results_figures(
    tmp_path: Path, broker, browser
) -> None:
    """A scan whose cameras all failed is kept nowhere (no directory, no result): the page
    names it, its time and reason, above the figures of the scan before, and takes the line
    away with the next result. It had gone on showing the older figures as the latest, valid,
    with nothing saying the last scan failed."""
    web_port = free_port()
    good = write_config(
        tmp_path / "good.toml", broker.port, tmp_path, web={"enabled": True, "port": web_port}
    )
    first = Daemon(good, tmp_path, "--scans", "1")
    assert first.wait(120) == 0
    (kept,) = [e["scan_id"] for e in first.log() if e.get("event") == "scan finished"]
    broken = write_config(
        tmp_path / "broken.toml",
        broker.port,
        tmp_path,
        cameras=(("broken", None),),
        web={"enabled": True, "port": web_port},
        schedule={"interval_s": 3600, "scan_at_start": True},
    )
    agent = Daemon(broken, tmp_path)
    try:
        (failed,) = agent.wait_log("scan failed")
        browser.get(f"http://127.0.0.1:{web_port}/")
        wait_js(browser, "!document.getElementById('last-failure').hidden")
        line = browser.find_element("id", "last-failure").text
        assert line.startswith(f"Last scan {failed['scan_id']} (") and failed["scan_id"] != kept
        assert "gave no result: capture: no camera delivered a cloud" in line
        assert browser.find_element("id", "scan-id").text == kept  # the figures: the one before
    finally:
        agent.kill()
    agent = Daemon(good, tmp_path)  # a result again: the line goes
    try:
        (finished,) = agent.wait_log("scan finished")
        browser.get(f"http://127.0.0.1:{web_port}/")
        wait_js(browser, f"document.body.dataset.scanId === '{finished['scan_id']}'")
        assert browser.find_element("id", "last-failure").get_attribute("hidden") is not None
    finally:
        agent.kill()


@pytest.mark.slow
def test_the_page_fades_while_the_agent_is_away_and_recovers(
    tmp_path: Path, broker, browser
) -> None:
    """The agent stopped under an open page: the header says reconnecting and the panels
    fade (they had stayed at full strength, the last figures read as current); started again
    on the same port, the page reconnects by itself and shows the state unfaded."""
    web_port = free_port()
    config = write_config(
        tmp_path / "agent.toml", broker.port, tmp_path, web={"enabled": True, "port": web_port}
    )
    agent = Daemon(config, tmp_path)
    try:
        agent.wait_log("scan finished")
        browser.get(f"http://127.0.0.1:{web_port}/")
        wait_js(browser, "document.getElementById('connection').textContent === 'connected'")
        assert not browser.execute_script("return document.body.classList.contains('stale')")
    finally:
        agent.kill()
    wait_js(browser, "document.body.classList.contains('stale')")
    assert browser.find_element("id", "connection").text == "reconnecting…"
    agent = Daemon(config, tmp_path)
    try:
        agent.wait_log("web page serving")
        wait_js(browser, "!document.body.classList.contains('stale')")
        assert browser.find_element("id", "connection").text == "connected"
    finally:
        agent.kill()


@pytest.mark.slow
def test_the_map_legends_read_heights_above_a_floor_that_is_not_at_zero(
    tmp_path: Path, broker, browser
) -> None:
    """A site whose floor is not at z = 0 (here z = -1 m): the page's and the report's map
    legends run from 0.00 m above the floor to the top. They had labelled the silo-frame z of
    the scale's ends as "height above the floor": "-1.00 m" for the floor itself."""
    web_port = free_port()
    config = write_config(
        tmp_path / "agent.toml", broker.port, tmp_path, web={"enabled": True, "port": web_port}
    )
    text = config.read_text()
    assert "floor_z = 0.0\n" in text
    config.write_text(text.replace("floor_z = 0.0\n", "floor_z = -1.0\n", 1))
    agent = Daemon(config, tmp_path)
    try:
        (finished,) = agent.wait_log("scan finished")
        browser.get(f"http://127.0.0.1:{web_port}/")
        wait_js(browser, "document.getElementById('legend-max').textContent !== ''")
        layout = browser.execute_script(
            f"return fetch('api/map/{finished['scan_id']}.json').then((r) => r.json());"
        )
        assert layout["vmin"] == -1.0  # the floor's z: the scale starts there
        top = layout["vmax"] - layout["vmin"]
        assert top > 1.0  # the flat grain, 1 m above z = 0, stands over 1 m above this floor
        shown = [browser.find_element("id", k).text for k in ("legend-min", "legend-max")]
        assert shown == ["0.00 m", f"{top:.2f} m"]
    finally:
        agent.kill()
    report = tmp_path / "report.html"
    done = run_cli("report", finished["scan_id"], "--config", str(config), "--out", str(report))
    assert done.returncode == 0, done.stderr
    legend = re.search(
        r'<p class="legend"><span>([^<]*)</span>.*?<span>([^<]*)</span>', report.read_text()
    )
    assert legend is not None and legend.groups() == ("0.00 m", f"{top:.2f} m")
