"""A reference: what recognition and pose estimation need of one registered object.

Its points in the model frame the user gave, their mapped 2-D coordinates, the grids
of augmented views the classifier is fitted on, and its scale.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class Reference:
    name: str
    points: np.ndarray  # (N, 3) float32, the model frame the user gave
    mapped: np.ndarray  # (N, 2) float32, the network's 2-D coordinates of ``points``
    view_grids: np.ndarray  # (V, 64, 64) float32, grids of augmented views
    scale: float  # radius: the largest distance from the centroid to a point

    @cached_property
    def points_sha256(self) -> str:
        """sha256 of the points as little-endian float32 x y z triples, row after row: what a
        client computes of the points it sent, to check the service holds exactly those."""
        return points_sha256(self.points)


def points_sha256(points: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(points, dtype="<f4").tobytes()).hexdigest()
