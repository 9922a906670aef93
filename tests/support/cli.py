"""The command line as users run it: `python -m silo_agent` in a subprocess."""

from __future__ import annotations

import subprocess
import sys


def run_cli(*args: str, check: bool = False) -> subprocess.CompletedProcess[str]:
    """The real `silo-agent` entry point in a subprocess."""
    return subprocess.run(
        [sys.executable, "-m", "silo_agent", *args],
        capture_output=True,
        text=True,
        check=check,
        timeout=120,
    )
