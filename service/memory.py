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

While a camera frame is searched (``frame_heap``), both thresholds are raised: a frame's
arrays (300,000 points: 2-7 MB each, dozens a frame) would otherwise each get fresh pages,
zeroed and faulted in, unmapped again when freed, and the heap's top handed back whenever
128 KiB of it was free; the engine ran 1.6-2 times slower in the service than in a plain
process. Once no frame has been searched for ``FRAME_IDLE_S`` the thresholds are restored and
the heap trimmed: trimmed after each frame, the next one faulted its pages in again, at times
100-190 ms of a 1280 x 720 frame's first arrays where they took 6 ms
(docs/decisions.md#the-heaps-thresholds).

Measured (scripts/load.py, docs/operations.md#memory): a growing gallery cost 2.2 MiB of
resident memory a reference, where a reference holds 0.7 MB; with the trim alone, three
changes a second beside two aligning threads still crept up by 1.4 MiB a minute, with both
it stayed flat (+0.1). Other C libraries are left alone.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters
MMAP_THRESHOLD = 128 * 1024  # bytes: glibc's own starting value, kept from moving
TRIM_THRESHOLD = 128 * 1024  # bytes: glibc's own, which a fixed mmap threshold keeps
FRAME_MMAP_THRESHOLD = 32 << 20  # while a frame is searched: glibc's own ceiling for it ...
FRAME_TRIM_THRESHOLD = 256 << 20  # ... and the heap's free top kept for the next arrays
FRAME_IDLE_S = 1.0  # ... until no frame has been searched this long (a camera's next frame)

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


_frames = 0  # frames being searched now, in this process
_frames_lock = threading.Lock()
_idle: threading.Timer | None = None  # restores the thresholds once no frame came for a while


@contextmanager
def frame_heap() -> Iterator[None]:
    """While a camera frame is searched, its arrays come from the heap and are reused; once no
    frame has been searched (in any thread) for ``FRAME_IDLE_S``, the thresholds are fixed
    again and the heap trimmed (glibc only; elsewhere nothing changes)."""
    global _frames, _idle
    libc = _glibc()
    if libc is None:
        yield
        return
    with _frames_lock:
        _frames += 1
        if _idle is not None:  # the heap of the frame before is this one's
            _idle.cancel()
            _idle = None
        if _frames == 1:
            libc.mallopt(M_MMAP_THRESHOLD, FRAME_MMAP_THRESHOLD)
            libc.mallopt(M_TRIM_THRESHOLD, FRAME_TRIM_THRESHOLD)
    try:
        yield
    finally:
        with _frames_lock:
            _frames -= 1
            if _frames == 0:
                _idle = threading.Timer(FRAME_IDLE_S, _frames_done)
                _idle.daemon = True
                _idle.start()


def _frames_done() -> None:
    """No frame came for ``FRAME_IDLE_S``: the thresholds restored, the heap trimmed."""
    global _idle
    libc = _glibc()
    with _frames_lock:
        if _frames or _idle is not threading.current_thread():  # a frame came meanwhile
            return
        _idle = None
        libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)
        libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    release_free_heap()
