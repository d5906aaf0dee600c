"""The systems a user would pick instead, measured on the same cases (docs/evaluation-protocol.md).

Each is a class built from ``references: dict[name, (N, 3) points]`` (every reference in its
own model frame) whose ``align(points)`` returns ``{"label", "rotation", "translation",
"score", ...}`` with the pose ``scene_point = rotation @ model_point + translation``.
"""

from __future__ import annotations

import numpy as np


def orient_normals(
    points: np.ndarray, normals: np.ndarray, viewpoint: np.ndarray | None = None
) -> np.ndarray:
    """Flip normals to a consistent side: toward ``viewpoint`` (a depth camera's position)
    when given, else away from the cloud's centroid (a rule that moves with the object, so a
    reference and a full scene of it agree). Returns a new (N, 3) array."""
    points = np.asarray(points, dtype=np.float64)
    normals = np.array(normals, dtype=np.float64)
    if viewpoint is None:
        outward = points - points.mean(axis=0)
    else:
        outward = np.asarray(viewpoint, dtype=np.float64) - points
    flip = np.einsum("ij,ij->i", normals, outward) < 0
    normals[flip] *= -1.0
    return normals
