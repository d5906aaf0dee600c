"""The gallery: registered references and the file format the shipped gallery uses.

A reference holds what recognition and pose estimation need of an object: its
points in the model frame the user gave, their mapped 2-D coordinates, the grids
of augmented views the classifier is fitted on, and its scale. The shipped
gallery is one ``.npz`` (arrays only, never pickle) with a JSON ``meta`` entry.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

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


def save_gallery(path: Path, references: list[Reference], meta: dict) -> None:
    arrays: dict[str, np.ndarray] = {
        "names": np.array([r.name for r in references]),
        "scales": np.array([r.scale for r in references], dtype=np.float64),
        "meta": np.array(json.dumps(meta)),
    }
    for i, reference in enumerate(references):
        arrays[f"points_{i}"] = reference.points.astype(np.float32)
        arrays[f"mapped_{i}"] = reference.mapped.astype(np.float32)
        arrays[f"view_grids_{i}"] = reference.view_grids.astype(np.float32)
    np.savez_compressed(path, **arrays)


def load_gallery(path: Path) -> tuple[list[Reference], dict]:
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
        references = [
            Reference(
                name=str(name),
                points=data[f"points_{i}"],
                mapped=data[f"mapped_{i}"],
                view_grids=data[f"view_grids_{i}"],
                scale=float(data["scales"][i]),
            )
            for i, name in enumerate(data["names"])
        ]
    return references, meta
