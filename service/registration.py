"""Step 4b: rigid poses from paired points.

Every pose here answers ``scene = R @ model + t`` for pairs ``(model[i], scene[i])``.
"""

from __future__ import annotations

import numpy as np


def kabsch(model: np.ndarray, scene: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotation and translation with centring and a determinant check."""
    rotations, translations = kabsch_batch(model[None], scene[None])
    return rotations[0], translations[0]


def kabsch_batch(model: np.ndarray, scene: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kabsch for a batch: (B, k, 3) pairs to (B, 3, 3) rotations and (B, 3) translations."""
    model_centroid = model.mean(axis=1)
    scene_centroid = scene.mean(axis=1)
    covariance = np.einsum(
        "bki,bkj->bij", scene - scene_centroid[:, None], model - model_centroid[:, None]
    )
    u, _, vt = np.linalg.svd(covariance)
    d = np.sign(np.linalg.det(u @ vt))
    d[d == 0] = 1.0
    u[:, :, 2] *= d[:, None]  # reflect the weakest axis when the best fit is a mirror
    rotations = u @ vt
    translations = scene_centroid - np.einsum("bij,bj->bi", rotations, model_centroid)
    return rotations, translations


def paper_least_squares(model: np.ndarray, scene: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The paper's solver, eqs. (5)-(6), with the translation it omits.

    With points as rows, ``S_scene ~= S_model @ A``; eq. (5) solves A by least squares
    (``(S_m^T S_m)^-1 S_m^T S_s``) and eq. (6) projects it onto the nearest orthogonal
    matrix ``U V^T``. Rows-as-points means ``A = R^T``. The clouds are centred first
    (the paper's clouds are centred by construction) and a reflection is turned into
    the nearest rotation.
    """
    model_centroid, scene_centroid = model.mean(axis=0), scene.mean(axis=0)
    a, *_ = np.linalg.lstsq(model - model_centroid, scene - scene_centroid, rcond=None)
    u, _, vt = np.linalg.svd(a)
    if np.linalg.det(u @ vt) < 0:
        u[:, 2] *= -1
    rotation = (u @ vt).T
    return rotation, scene_centroid - rotation @ model_centroid


def ransac(
    model: np.ndarray,
    scene: np.ndarray,
    threshold: float,
    iterations: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust Kabsch over putative pairs: the minimal 3-pair sample with most inliers wins.

    All samples are solved and scored at once; the winner is re-fitted on its inliers.
    Returns the rotation, the translation and the inlier mask.
    """
    count = len(model)
    samples = rng.integers(0, count, size=(iterations, 3))
    rotations, translations = kabsch_batch(model[samples], scene[samples])
    predicted = np.einsum("bij,nj->bni", rotations, model) + translations[:, None, :]
    inliers = ((predicted - scene[None]) ** 2).sum(axis=2) < threshold**2  # (B, N)
    best = int(inliers.sum(axis=1).argmax())
    mask = inliers[best]
    if mask.sum() >= 3:
        rotation, translation = kabsch(model[mask], scene[mask])
        mask = ((model @ rotation.T + translation - scene) ** 2).sum(axis=1) < threshold**2
        return rotation, translation, mask
    return rotations[best], translations[best], mask
