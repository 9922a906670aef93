"""Keep freed array memory in the process between scans instead of handing it back (glibc).

glibc serves every allocation above its mmap threshold (128 KiB at start) with a fresh mmap and
unmaps it on free. A reconstruction allocates and frees dozens of 10-20 MB arrays, and the
kernel faults and zeroes each new one page by page: about a fifth of the reconstruction time
(bench/speed.py measures it). Raising the mmap and trim thresholds makes glibc keep those pages
in its heap and reuse them. The threshold stops at 32 MiB, and a big silo's arrays are larger
(4 M cells of float64 at 1 cm, 6-10 M points): so glibc is told to map no block at all, and
every block comes from the heap. A 20 m silo, 16 full-resolution cameras, 1 cm: 1.25 M page
faults and 3.4 s of system time against 0.33 M and 1.0 s, the same peak (1.18 against 1.16
GB; `process`, one core, bench/silos.py's scan). The price: the process keeps its peak heap
between scans (a few hundred MB for four 400k-point clouds at a 1 cm grid, about 1.2 GB for
that silo). Other C libraries: nothing changes.

numpy also asks the kernel for transparent huge pages (madvise) on every array of 4 MB or more.
Where the kernel's THP defrag is `madvise` (Debian's default), each such fault may compact
memory first: on the bench machine that made a 12 m silo's `process` at 1 cm take 2.40 s of CPU
instead of 1.97 s (median of 4 alternating runs each; bench/silos.py's scan). `small_pages`
asks numpy, before it is imported, not to; the documented NUMPY_MADVISE_HUGEPAGE=1 still wins.
"""

from __future__ import annotations

import ctypes
import os

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameter numbers (malloc.h)
M_MMAP_THRESHOLD = -3
M_MMAP_MAX = -4
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # glibc's maximum ...
MMAP_MAX_BLOCKS = 0  # ... and past it, no mapped block at all: the heap serves every one
TRIM_THRESHOLD_BYTES = 1024 * 1024 * 1024


def keep_freed_memory() -> bool:
    """Ask glibc to reuse freed blocks of any size; False where mallopt is not available."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    settings = (
        (M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES),
        (M_MMAP_MAX, MMAP_MAX_BLOCKS),
        (M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
    )
    return all([bool(mallopt(parameter, value)) for parameter, value in settings])


def small_pages() -> None:
    """Before numpy is imported: no huge-page advice on its arrays unless the environment asks."""
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
