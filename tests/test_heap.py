"""The agent keeps freed array memory for the next scan (silo_agent/base/heap.py), runs numpy
without huge-page advice and BLAS on one thread (silo_agent/cli `_dispatch`)."""

from __future__ import annotations

import subprocess
import sys

# Page faults taken by re-allocating and filling an array after freeing one of that size.
SNIPPET = """
import resource, sys
import numpy as np
from silo_agent.base.heap import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
size = int(sys.argv[2])
np.ones(size)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
np.ones(size)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str, floats: int) -> int:
    out = subprocess.run(
        [sys.executable, "-c", SNIPPET, mode, str(floats)],
        capture_output=True,
        text=True,
        check=True,
    )
    return int(out.stdout)


def test_freed_arrays_are_reused_without_page_faults() -> None:
    for floats in (2_000_000, 8_000_000):  # 16 MB, and 64 MB: past glibc's largest threshold
        assert _faults("default", floats) > 50  # glibc hands it back and faults it in again
        assert _faults("keep", floats) < 5


# Whether numpy advises huge pages on its arrays, after the command line ran a command.
HUGE_PAGES = """
import sys
from silo_agent.cli import main
main(["process", sys.argv[1]])  # a missing directory: refused, after the command's set-up
import numpy
print(numpy._core.multiarray._get_madvise_hugepage())
"""


def _advised(tmp_path, environment: dict[str, str]) -> str:
    import os

    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"} | environment
    out = subprocess.run(
        [sys.executable, "-c", HUGE_PAGES, str(tmp_path / "missing")],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    return out.stdout.strip()


def test_commands_run_numpy_without_huge_page_advice_unless_asked(tmp_path) -> None:
    assert _advised(tmp_path, {}) == "False"
    assert _advised(tmp_path, {"NUMPY_MADVISE_HUGEPAGE": "1"}) == "True"


# How many threads OpenBLAS runs, after the command line ran a command.
BLAS_THREADS = """
import sys
from silo_agent.cli import main
main(["process", sys.argv[1]])  # a missing directory: refused, after the command's set-up
import numpy
from threadpoolctl import threadpool_info
print(*[pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"])
"""


def _blas_threads(tmp_path, environment: dict[str, str]) -> set[str]:
    """The thread counts of the BLAS libraries loaded (numpy's and scipy's)."""
    import os

    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"} | environment
    out = subprocess.run(
        [sys.executable, "-c", BLAS_THREADS, str(tmp_path / "missing")],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    return set(out.stdout.split())


def test_commands_run_blas_on_one_thread_unless_asked(tmp_path) -> None:
    assert _blas_threads(tmp_path, {}) == {"1"}
    assert _blas_threads(tmp_path, {"OPENBLAS_NUM_THREADS": "2"}) == {"2"}
