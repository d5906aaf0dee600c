"""The paper's measure of fit (Sect. 4.2): how far the observation lies from the reference.

The mean distance from each observed point to the nearest reference point with the
reference placed at the pose. Carrying the observation back into the model frame
by the inverse pose gives the same distances, so one tree per reference serves
every pose.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def to_model_frame(scene: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Scene points carried back by the inverse of ``scene = R @ model + t``."""
    return (scene - translation) @ rotation


def alignment_error(
    scene: np.ndarray, reference_tree: cKDTree, rotation: np.ndarray, translation: np.ndarray
) -> float:
    """Mean distance from each scene point to the nearest reference point at the pose."""
    distance, _ = reference_tree.query(to_model_frame(scene, rotation, translation), k=1)
    return float(distance.mean())
