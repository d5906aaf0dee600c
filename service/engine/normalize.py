"""Step 1, normalise: put a cloud in the frame the network was trained in.

The network sees points centred on their centroid and divided by the radius
(the largest distance from the centroid to a point, the contract's *scale*),
so the same object gives the same input at any position and size. Optionally
the cloud is also rotated into its principal-axes frame (``canonical=True``),
which removes most of the pose before the network sees it; the paper's
network sees the centred and scaled cloud only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.engine import kernels
from service.engine.principal_axes import principal_frame


@dataclass(frozen=True)
class Normalized:
    points: np.ndarray  # (N, 3) float32: the network's input, ((p - centroid) @ frame) / scale
    centroid: np.ndarray  # (3,)
    scale: float
    frame: np.ndarray  # (3, 3) rotation, columns are the axes the input is expressed in


def radius(points: np.ndarray, centroid: np.ndarray | None = None) -> float:
    """The scale of a cloud: the largest distance from its centroid to one of its points."""
    centre = points.mean(axis=0) if centroid is None else centroid
    # the largest square's root: the same float (sqrt is monotone), without an (N, 3) copy
    return float(np.sqrt(squared_distances(points, centre).max()))


def lengths(vectors: np.ndarray) -> np.ndarray:
    """(...) the length of each row of ``vectors`` (..., 3): ``np.linalg.norm(vectors,
    axis=-1)`` to the bit, summed column by column, 7 times faster on a camera frame's points
    (whose reduction along a row of three is numpy's slow path;
    docs/decisions.md#a-frames-body)."""
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    return np.sqrt(x * x + y * y + z * z)


def squared_distances(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(N,) each point's squared distance from ``centre``: ``np.sum((points - centre) ** 2,
    axis=1)`` to the bit, a column at a time, without the (N, 3) difference (a third of the
    time on a 1280 x 720 frame's points); in one compiled pass where it can be
    (``kernels``)."""
    if kernels.takes(points):
        return kernels.squared_distances(points, np.ascontiguousarray(centre, np.float64))
    x = points[:, 0] - centre[0]
    y = points[:, 1] - centre[1]
    z = points[:, 2] - centre[2]
    return x * x + y * y + z * z


def distances(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(N,) each point's distance from ``centre``: ``lengths(points - centre)`` to the bit,
    without the (N, 3) difference."""
    return np.sqrt(squared_distances(points, centre))


def radius_at_least(points: np.ndarray, stride: int = 16) -> float:
    """A lower bound of ``radius``, cheap on a frame of many points: half the widest span of
    every ``stride``-th point along an axis (two points lie within twice the radius of each
    other, whatever the centre)."""
    sample = points[::stride]
    if not len(sample):
        return 0.0
    low, high = sample[sample.argmin(axis=0)], sample[sample.argmax(axis=0)]  # each axis's
    return float(lengths(high - low).max()) / 2


def radius_bounds(points: np.ndarray, stride: int = 16) -> tuple[float, float]:
    """A lower and an upper bound of ``radius`` without every point's distance: the farthest
    of every ``stride``-th point, and the farthest corner of the points' box, from the
    centroid (summed a column at a time: ``mean(axis=0)`` over rows of three is numpy's slow
    path, 13 of the 18 ms ``radius`` takes on a 1280 x 720 frame). A hair apart on a camera's
    frame, they settle which sizes it holds without the exact figure
    (docs/decisions.md#a-frames-scale-and-pixel-angle-once)."""
    columns = [points[:, axis] for axis in range(3)]
    centre = np.array([column.mean() for column in columns])
    low = float(np.sqrt(squared_distances(points[::stride], centre).max()))
    corners = np.array([[column.min(), column.max()] for column in columns])
    reach = np.maximum(centre - corners[:, 0], corners[:, 1] - centre)
    # the margins cover the rounding of a centroid summed in another order than radius's
    return low * (1 - 1e-9), float(np.sqrt(reach @ reach)) * (1 + 1e-9)


def no_larger(scales: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Which of ``scales`` are no larger than the radius of ``points``: ``scales <=
    radius(points)``, with every point's distance measured only where a scale lies between
    the radius's bounds: ``radius_at_least`` where every scale fits under it (0.25 ms on
    300,000 points), else ``radius_bounds``."""
    if not len(points):
        return scales <= 0.0
    if len(scales) and scales.max() <= radius_at_least(points):
        return np.ones(len(scales), dtype=bool)
    low, high = radius_bounds(points)
    if np.any((scales > low) & (scales <= high)):
        return scales <= radius(points)
    return scales <= low


# All points (nearly) the same: a cloud whose radius is below this share of its coordinates'
# magnitude (at least 1 unit) lies within a few float32 steps of one point
MIN_RELATIVE_RADIUS = 1e-6


def has_extent(size: float, magnitude: float) -> bool:
    """Whether a cloud of radius ``size`` whose coordinates reach ``magnitude`` spans more
    than one point (``MIN_RELATIVE_RADIUS``): one that does not has no scale to normalise by."""
    return size > MIN_RELATIVE_RADIUS * max(1.0, magnitude)


def normalize(points: np.ndarray, canonical: bool = False) -> Normalized:
    """Centre on the centroid, divide by the radius, and optionally rotate to principal axes.
    Points all at one place (a registration's augmented view may keep only those of a cloud
    that is mostly one point) are all the origin."""
    points = np.asarray(points, dtype=np.float64)
    centroid = points.mean(axis=0)
    centred = points - centroid
    scale = radius(points, centroid) or 1.0
    frame = principal_frame(centred) if canonical else np.eye(3)
    network_input = (centred @ frame) / scale
    return Normalized(network_input.astype(np.float32), centroid, scale, frame)


def subsample(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of at most ``count`` points chosen at random without replacement."""
    if len(points) <= count:
        return np.arange(len(points))
    return np.sort(rng.choice(len(points), size=count, replace=False))
