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


# What numpy prints of itself after the command line ran a command (a missing directory:
# refused, after the command's set-up), in a fresh process.
AFTER_A_COMMAND = """
import sys
from silo_agent.cli import main
main(["process", sys.argv[1]])
import numpy
from threadpoolctl import threadpool_info
print(numpy._core.multiarray._get_madvise_hugepage())  # whether numpy advises huge pages
print(*[pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"])
"""


def _after_a_command(tmp_path, unset: str, environment: dict[str, str]) -> tuple[str, set[str]]:
    """(huge-page advice, the thread counts of the BLAS libraries loaded: numpy's and scipy's)
    with `unset` taken out of the environment and `environment` added."""
    import os

    env = {k: v for k, v in os.environ.items() if k != unset} | environment
    out = subprocess.run(
        [sys.executable, "-c", AFTER_A_COMMAND, str(tmp_path / "missing")],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    advice, threads = out.stdout.splitlines()
    return advice, set(threads.split())


def test_commands_run_numpy_without_huge_page_advice_unless_asked(tmp_path) -> None:
    unset = "NUMPY_MADVISE_HUGEPAGE"
    assert _after_a_command(tmp_path, unset, {})[0] == "False"
    assert _after_a_command(tmp_path, unset, {unset: "1"})[0] == "True"


def test_commands_run_blas_on_one_thread_unless_asked(tmp_path) -> None:
    unset = "OPENBLAS_NUM_THREADS"
    assert _after_a_command(tmp_path, unset, {})[1] == {"1"}
    assert _after_a_command(tmp_path, unset, {unset: "2"})[1] == {"2"}
