"""Step 5, hypothesise: rigid poses from paired points.

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
    # matmul, not einsum: einsum takes a slow unblocked path for these shapes
    covariance = (scene - scene_centroid[:, None]).transpose(0, 2, 1) @ (
        model - model_centroid[:, None]
    )
    u, _, vt = np.linalg.svd(covariance)
    d = np.sign(det3(u @ vt))
    d[d == 0] = 1.0
    u[:, :, 2] *= d[:, None]  # reflect the weakest axis when the best fit is a mirror
    rotations = u @ vt
    translations = scene_centroid - (rotations @ model_centroid[:, :, None])[:, :, 0]
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
    score_pairs: int = 256,
    confidence: float = 0.99,
    chunk: int = 50,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust Kabsch over putative pairs: the minimal 3-pair sample with most inliers wins.

    Samples are solved ``chunk`` at a time and scored on ``score_pairs`` random pairs; it stops
    after ``iterations`` samples, or earlier once the best inlier share ``w`` so far says that
    ``log(1 - confidence) / log(1 - w^3)`` samples would have drawn an all-inlier one (the
    adaptive termination of Hartley and Zisserman, Alg. 4.5), and after the first chunk when no
    scored pair agrees with any of its samples. The winner is re-fitted on its inliers among all
    pairs. Returns the rotation, the translation and the inlier mask.
    """
    count = len(model)
    scored = rng.choice(count, size=min(count, score_pairs), replace=False)
    best, best_inliers, drawn = (np.eye(3), np.zeros(3)), -1, 0
    while drawn < iterations:
        size = min(chunk, iterations - drawn)
        samples = rng.integers(0, count, size=(size, 3))
        rotations, translations = kabsch_batch(model[samples], scene[samples])
        residuals = squared_residuals(model[scored], scene[scored], rotations, translations)
        inliers = (residuals < threshold**2).sum(axis=0)
        drawn += size
        top = int(inliers.argmax())
        if inliers[top] > best_inliers:
            best, best_inliers = (rotations[top], translations[top]), int(inliers[top])
        share = best_inliers / len(scored)
        if share == 0:  # not one scored pair agrees with any sample: nothing to find
            break
        if share >= 1 or drawn >= np.log(1 - confidence) / np.log1p(-(min(share, 0.999) ** 3)):
            break
    rotation, translation = best
    mask = ((model @ rotation.T + translation - scene) ** 2).sum(axis=1) < threshold**2
    if mask.sum() >= 3:
        rotation, translation = kabsch(model[mask], scene[mask])
        mask = ((model @ rotation.T + translation - scene) ** 2).sum(axis=1) < threshold**2
    return rotation, translation, mask


def squared_residuals(
    model: np.ndarray, scene: np.ndarray, rotations: np.ndarray, translations: np.ndarray
) -> np.ndarray:
    """(N, B) ``|R_b m_n + t_b - s_n|^2`` for every pair n and pose b, as one matrix product.

    Expanded, the square is ``|m|^2 + |s|^2 + |t|^2 - 2 s.t + 2 m.(R^T t) - 2 s^T R m``,
    and ``s^T R m`` is the dot product of ``vec(s m^T)`` with ``vec(R)``; so no (N, B, 3)
    array is ever built (numpy's batched 3x3 products are slow and memory-bound).
    """
    outer = (scene[:, :, None] * model[:, None, :]).reshape(len(model), 9)
    features = np.hstack([outer, model, scene])  # (N, 15)
    rotated_t = np.einsum("bij,bi->bj", rotations, translations)  # R^T t, (B, 3)
    weights = np.hstack([-2 * rotations.reshape(-1, 9), 2 * rotated_t, -2 * translations])
    constant = (model**2).sum(axis=1) + (scene**2).sum(axis=1)
    return features @ weights.T + constant[:, None] + (translations**2).sum(axis=1)[None]


def det3(matrices: np.ndarray) -> np.ndarray:
    """Determinants of a stack of 3x3 matrices, in closed form."""
    m = matrices
    return (
        m[:, 0, 0] * (m[:, 1, 1] * m[:, 2, 2] - m[:, 1, 2] * m[:, 2, 1])
        - m[:, 0, 1] * (m[:, 1, 0] * m[:, 2, 2] - m[:, 1, 2] * m[:, 2, 0])
        + m[:, 0, 2] * (m[:, 1, 0] * m[:, 2, 1] - m[:, 1, 1] * m[:, 2, 0])
    )
