"""A verified pose hypothesis of one candidate part: what the search ranks and refines."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Fit:
    """One verified (and perhaps refined) hypothesis of one candidate."""

    row: int  # the candidate's row in the classifier
    rotation: np.ndarray
    translation: np.ndarray
    source: str  # the hypothesis source it came from (service.engine.hypotheses.SOURCES, ...)
    view: int  # the view the camera was expected to see (-1: the whole part)
    fit: float
    coverage: float
    refined: bool = False
    settled: bool = False  # its last refinement stopped before its iterations ran out

    @property
    def score(self) -> float:
        return self.fit * self.coverage
