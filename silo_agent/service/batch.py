"""`silo-agent process` over one or many scan directories in one process.

Re-processing an archive pays the imports once instead of once per scan, and a fresh process
faults every array in for the first time: the second scan of a batch runs faster than the
first. Each scan goes through `outcome_of`; a scan that fails is one line on stderr naming
its directory and the others go on. Nothing here imports numpy, scipy or pydantic at module
level, so `process --help` stays quick.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from silo_agent.base.exits import CONFIG_ERROR, DATA_ERROR, FAILURE

if TYPE_CHECKING:
    from silo_agent.config import Config

MANIFEST = "scan.json"  # silo_agent.scan.MANIFEST, not imported: no numpy before it is needed
PROGRESS_MIN_SCANS = 4  # a progress bar only for batches longer than this


@dataclass(frozen=True)
class Options:
    """What applies to every scan of the batch: --config (already loaded) and the flags."""

    config: Config | None = None
    grid_step: float | None = None
    method: str | None = None
    json: bool = False


@dataclass(frozen=True)
class Processed:
    """One scan's outcome; `output` is its stdout text (a JSON line or a summary)."""

    scan_dir: str
    status: int  # 0, DATA_ERROR, CONFIG_ERROR or FAILURE
    output: str = ""
    error: str = ""


def scan_dirs(targets: Sequence[Path]) -> list[Path]:
    """The scan directories to process: each target that is a scan (has scan.json) or is not
    a directory of scans, and the scans directly inside a directory of scans (an audit
    cache), in name order. A target that is neither stays, so it fails with a clear line."""
    found: list[Path] = []
    for target in targets:
        if target.is_dir() and not (target / MANIFEST).exists():
            children = sorted(
                c
                for c in target.iterdir()
                if not c.name.startswith(".") and (c / MANIFEST).is_file()
            )
            if children:
                found += children
                continue
        found.append(target)
    return found


def outcome_of(directory: Path, options: Options) -> Processed:
    """`scan_path.process_directory` of one scan, its outcome as a line to print; never
    raises for a bad scan."""
    from silo_agent.base.limits import LimitExceeded
    from silo_agent.config import ConfigError
    from silo_agent.detect import ModelError
    from silo_agent.scan import ScanError
    from silo_agent.service.scan_path import process_directory

    name = str(directory)
    try:
        _scan, result, summary = process_directory(
            directory, options.config, options.grid_step, options.method, release_points=True
        )
    except ScanError as exc:  # its message names the file already
        return Processed(name, DATA_ERROR, error=str(exc))
    except LimitExceeded as exc:  # a grid or cloud past the documented limits
        return Processed(name, DATA_ERROR, error=f"{name}: {exc}")
    except (ConfigError, ModelError) as exc:
        return Processed(name, CONFIG_ERROR, error=f"{name}: {exc}")
    except Exception as exc:  # a bug or an odd scan must not stop the rest of a batch
        return Processed(
            name, FAILURE, error=f"{name}: processing failed: {type(exc).__name__}: {exc}"
        )
    if options.json:
        return Processed(
            name, 0, json.dumps({**summary.to_json(), "scan_dir": name}, allow_nan=False)
        )
    return Processed(name, 0, result.describe())


def _outcomes(dirs: Sequence[Path], options: Options, jobs: int) -> Iterator[Processed]:
    """Each scan's outcome in the order given, from `jobs` worker processes if more than one."""
    if jobs <= 1 or len(dirs) <= 1:
        for directory in dirs:
            yield outcome_of(directory, options)
        return
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(max_workers=min(jobs, len(dirs))) as pool:
        yield from pool.map(outcome_of, dirs, [options] * len(dirs))


class Progress:
    """A one-line bar on a terminal's stderr, redrawn in place; nothing when not a TTY."""

    WIDTH = 30

    def __init__(self, total: int, stream: TextIO) -> None:
        self.total = total
        self.stream = stream
        self.shown = total > PROGRESS_MIN_SCANS and stream.isatty()

    def update(self, done: int, name: str) -> None:
        if self.shown:
            filled = self.WIDTH * done // self.total
            bar = "#" * filled + "." * (self.WIDTH - filled)
            self.stream.write(f"\r\x1b[K[{bar}] {done}/{self.total} {name}")
            self.stream.flush()

    def clear(self) -> None:
        """Erase the bar so a message line starts at column 0."""
        if self.shown:
            self.stream.write("\r\x1b[K")
            self.stream.flush()


def run(targets: Sequence[Path], options: Options, jobs: int = 1) -> int:
    """Process every scan of `targets`, print each result as it comes (in the order given) and
    return the exit status: 0 when all were processed, else the status of the first failure
    (65 bad scan data, 78 bad settings or model, 1 other); the count is the last stderr line."""
    dirs = scan_dirs(targets)
    progress = Progress(len(dirs), sys.stderr)
    failed: list[Processed] = []
    for done, outcome in enumerate(_outcomes(dirs, options, jobs), start=1):
        progress.clear()
        if outcome.status == 0:
            print(outcome.output, flush=True)
        else:
            failed.append(outcome)
            print(f"silo-agent: {outcome.error}", file=sys.stderr, flush=True)
        progress.update(done, Path(outcome.scan_dir).name)
    progress.clear()
    if len(dirs) > 1:
        print(
            f"silo-agent: {len(dirs) - len(failed)} of {len(dirs)} scans processed"
            + (f", {len(failed)} failed" if failed else ""),
            file=sys.stderr,
        )
    return failed[0].status if failed else 0
