"""Step 7, refine: a pose refined with robust point-to-plane ICP on the reference's distance field.

Each iteration carries the observed points into the model frame, looks up the nearest reference
point and its normal in the distance field (O(1), no tree), and solves the linearised
point-to-plane problem: the small rotation ``w`` and translation ``d`` that minimise
``sum_i rho(n_i . (m_i + w x m_i + d - q_i))``. The robust kernel rho is Tukey's biweight with a
scale taken from the residuals' median absolute deviation (floored by ``noise``), so points that
the reference does not explain (clutter, another part, the wrong side) weigh nothing; pairs
farther than ``gate`` from their nearest point are left out at once. Iteratively reweighted
least squares; a little damping keeps the 6x6 system solvable on planes and cylinders, whose
sliding directions the data do not fix. Stops when the update turns by less than
``tolerance_rad`` and moves by less than ``tolerance`` times ``noise``.

Told where the camera was (``viewpoint``), the pairs of the last, precise iterations leave out
reference samples that face away from it: a depth camera sees no surface that turns its back
to it, but across a thin wall the nearest sample is as often the far side's
(docs/decisions.md#refine).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from service.engine.alignment import to_model_frame
from service.engine.distance_field import DistanceField
from service.engine.tuning import BACK_FACING, BEHIND, CLOSE, CLOSE_RAD, SURFACE_NEIGHBOURS

TUKEY = 4.685  # Tukey's constant: 95 % efficiency on Gaussian residuals
DAMPING = 1e-6  # relative to the system's trace


@dataclass(frozen=True)
class Surface:
    """A reference's surface as refinement and verification see it."""

    points: np.ndarray  # (N, 3) float64, model frame
    normals: np.ndarray  # (N, 3) unit, outward
    field: DistanceField
    neighbours: np.ndarray  # (N, k) each point's nearest others (itself first)
    spacing: float  # the median distance from a sample to its nearest other

    @classmethod
    def of(
        cls, points: np.ndarray, normals: np.ndarray, field: DistanceField, tree: cKDTree
    ) -> Surface:
        # a cloud of fewer points than SURFACE_NEIGHBOURS has that many neighbours a point (the tree
        # would name a missing one by an index past the end)
        count = min(SURFACE_NEIGHBOURS, len(points))
        distances, neighbours = tree.query(points, k=list(range(1, count + 1)))
        spacing = float(np.median(distances[:, 1]))
        return cls(points, normals, field, neighbours.astype(np.intp), spacing)

    def nearest(
        self, points: np.ndarray, facing: bool = False, camera: np.ndarray | None = None
    ) -> np.ndarray:
        """Index of the surface sample nearest each of ``points`` (..., 3): the distance
        field's answer, corrected among that sample's neighbours. The field names the sample
        nearest the voxel's centre, which may be a voxel away from the point's own nearest;
        that one is almost always among its neighbours.

        With ``facing``, the nearest of those the point lies in front of (not more than
        ``BEHIND`` spacings behind its tangent plane; the nearest where it is behind them
        all). A point is seen on the outside of its surface; across a thin wall (a hollow
        brick's, a cup's) the nearest sample is often on the far side, a wall's thickness
        from the point's own plane, with the point behind it. Measured at the true pose, 7-8 %
        of a hollow brick's full-cloud points lay beyond the tolerance from their nearest
        sample's tangent patch, 4-5 % from the facing one's.

        With ``camera`` (a point in the model frame), the nearest of those that do not face
        away from it (``BACK_FACING``; the nearest where they all do)."""
        candidates = self.neighbours[self.field.lookup(points)]  # (..., k)
        offsets = points[..., None, :] - self.points[candidates]
        square = np.einsum("...ki,...ki->...k", offsets, offsets)
        if facing:
            along = np.einsum("...ki,...ki->...k", offsets, self.normals[candidates])
            behind = along < -BEHIND * self.spacing
            square[behind & ~behind.all(axis=-1, keepdims=True)] = np.inf
        if camera is not None:
            sight = camera - self.points[candidates]
            toward = np.einsum("...ki,...ki->...k", sight, self.normals[candidates])
            away = toward < -BACK_FACING * np.linalg.norm(sight, axis=-1)
            square[away & ~away.all(axis=-1, keepdims=True)] = np.inf
        best = np.argmin(square, axis=-1)
        return np.take_along_axis(candidates, best[..., None], axis=-1)[..., 0]


def rotation_vector(w: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by ``|w|`` about ``w``."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = w / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def icp(
    scene: np.ndarray,
    surface: Surface,
    rotation: np.ndarray,
    translation: np.ndarray,
    noise: float,
    gate: float,
    iterations: int = 20,
    tolerance_rad: float = 5e-4,
    tolerance: float = 0.05,
    viewpoint: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The pose ``scene = R @ model + t`` refined from the given one, and the iterations run.

    ``noise`` is the smallest residual scale the kernel assumes (the sensor's noise), ``gate``
    the largest point-to-point distance of a pair that is used at all, ``viewpoint`` where the
    camera was (scene frame), if known.
    """
    rotation, translation = np.asarray(rotation, np.float64), np.asarray(translation, np.float64)
    done, precise = 0, False
    for iteration in range(1, iterations + 1):
        done = iteration
        model = to_model_frame(scene, rotation, translation)
        # the distance field's own answer while far; corrected among neighbours once close
        if precise:
            camera = None if viewpoint is None else (viewpoint - translation) @ rotation
            nearest = surface.nearest(model, camera=camera)
        else:
            nearest = surface.field.lookup(model)
        offset = model - surface.points[nearest]
        normals = surface.normals[nearest]
        near = np.einsum("ij,ij->i", offset, offset) < gate**2
        if near.sum() < 6:
            break
        model, offset, normals = model[near], offset[near], normals[near]
        residual = np.einsum("ij,ij->i", offset, normals)
        spread = max(1.4826 * _median(np.abs(residual)), noise)
        u = residual / (TUKEY * spread)
        weight = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
        jacobian = _jacobian(model, normals)  # (M, 6)
        weighted = jacobian * weight[:, None]
        system = weighted.T @ jacobian
        system[np.diag_indices(6)] += DAMPING * np.trace(system) + 1e-12
        step = -np.linalg.solve(system, weighted.T @ residual)
        correction = rotation_vector(step[:3])  # model points m -> C m + d
        rotation = rotation @ correction.T
        translation = translation - rotation @ step[3:]
        turned, moved = np.linalg.norm(step[:3]), np.linalg.norm(step[3:])
        if turned < CLOSE_RAD and moved < CLOSE * noise:
            if precise and turned < tolerance_rad and moved < tolerance * noise:
                break
            precise = True
    return rotation, translation, done


def _jacobian(model: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(M, 6): each pair's [m x n, n], the derivative of its point-to-plane residual by the
    small rotation and the translation (written out: np.cross costs more than the loop's
    arithmetic on a few hundred points)."""
    jacobian = np.empty((len(model), 6))
    mx, my, mz = model.T
    nx, ny, nz = normals.T
    jacobian[:, 0] = my * nz - mz * ny
    jacobian[:, 1] = mz * nx - mx * nz
    jacobian[:, 2] = mx * ny - my * nx
    jacobian[:, 3:] = normals
    return jacobian


def _median(values: np.ndarray) -> float:
    """The median of a 1-D array (np.median's checks cost more than the partition)."""
    half = len(values) // 2
    part = np.partition(values, [half - 1, half] if len(values) % 2 == 0 else half)
    return float(part[half] if len(values) % 2 else 0.5 * (part[half - 1] + part[half]))
