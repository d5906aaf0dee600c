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


def turned_about(
    rotation: np.ndarray, translation: np.ndarray, turns: np.ndarray, centre: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The pose ``scene = R m + t`` with the part first turned by each of ``turns`` (K, 3, 3)
    about ``centre`` (model frame): ``scene = R (T (m - c) + c) + t``. (K, 3, 3), (K, 3)."""
    rotations = np.einsum("ij,njk->nik", rotation, turns)
    return rotations, translation + (centre - turns @ centre) @ rotation.T


def alignment_error(
    scene: np.ndarray, reference_tree: cKDTree, rotation: np.ndarray, translation: np.ndarray
) -> float:
    """Mean distance from each scene point to the nearest reference point at the pose."""
    distance, _ = reference_tree.query(to_model_frame(scene, rotation, translation), k=1)
    return float(distance.mean())


def orthonormal(rotation: np.ndarray) -> np.ndarray:
    """The rotation nearest ``rotation`` (SVD): what an answer carries. Poses composed in
    float32 (a rendered view's frame) and refined step by step drift from orthonormal by a
    few 1e-7, which a client that checks R R^T = I to 1e-6 sees."""
    u, _, vt = np.linalg.svd(np.asarray(rotation, dtype=np.float64))
    if np.linalg.det(u @ vt) < 0:
        u[:, -1] = -u[:, -1]
    return u @ vt
