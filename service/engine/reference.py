"""A reference: what recognition and pose estimation need of one registered object.

Its points in the model frame the user gave, their mapped 2-D coordinates, the grids of
augmented views the classifier is fitted on, and its scale; then what registration derives
from them once (``Engine.make_reference``), so that no query pays for it: outward surface
normals, which points each rendered single-camera view sees and the features of its grid, a
distance field, and the part's rotational symmetry. A reference stored before a derived field
existed has it ``None``; the engine fills it in from the points (``Engine.complete``).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, fields, replace
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class Reference:
    name: str
    points: np.ndarray  # (N, 3) float32, the model frame the user gave
    mapped: np.ndarray  # (N, 2) float32, the network's 2-D coordinates of ``points``
    view_grids: np.ndarray  # (V, 64, 64) float32, grids of augmented full views (eq. 4)
    scale: float  # radius: the largest distance from the centroid to a point
    # derived at registration
    normals: np.ndarray | None = None  # (N, 3) float32, unit, outward
    visibility: np.ndarray | None = None  # (K, ceil(N / 8)) uint8: the points each view sees
    view_features: np.ndarray | None = None  # (K, F) float16: each view's grid, pooled
    field: np.ndarray | None = None  # (X, Y, Z) uint16: the point nearest each voxel centre
    field_frame: np.ndarray | None = None  # (4,) float64: voxel (0,0,0)'s centre, voxel edge
    symmetry: dict | None = None  # {"kind": "none" | "revolution" | "discrete", ...}
    # the parts its registration check could not tell it from: name -> their points_sha256
    # then (``service.engine.look_alikes``); None: none, or stored before the field existed
    look_alikes: dict | None = None

    @cached_property
    def points_sha256(self) -> str:
        """sha256 of the points as little-endian float32 x y z triples, row after row: what a
        client computes of the points it sent, to check the service holds exactly those."""
        return points_sha256(self.points)

    @property
    def missing(self) -> list[str]:
        """The derived fields this reference lacks (stored before they existed)."""
        return [f.name for f in fields(self) if f.name in DERIVED and getattr(self, f.name) is None]

    def visible(self) -> np.ndarray:
        """(K, N) bool: the points each rendered view sees."""
        bits = np.unpackbits(self.visibility, axis=1, count=len(self.points))
        return bits.astype(bool)

    def with_(self, **changes) -> Reference:
        return replace(self, **changes)


DERIVED = ("normals", "visibility", "view_features", "field", "field_frame", "symmetry")


def points_sha256(points: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(points, dtype="<f4").tobytes()).hexdigest()
