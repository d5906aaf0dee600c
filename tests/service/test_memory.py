"""glibc's heap hands freed memory back to the system (service.memory)."""

from __future__ import annotations

import ctypes
import json
import subprocess
import sys

import pytest

from service.memory import fix_mmap_threshold, release_free_heap

GLIBC = hasattr(ctypes.CDLL(None), "gnu_get_libc_version")

CHILD = """
import json, sys
from pathlib import Path

def rss_mib():
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
"""

# In a child, so that its heap is nobody else's: 256 MiB in 64 KiB blocks (below glibc's mmap
# threshold: they come from the heap), every 16th kept alive so no free stretch reaches the
# top of the heap, the rest freed. Resident memory before and after the release.
FRAGMENT = (
    CHILD
    + """
from service.memory import release_free_heap

blocks = [bytearray(b"x" * 65536) for _ in range(4096)]
kept = blocks[::16]
del blocks
before = rss_mib()
released = release_free_heap()
print(json.dumps({"released": released, "before": before, "after": rss_mib()}))
"""
)


@pytest.mark.skipif(not GLIBC, reason="glibc only")
def test_free_pages_between_live_blocks_go_back_to_the_system():
    done = subprocess.run(
        [sys.executable, "-c", FRAGMENT], capture_output=True, text=True, check=True, timeout=60
    )
    result = json.loads(done.stdout)
    assert result["released"] is True
    assert result["before"] - result["after"] > 128  # of the 240 MiB freed, most goes back


# 1 MiB blocks after a 16 MiB one was freed, each followed by a smaller live one, then freed:
# glibc's own threshold (raised to 16 MiB) takes them from the heap, where the small blocks
# pin their pages; a fixed threshold maps each one apart and unmaps it when freed.
LARGE_BLOCKS = (
    CHILD
    + """
from service.memory import fix_mmap_threshold

fixed = fix_mmap_threshold() if sys.argv[1] == "fixed" else None
big = bytearray(16 << 20)
del big  # a 16 MiB block, freed
blocks, pins = [], []
for _ in range(128):
    blocks.append(bytearray(1 << 20))  # zero-filled: its pages are touched
    pins.append(bytearray(100_000))  # under the threshold: from the heap, right after it
before = rss_mib()
del blocks
print(json.dumps({"fixed": fixed, "freed_mib": before - rss_mib()}))
"""
)


def large_blocks(mode: str) -> dict:
    done = subprocess.run(
        [sys.executable, "-c", LARGE_BLOCKS, mode],
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    return json.loads(done.stdout)


@pytest.mark.skipif(not GLIBC, reason="glibc only")
def test_with_a_fixed_mmap_threshold_freed_large_blocks_leave_the_process():
    assert large_blocks("glibc")["freed_mib"] < 32  # glibc's own way: the pages stay
    fixed = large_blocks("fixed")
    assert fixed["fixed"] is True
    assert fixed["freed_mib"] > 96  # of 128 MiB


def test_release_is_safe_to_call_at_any_time():
    assert release_free_heap() is GLIBC
    assert release_free_heap() is GLIBC
    assert fix_mmap_threshold() is GLIBC  # and so is fixing the threshold again


# While a frame is searched, 1 MiB blocks come from the heap and stay there when freed (the
# next array reuses them); so they do for the next frame, and once no frame came for
# FRAME_IDLE_S the heap is trimmed, and the next blocks that no freed one holds get pages of
# their own again (docs/decisions.md#the-heaps-thresholds).
FRAME = (
    CHILD
    + """
import time
from service.memory import FRAME_IDLE_S, fix_mmap_threshold, frame_heap

def churn(mib):
    blocks, pins = [], []
    for _ in range(128 // mib):
        blocks.append(bytearray(mib << 20))
        pins.append(bytearray(100_000))
    before = rss_mib()
    del blocks
    return pins, before - rss_mib()

fix_mmap_threshold()
with frame_heap():
    pins, freed_in_frame = churn(1)
    before_trim = rss_mib()
kept = before_trim - rss_mib()  # at once: the next frame's
time.sleep(FRAME_IDLE_S + 1.0)
after_frame = before_trim - rss_mib()
more, freed_after = churn(2)  # larger than the heap's freed blocks
print(json.dumps({"in_frame": freed_in_frame, "kept": kept, "trimmed": after_frame,
                  "after": freed_after}))
"""
)


@pytest.mark.skipif(not GLIBC, reason="glibc only")
def test_a_frames_arrays_stay_in_the_heap_until_no_frame_comes():
    done = subprocess.run(
        [sys.executable, "-c", FRAME], capture_output=True, text=True, check=True, timeout=60
    )
    result = json.loads(done.stdout)
    assert result["in_frame"] < 32  # of 128 MiB freed: kept for the next arrays
    assert result["kept"] < 32  # ... and for the next frame's, right after this one
    assert result["trimmed"] > 96  # handed back once no frame came for FRAME_IDLE_S
    assert result["after"] > 96  # and the fixed threshold is back: pages of their own
