"""What one ``Engine.align`` call works on: the query (what was asked, and its clock) and one
reading of the observation as steps 1-3 leave it, and step 4's ranking of the parts."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from service.engine.entry import Snapshot
from service.engine.tuning import NOISE_TOLERANCES


class Stopwatch:
    """Milliseconds per step, in the order the steps ran."""

    def __init__(self):
        self.timings: dict[str, float] = {}
        self.began = self.last = time.perf_counter()

    def lap(self, step: str) -> None:
        now = time.perf_counter()
        self.timings[step] = self.timings.get(step, 0.0) + (now - self.last) * 1e3
        self.last = now

    def total(self) -> dict[str, float]:
        self.timings["total"] = (time.perf_counter() - self.began) * 1e3
        return {k: round(v, 3) for k, v in self.timings.items()}


@dataclass
class Query:
    """What one ``align`` call asked, and its clock."""

    snapshot: Snapshot
    allowed: np.ndarray  # the classifier rows the caller allows
    sources: tuple[str, ...]
    top_k: int | None
    refine: bool
    viewpoint: np.ndarray | None
    rng: np.random.Generator
    clock: Stopwatch
    noise: float = 0.0  # the sensor's depth noise (sigma) where the part lies, if known
    rescued: int | None = None  # parts rescued where none fits well (None: the settings')

    def tolerance(self, fraction: float, scale: float) -> float:
        """A distance tolerance of ``fraction`` of a part's ``scale``, but never under
        ``NOISE_TOLERANCES`` times the sensor's noise: a small part far from the camera is
        measured no finer than the sensor measures (docs/decisions.md#detect)."""
        return max(fraction * scale, NOISE_TOLERANCES * self.noise)


@dataclass
class Observed:
    """One reading of the observation after steps 1-3."""

    scene: np.ndarray  # (M, 3) every point of the reading
    points: np.ndarray  # (n, 3) the network's sample of them (1. normalise)
    size: float  # the sample's radius
    spacing: float  # the reading's median distance between neighbouring points
    mapped: np.ndarray | None = None  # (n, 2) their 2-D coordinates (2. map)
    grid: np.ndarray | None = None  # (64, 64) the grid of those (3. grid)
    nearest_views: list[int] = field(default_factory=list)  # rows, by their views' likeness
    whole: bool = False  # a whole part's cloud, searched without its single views


@dataclass(frozen=True)
class Ranking:
    """Step 4's answer: eq. (4)'s score per classifier row, the rows of a plausible size best
    first, the few verified in every pass, and eq. (4)'s first choice when it is sure of it."""

    scores: np.ndarray
    ranked: np.ndarray
    shortlist: np.ndarray
    first: int | None
