"""Step 5b: refine a pose with point-to-point ICP against the reference's tree.

Each iteration pairs every observed point with its nearest reference point at
the current pose, drops pairs farther than ``trim`` times the median distance
(so parts of the scene the reference does not explain pull less), and solves
Kabsch on the rest. Stops when the mean distance improves by less than
``tolerance`` (relative) from one iteration to the next.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from service.engine.alignment import to_model_frame
from service.engine.registration import kabsch


def icp(
    scene: np.ndarray,
    reference_points: np.ndarray,
    reference_tree: cKDTree,
    rotation: np.ndarray,
    translation: np.ndarray,
    iterations: int = 10,
    trim: float = 3.0,
    tolerance: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray]:
    """The pose ``scene = R @ model + t`` refined from the given one."""
    previous = np.inf
    for _ in range(iterations):
        distance, nearest = reference_tree.query(to_model_frame(scene, rotation, translation), k=1)
        mean = float(distance.mean())
        if mean > previous * (1 - tolerance):
            break
        previous = mean
        keep = distance <= trim * max(float(np.median(distance)), 1e-12)
        if keep.sum() < 3:
            break
        rotation, translation = kabsch(reference_points[nearest[keep]], scene[keep])
    return rotation, translation
