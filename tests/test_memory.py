"""Free heap pages go back to the system after a gallery change (service.memory)."""

from __future__ import annotations

import ctypes
import json
import subprocess
import sys

import pytest

from service.memory import release_free_heap

GLIBC = hasattr(ctypes.CDLL(None), "gnu_get_libc_version")

# In a child, so that its heap is nobody else's: 256 MiB in 64 KiB blocks (below glibc's mmap
# threshold: they come from the heap), every 16th kept alive so no free stretch reaches the
# top of the heap, the rest freed. Resident memory before and after the release.
FRAGMENT = """
import json
from pathlib import Path
from service.memory import release_free_heap

def rss_mib():
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024

blocks = [bytearray(b"x" * 65536) for _ in range(4096)]
kept = blocks[::16]
del blocks
before = rss_mib()
released = release_free_heap()
print(json.dumps({"released": released, "before": before, "after": rss_mib()}))
"""


@pytest.mark.skipif(not GLIBC, reason="glibc only")
def test_free_pages_between_live_blocks_go_back_to_the_system():
    done = subprocess.run(
        [sys.executable, "-c", FRAGMENT], capture_output=True, text=True, check=True, timeout=60
    )
    result = json.loads(done.stdout)
    assert result["released"] is True
    assert result["before"] - result["after"] > 128  # of the 240 MiB freed, most goes back


def test_release_is_safe_to_call_at_any_time():
    assert release_free_heap() is GLIBC
    assert release_free_heap() is GLIBC
