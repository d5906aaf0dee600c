"""Keep the resident memory of a long-running service flat: glibc's heap, two settings.

Every registration or removal builds a new snapshot (trees, classifier features, the Gram, a
refit) on a worker thread while alignments allocate and free their own arrays on others.
glibc keeps what those frees leave in its arenas for later use, and returns little of it:

- Blocks of 128 KiB and more get pages of their own (mmap) and give them back when freed,
  but glibc raises that threshold to the largest such block freed so far (up to 32 MiB).
  After the first refit freed an 8 MiB Gram, the engine's arrays came from the arenas and
  pinned their pages there. ``fix_mmap_threshold`` keeps it at 128 KiB.
- Free pages between live blocks stay resident. ``release_free_heap`` (``malloc_trim``)
  hands them back; the catalog calls it after each change (a few milliseconds).

Measured (scripts/load.py, docs/operations.md#memory): a growing gallery cost 2.2 MiB of
resident memory a reference, where a reference holds 0.7 MB; with the trim alone, three
changes a second beside two aligning threads still crept up by 1.4 MiB a minute, with both
it stayed flat (+0.1). Other C libraries are left alone.
"""

from __future__ import annotations

import ctypes
import functools
import logging

M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter
MMAP_THRESHOLD = 128 * 1024  # bytes: glibc's own starting value, kept from moving

log = logging.getLogger(__name__)


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    libc = ctypes.CDLL(None)  # the process's own C library
    if all(hasattr(libc, name) for name in ("gnu_get_libc_version", "mallopt", "malloc_trim")):
        return libc
    log.info("not glibc: the heap is left to the C library")
    return None


def fix_mmap_threshold() -> bool:
    """Give every block of 128 KiB or more pages of its own, for good; True if glibc took it.

    Call once, early: blocks allocated before keep where they are.
    """
    libc = _glibc()
    return libc is not None and bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD))


def release_free_heap() -> bool:
    """Return the heap's free pages to the system; True if the C library did (glibc only)."""
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)  # its result says whether anything was released, not whether it worked
    return True
