"""Hand the heap's free pages back to the system after a gallery change.

Every registration or removal builds a new snapshot (trees, classifier features, a refit) on a
worker thread while alignments allocate and free their own arrays on others. glibc keeps the
pages those frees leave behind in its arenas for later use, and seldom returns them, so without
a trim the resident memory of a service grew by about 1.5 MB per registered reference where
the reference itself holds 0.7 MB (scripts/load.py; README, "Sustained load"). ``malloc_trim``
returns every whole free page; it takes a few milliseconds, once per change. Other C libraries
are left alone.
"""

from __future__ import annotations

import ctypes
import functools
import logging

log = logging.getLogger(__name__)


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    libc = ctypes.CDLL(None)  # the process's own C library
    if hasattr(libc, "gnu_get_libc_version") and hasattr(libc, "malloc_trim"):
        return libc
    log.info("not glibc: free heap pages are left to the C library")
    return None


def release_free_heap() -> bool:
    """Return the heap's free pages to the system; True if the C library did (glibc only)."""
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)  # its result says whether anything was released, not whether it worked
    return True
