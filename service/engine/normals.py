"""Surface normals of a reference: from the mesh when one was uploaded, else estimated.

Point-to-plane refinement and the visibility checks need a normal at every reference point:
- a mesh gives each sampled point the normal of the triangle it lies on;
- a cloud gets the normal of the plane fitted to its nearest neighbours (the eigenvector of
  their covariance with the smallest eigenvalue).
Either is then oriented outward by the cameras that see the point: a surface faces the camera
it is seen from, so each normal is flipped to agree with the directions of the views that see
its point (``service.engine.views``); a point no view sees takes the orientation of its nearest
seen neighbour.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

NEIGHBOURS = 16  # points in the plane fitted for an estimated normal


def estimate_normals(
    points: np.ndarray, neighbours: int = NEIGHBOURS, tree: cKDTree | None = None
) -> np.ndarray:
    """(N, 3) unit normals of a cloud, up to sign: the local plane of each point's neighbours."""
    points = np.asarray(points, dtype=np.float64)
    k = min(neighbours, len(points))
    _, index = (tree or cKDTree(points)).query(points, k=k)
    local = points[index] - points[index].mean(axis=1, keepdims=True)  # (N, k, 3)
    covariance = local.transpose(0, 2, 1) @ local
    _, vectors = np.linalg.eigh(covariance)  # ascending eigenvalues
    return vectors[:, :, 0]


def orient_by_views(
    points: np.ndarray, normals: np.ndarray, directions: np.ndarray, visible: np.ndarray
) -> np.ndarray:
    """Normals flipped to face the views that see their points.

    ``directions`` (K, 3) point from the object towards each view's camera; ``visible`` (K, N)
    says which points each view sees.
    """
    normals = np.asarray(normals, dtype=np.float64)
    # per point: the sum over the views that see it of n . d (its sign is the orientation)
    votes = np.einsum("kn,kn->n", visible.astype(np.float64), directions @ normals.T)
    oriented = normals * np.where(votes < 0, -1.0, 1.0)[:, None]
    unseen = ~visible.any(axis=0)
    if unseen.any() and (~unseen).any():
        seen_index = np.flatnonzero(~unseen)
        _, nearest = cKDTree(points[seen_index]).query(points[unseen], k=1)
        neighbour = oriented[seen_index[nearest]]
        flip = np.einsum("ij,ij->i", oriented[unseen], neighbour) < 0
        oriented[np.flatnonzero(unseen)[flip]] *= -1
    return oriented
