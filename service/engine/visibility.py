"""Which points of a cloud a single depth camera would see.

Hidden-point removal (Katz, Tal and Basri, SIGGRAPH 2007): flip every point about a
large sphere centred on the camera (p -> p + 2 (R - |p|) p / |p|); the points that
land on the convex hull of the flipped cloud and the camera are the visible ones.
Used to make partial views: the evaluation's "partial" family and the classifier's
augmented views, so that a half-seen part is still recognised.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from service.engine.tuning import HPR_LOG_RADIUS


def visible_points(points: np.ndarray, camera: np.ndarray) -> np.ndarray:
    """Which of ``points`` (a surface sample) are seen from ``camera``: a boolean mask."""
    relative = np.asarray(points, dtype=np.float64) - np.asarray(camera, dtype=np.float64)
    norms = np.linalg.norm(relative, axis=1, keepdims=True)
    if np.any(norms <= 0):
        raise ValueError("the camera must not lie on a point")
    radius = norms.max() * 10.0**HPR_LOG_RADIUS
    flipped = relative + 2.0 * (radius - norms) * relative / norms
    hull = ConvexHull(np.vstack([flipped, np.zeros((1, 3))]))
    seen = np.zeros(len(relative), dtype=bool)
    seen[hull.vertices[hull.vertices < len(relative)]] = True
    return seen


def random_camera(points: np.ndarray, distance: float, rng: np.random.Generator) -> np.ndarray:
    """A camera position ``distance`` radii from the centroid, in a uniformly random direction."""
    centroid = points.mean(axis=0)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    return centroid + direction * distance * np.linalg.norm(points - centroid, axis=1).max()
