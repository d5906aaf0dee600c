"""Step 5, hypothesise: pair observed and reference points that land on the same 2-D coordinate.

The mapping is meant to send a surface point to the same 2-D coordinate in any
pose, so each observed point's nearest reference point in mapped space is its
putative correspondence (the paper's pairing, Fig. 1). A tree over the
reference's mapped coordinates is built once per reference.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def mapped_pairs(observed_mapped: np.ndarray, reference_tree: cKDTree) -> np.ndarray:
    """Index of the reference point nearest to each observed point in mapped 2-D space."""
    _, nearest = reference_tree.query(observed_mapped, k=1)
    return nearest


def correspondence_quality(
    observed_in_model_frame: np.ndarray,
    reference_points: np.ndarray,
    paired: np.ndarray,
    scale: float,
    tolerance: float = 0.05,
) -> float:
    """Share of pairs whose reference point lies within ``tolerance * scale`` of the true one.

    ``observed_in_model_frame`` are the observed points carried back by the true pose,
    so a perfect mapping pairs each with a reference point at the same place.
    """
    distance = np.linalg.norm(reference_points[paired] - observed_in_model_frame, axis=1)
    return float((distance < tolerance * scale).mean())
