"""Step 6, verify: how well a reference at a pose explains the observation, and how much is seen.

Two shares, both in [0, 1], measured in units of the reference's own scale:
- ``fit``: of the observed points, the share that lie within ``tolerance`` of the reference's
  surface at the pose. Distances come from the distance field: to the tangent plane at the
  nearest surface sample the point lies in front of, within that sample's patch, so a point
  between samples is as near as the surface it lies on, and one on a thin wall is measured to
  its own side of it;
- ``coverage``: of the reference points the camera should see at that pose, the share that
  have an observed point within ``tolerance``. Which points are seen comes from the view the
  pose implies: with a viewpoint, the rendered view nearest to the camera's direction in the
  model frame; without one, the view the hypothesis came from; a full-cloud hypothesis
  expects every point.

Neither alone tells parts apart: a larger part swallows a smaller one's points (high fit, low
coverage), a smaller part hides inside a larger one's visible surface (high coverage, low
fit). Their product ranks hypotheses of every candidate part on one scale
(docs/decisions.md#verify).

``Occupancy`` answers "is there an observed point near here" for thousands of points at once:
the observed points' voxels and their neighbours, in a dense grid over the observation.

Where numba is installed, distances, ``fit`` and ``coverage`` run as compiled loops of the same
arithmetic (``kernels``; docs/decisions.md#compiled-loops).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from service.engine import kernels
from service.engine.icp import Surface
from service.engine.tuning import BEHIND, OCCUPANCY_SPACINGS, PATCH_SPACINGS

Lookup = Literal["facing", "nearest", "field"]  # which sample ``surface_distance`` measures to
LOOKUPS = {"field": kernels.FIELD, "nearest": kernels.NEAREST, "facing": kernels.FACING}


class Occupancy:
    """The voxels within one voxel of an observed point, for O(1) "is a point near" tests: a
    dense grid over the observation's box (the voxel is at least 4 % of its radius, so at most
    some 54^3 cells), dilated by one voxel."""

    @classmethod
    def around(cls, observed: np.ndarray, tolerance: float, spacing: float) -> Occupancy:
        """At ``tolerance``, or coarser where the observation is sparser: a voxel of at least
        ``OCCUPANCY_SPACINGS`` times the median distance between neighbouring observed points."""
        return cls(observed, max(tolerance, OCCUPANCY_SPACINGS * spacing))

    def __init__(self, points: np.ndarray, voxel: float):
        self.voxel = float(voxel)
        self.low = points.min(axis=0) - 2 * self.voxel
        cells = np.floor((points - self.low) / self.voxel).astype(np.intp)
        self.shape = cells.max(axis=0) + 3
        grid = np.zeros(self.shape, dtype=bool)
        grid[cells[:, 0], cells[:, 1], cells[:, 2]] = True
        for axis in range(3):  # a 3x3x3 box is three 3-voxel lines (ndimage's took 0.8 ms)
            grid = dilate_along(grid, axis)
        # two empty voxels on every side, one after dilating; the outermost layer is kept
        # empty (rounding may put the lowest point one voxel lower), so that a point past the
        # grid, clipped onto it, is near nothing
        grid[[0, -1]] = grid[:, [0, -1]] = grid[:, :, [0, -1]] = False
        self.grid = grid.reshape(-1)
        self.last = self.shape - 1
        self.strides = np.array([self.shape[1] * self.shape[2], self.shape[2], 1], dtype=np.intp)

    def near(self, points: np.ndarray) -> np.ndarray:
        """Whether an observed point lies within about a voxel of each of ``points`` (..., 3)."""
        cells = np.floor((points - self.low) / self.voxel).astype(np.intp)
        np.minimum(np.maximum(cells, 0, out=cells), self.last, out=cells)  # as np.clip, faster
        return self.grid.take(cells @ self.strides)


def dilate_along(grid: np.ndarray, axis: int) -> np.ndarray:
    """``grid`` with each true voxel's two neighbours along ``axis`` set too."""
    grown = grid.copy()
    ahead = [slice(None)] * 3
    behind = [slice(None)] * 3
    ahead[axis], behind[axis] = slice(1, None), slice(None, -1)
    grown[tuple(ahead)] |= grid[tuple(behind)]
    grown[tuple(behind)] |= grid[tuple(ahead)]
    return grown


def surface_distance(
    surface: Surface, model_points: np.ndarray, lookup: Lookup = "facing"
) -> tuple[np.ndarray, np.ndarray]:
    """Distance from each point (model frame, any leading shape) to the reference's surface,
    and the index of the surface sample it was measured to, by ``lookup``: ``facing``, the
    nearest sample the point lies in front of (``Surface.nearest``'s ``facing``: right across
    a thin wall); ``nearest``, the nearest sample (``Surface.nearest``); ``field``, the distance
    field's own answer (a fifth of the time, for screening). A point on the surface lies up to
    about two spacings from the nearest sample of a random sample, so within
    ``PATCH_SPACINGS`` spacings only its distance to the tangent plane counts."""
    if kernels.switch.enabled:
        flat = np.ascontiguousarray(model_points, np.float64).reshape(-1, 3)
        distance, nearest = kernels.distances(flat, LOOKUPS[lookup], *_measured(surface))
        shape = model_points.shape[:-1]
        return distance.reshape(shape), nearest.reshape(shape)
    if lookup == "field":
        nearest = surface.field.lookup(model_points)
    else:
        nearest = surface.nearest(model_points, facing=lookup == "facing")
    return patch_distance(surface, model_points, nearest), nearest


def _measured(surface: Surface) -> tuple:
    """What ``kernels`` measure a surface by: its arrays, how far behind a tangent plane a
    point may lie (``BEHIND``), how far a patch reaches (``PATCH_SPACINGS``)."""
    return surface.compiled, BEHIND * surface.spacing, PATCH_SPACINGS * surface.spacing


def patch_distance(surface: Surface, model_points: np.ndarray, nearest: np.ndarray) -> np.ndarray:
    """Distance from each point to the tangent patch of its surface sample ``nearest``: to the
    tangent plane within ``PATCH_SPACINGS`` spacings of the sample, beyond that also across."""
    patch = PATCH_SPACINGS * surface.spacing
    offset = model_points - surface.points.take(nearest, axis=0)
    along = np.einsum("...i,...i->...", offset, surface.normals.take(nearest, axis=0))
    across = np.sqrt(np.maximum(np.einsum("...i,...i->...", offset, offset) - along**2, 0.0))
    return np.sqrt(along**2 + np.maximum(across - patch, 0.0) ** 2)


def fit(
    surface: Surface,
    observed: np.ndarray,
    rotations: np.ndarray,
    translations: np.ndarray,
    tolerance: float,
    lookup: Lookup = "facing",
) -> np.ndarray:
    """(H,) share of ``observed`` (S, 3) within ``tolerance`` of the surface, for each of H poses
    ``scene = R @ model + t``."""
    if kernels.switch.enabled:  # each point carried and measured in one loop
        floats = (np.ascontiguousarray(a, np.float64) for a in (observed, rotations, translations))
        return kernels.shares(*floats, tolerance, LOOKUPS[lookup], *_measured(surface))
    model = np.matmul(observed[None] - translations[:, None], rotations)  # R^T (q - t)
    distance, _ = surface_distance(surface, model, lookup)
    return (distance < tolerance).mean(axis=1)


def coverage(
    expected: np.ndarray, rotations: np.ndarray, translations: np.ndarray, occupancy: Occupancy
) -> np.ndarray:
    """(H,) share of the expected-visible reference points ``expected`` (H, M, 3) that have an
    observed point near them at each pose."""
    if kernels.switch.enabled:
        return kernels.covered(
            np.ascontiguousarray(expected, np.float64),
            np.ascontiguousarray(rotations, np.float64),
            np.ascontiguousarray(translations, np.float64),
            np.asarray(occupancy.low, np.float64),
            occupancy.voxel,
            occupancy.last,
            occupancy.strides,
            occupancy.grid,
        )
    placed = np.matmul(expected, rotations.transpose(0, 2, 1)) + translations[:, None]
    return occupancy.near(placed).mean(axis=1)
