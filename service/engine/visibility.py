"""Which points of a cloud a single depth camera would see.

Hidden-point removal (Katz, Tal and Basri, SIGGRAPH 2007): flip every point about a
large sphere centred on the camera (p -> p + 2 (R - |p|) p / |p|); the points that
land on the convex hull of the flipped cloud and the camera are the visible ones.
Used to make partial views: the evaluation's "partial" family and the classifier's
augmented views, so that a half-seen part is still recognised.

``hidden_share`` asks the other way whether a cloud is one camera's view: a view hides almost
none of its own points from its camera, while a whole part's cloud hides about a fifth of them
from every side (docs/decisions.md#a-whole-parts-cloud).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from service.engine.normalize import radius
from service.engine.supports import in_plane
from service.engine.tuning import HIDDEN_CELL, HIDDEN_DEPTH, HIDDEN_POINTS, HPR_LOG_RADIUS

# the 13 axes of a cube (its faces', edges' and corners' directions), each looked along both ways
_AXES = np.array(
    [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, -1, 0], [1, 0, 1], [1, 0, -1], [0, 1, 1]]
    + [[0, 1, -1], [1, 1, 1], [1, 1, -1], [1, -1, 1], [-1, 1, 1]],
    dtype=np.float64,
)
AXES = _AXES / np.linalg.norm(_AXES, axis=1, keepdims=True)
# each axis's image plane: two unit vectors across it
ACROSS, UP = np.stack([in_plane(axis) for axis in AXES]).transpose(2, 0, 1)


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


def hidden_share(points: np.ndarray, rng: np.random.Generator) -> float:
    """The least share of ``points`` that lie behind others, looked at along any of 26
    directions (a cube's axes both ways; parallel projection): of ``HIDDEN_POINTS`` of them, a
    point is hidden where another in its cell of the image (``HIDDEN_CELL`` point spacings
    wide) lies ``HIDDEN_DEPTH`` spacings or more nearer. On the evaluation's cases, a camera's
    view of a part 0-0.15 (a cavity's floor by its rim, steep faces by the outline share a
    cell with nearer points); a whole part's cloud 0.12 at the 5th percentile, 0.21 median,
    low where the part is thin (docs/decisions.md#a-whole-parts-cloud)."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) > HIDDEN_POINTS:
        points = points[rng.choice(len(points), HIDDEN_POINTS, replace=False)]
    if len(points) < 8:
        return 0.0
    points = points - points.mean(axis=0)
    distances, _ = cKDTree(points).query(points, k=2)
    spacing = float(np.median(distances[:, 1]))
    reach = radius(points, np.zeros(3))
    if spacing <= 0 or reach <= 0:
        return 0.0
    cell = HIDDEN_CELL * spacing
    side = int(np.ceil(2 * reach / cell)) + 1
    across = ((points @ ACROSS.T + reach) / cell).astype(np.intp)  # (N, 13)
    up = ((points @ UP.T + reach) / cell).astype(np.intp)
    depth = points @ AXES.T
    cells = np.arange(len(AXES)) * side * side + across * side + up
    nearest = np.full(len(AXES) * side * side, -np.inf)  # looked at from +axis
    farthest = np.full(len(AXES) * side * side, np.inf)  # ... from -axis
    np.maximum.at(nearest, cells.ravel(), depth.ravel())
    np.minimum.at(farthest, cells.ravel(), depth.ravel())
    gap = HIDDEN_DEPTH * spacing
    from_front = (depth < nearest[cells] - gap).mean(axis=0)
    from_back = (depth > farthest[cells] + gap).mean(axis=0)
    return float(min(from_front.min(), from_back.min()))
