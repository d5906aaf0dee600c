"""The last alignments the service answered, kept in memory so that the console can replay them.

A bounded ring (``Settings.recent_alignments`` entries; the oldest goes first): each entry keeps
the points as aligned (float32), the viewpoint used, where the points came from and the answer.
It holds every caller's points, so it is off once API keys are configured, unless asked for.
A camera frame is kept thinned to ``KEPT_POINTS`` (every k-th point), so that 20 entries hold
at most 16 MB however large the clouds (at the 3,145,728-point limit, 755 MB whole).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from service.api.schemas import AlignResponse

KEPT_POINTS = 65536  # an entry's points at most: what the console draws of a frame


@dataclass(frozen=True)
class Recorded:
    id: int
    time: float  # seconds since the epoch
    source: str  # "json", "raw" or "file <name>"
    points: np.ndarray  # (N, 3) float32, as aligned
    viewpoint: list[float] | None
    answer: AlignResponse


class RecentAlignments:
    """A thread-safe ring of ``Recorded`` alignments; a capacity of 0 keeps nothing."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._entries: deque[Recorded] = deque(maxlen=capacity or None)
        self._lock = threading.Lock()
        self._next_id = 1

    def add(
        self,
        points: np.ndarray,
        viewpoint: list[float] | None,
        source: str,
        answer: AlignResponse,
    ) -> None:
        if not self.capacity:
            return
        if len(points) > KEPT_POINTS:
            points = points[:: -(-len(points) // KEPT_POINTS)]  # every k-th, at most KEPT_POINTS
        with self._lock:
            entry = Recorded(self._next_id, time.time(), source, points, viewpoint, answer)
            self._entries.append(entry)
            self._next_id += 1

    def newest_first(self) -> list[Recorded]:
        with self._lock:
            return list(reversed(self._entries))

    def get(self, entry_id: int) -> Recorded | None:
        with self._lock:
            return next((entry for entry in self._entries if entry.id == entry_id), None)
