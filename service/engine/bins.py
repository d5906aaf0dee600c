"""A bin around its floor: the band its walls and rims stand in, set aside with the floor.

A bin's floor is found as a support (level on the table, just above it), but its walls hold
too few points each to be found as planes, and its rims (the walls' tops, level with the
table at the walls' height) look like parts' top faces. Both lie where no part in the bin
can: over the floor's outline. The floor's outline is the smallest rectangle round its points
(the floor is seen between the parts on it, out to the walls' feet); the band runs from just
inside it to ``BAND_OUTSIDE`` of the floor's reach outside it, from the table up. A part lying in
the bin lies inside the outline (docs/decisions.md#a-bins-walls-and-rims).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import QhullError

from service.engine.normalize import subsample
from service.engine.tuning import BAND_INSIDE, BAND_OUTSIDE, BAND_SIDE, BAND_STANDING, BAND_TRIM


@dataclass(frozen=True)
class Band:
    """The band a bin's walls and rims stand in, round its floor's outline."""

    plane: np.ndarray  # (4,) the floor's plane, the normal towards the camera
    axes: np.ndarray  # (3, 2) the outline's two axes, in the floor's plane
    centre: np.ndarray  # (2,) the outline's centre along them
    half: np.ndarray  # (2,) its half sides
    inside: float  # the band starts this far inside the outline ...
    outside: float  # ... and ends this far outside it
    below: float  # points lower than this under the floor's plane are not the bin's

    def holds(self, points: np.ndarray) -> np.ndarray:
        """(N,) which of ``points`` lie in the band."""
        along = points @ self.axes
        within = points @ self.plane[:3] - self.plane[3] > self.below
        deep_inside = np.ones(len(points), dtype=bool)
        for k in range(2):  # column by column: all() along rows of two is numpy's slow path
            across = np.abs(along[:, k] - self.centre[k])
            within &= across <= self.half[k] + self.outside
            deep_inside &= across < self.half[k] - self.inside
        return within & ~deep_inside


def outline(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The smallest rectangle round 2-D points (trimesh's), trimmed to the ``BAND_TRIM`` and
    1 - ``BAND_TRIM`` quantiles along its sides: (its two unit axes as the columns of a (2, 2)
    matrix, its centre and its half sides along them). Points on a line: ``QhullError``."""
    transform, _ = trimesh.bounds.oriented_bounds_2D(flat)
    frame = transform[:2, :2].T
    low, high = np.quantile(flat @ frame, [BAND_TRIM, 1 - BAND_TRIM], axis=0)
    return frame, (low + high) / 2, (high - low) / 2


def bin_band(
    floor: np.ndarray,
    plane: np.ndarray,
    axes: np.ndarray,
    points: np.ndarray,
    left: np.ndarray,
    cell: float,
    reach: float,
    tolerance: float,
    rng: np.random.Generator,
) -> tuple[Band, np.ndarray] | None:
    """The band of the bin whose floor's points are ``floor`` (on ``plane``), and which of
    ``points`` it holds, if those still ``left`` (a mask) stand in it as walls do: higher over
    the floor than its slab, along at least three sides of its outline (``BAND_SIDE`` of the
    floor's points each); None for a floor with nothing standing round it (a mat, a tray's
    flat bottom) or a part beside it. ``axes``: two unit vectors spanning the plane."""
    flat = floor[subsample(floor, 4096, rng)] @ axes
    if len(flat) < 16:
        return None
    try:
        frame, centre, half = outline(flat)
    except QhullError:  # the floor's points on a line: no outline
        return None
    band = Band(
        plane, axes @ frame, centre, half, BAND_INSIDE * cell, BAND_OUTSIDE * reach, -tolerance
    )
    held = band.holds(points)
    standing = points[held & left]
    standing = standing[standing @ plane[:3] - plane[3] > BAND_STANDING * reach]
    # by the side of the outline each stands at: walls round the floor, not a part beside it
    along = standing @ band.axes - band.centre
    axis = np.argmax(np.abs(along) - band.half, axis=1)
    side = 2 * axis + (along[np.arange(len(along)), axis] > 0)
    sides = np.bincount(side, minlength=4) >= BAND_SIDE * len(floor)
    return (band, held) if sides.sum() >= 3 else None
