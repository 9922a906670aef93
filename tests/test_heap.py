"""The agent keeps freed array memory for the next scan (silo_agent/base/heap.py)."""

from __future__ import annotations

import subprocess
import sys

# Page faults taken by re-allocating and filling a 16 MB array after freeing one of that size.
SNIPPET = """
import resource, sys
import numpy as np
from silo_agent.base.heap import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
np.ones(2_000_000)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
np.ones(2_000_000)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> int:
    out = subprocess.run(
        [sys.executable, "-c", SNIPPET, mode], capture_output=True, text=True, check=True
    )
    return int(out.stdout)


def test_freed_arrays_are_reused_without_page_faults() -> None:
    assert _faults("default") > 50  # glibc hands the 16 MB back and faults it in again
    assert _faults("keep") < 5
