"""The audit cache's listing against the number of scans it holds.

`AuditCache.entries` lists the scans (retention, pile ids and the page call it two or three
times a scan). A first call reads every directory (its manifest, every file's size): what each
call cost before 2026-12-05; later calls read again only the directories whose mtime moved.
The cache is N copies (hard links: no disk) of one simulated scan of eight 848x480 cameras
(bin-heap, eave layout: its eight clouds and its manifest), five minutes
apart; median of `--runs` calls of each kind.

Writes Markdown with its provenance (bench/results/cache.md holds a run).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

from benchlib import header, pinned, write_report

from silo_agent.config import AuditConfig
from silo_agent.sim import simulate
from silo_agent.storage.audit import FRESH_NS, AuditCache

SILO = "bench"
T0 = datetime(2026, 1, 1, tzinfo=UTC)


def cache_of(root: Path, scans: int, source: Path) -> AuditCache:
    """`scans` hard-linked copies of `source` under `root`, named as the agent names scans,
    their directories aged past FRESH_NS."""
    aged = time.time_ns() - 10 * FRESH_NS
    for k in range(scans):
        directory = root / f"{SILO}-{T0 + timedelta(minutes=5 * k):%Y%m%dT%H%M%SZ}"
        directory.mkdir()
        for item in source.iterdir():
            os.link(item, directory / item.name)
        os.utime(directory, ns=(aged, aged))
    return AuditCache(AuditConfig(directory=root), SILO)


def median_s(call: Callable[[], object], runs: int) -> float:
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scans", default="500,2000,8000", help="comma list of cache sizes")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--cpu", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("bench/results/cache.md"))
    args = p.parse_args(argv)
    pinned(args.cpu)
    load = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        source_cache = AuditCache(AuditConfig(directory=work / "source"), SILO)
        scan = simulate("bin-heap", [f"A{k}" for k in range(1, 9)], seed=0, layout="eave")
        scan = replace(scan, silo_id=SILO, scan_id=f"{SILO}-{T0:%Y%m%dT%H%M%SZ}")
        source = source_cache.write_scan(scan, {})
        files = len(list(source.iterdir()))
        for count in (int(n) for n in args.scans.split(",")):
            root = work / f"cache-{count}"
            root.mkdir()
            cache = cache_of(root, count, source)

            def cold(root: Path = root) -> None:  # a new cache reads every directory
                AuditCache(AuditConfig(directory=root), SILO).entries()

            first = median_s(cold, args.runs)
            cache.entries()
            again = median_s(cache.entries, args.runs)
            listed = len(cache.entries())
            rows.append(
                f"| {count:,} | {listed:,} | {first:.3f} | {again:.4f} | {first / again:.0f}x |"
            )
            print(rows[-1], flush=True)
    lines = [
        f"Each scan directory holds {files} files. Seconds a call, one core.",
        "",
        "| scans cached | listed | every directory read (each call before) | again, nothing"
        " changed | faster |",
        "|---|---|---|---|---|",
        *rows,
        "",
    ]
    write_report(args.out, header("The audit cache's listing"), load, lines, "the seconds")


if __name__ == "__main__":
    main()
