"""A camera's whole frame as ``Engine.detect`` sees it: the valid points, where each came from
in the request, the pixel grid when the frame is organized, and where the camera was.

An organized frame (a depth image, a PCD or NPY of height > 1) keeps its grid: a point's
``index`` is its pixel, ``row * width + col``, and its neighbours in the image are its
neighbours on the surface unless the depth jumps. A frame far denser than the decisions need
is thinned at once (``thinned``): every k-th row and column of an organized frame, one point a
voxel of any other, so that a camera's resolution costs little.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from service.engine.normalize import distances, lengths, subsample
from service.engine.tuning import PIXEL_PAIRS


@dataclass(frozen=True)
class Frame:
    points: np.ndarray  # (N, 3) float64, every one finite
    index: np.ndarray  # (N,) int64: each point's index in the request (its pixel if organized)
    shape: tuple[int, int] | None  # (height, width) of an organized frame's grid
    viewpoint: np.ndarray  # (3,) where the camera was, in the frame's coordinates
    step: int = 1  # the grid's stride once thinned: every step-th row and column kept

    @classmethod
    def of(
        cls,
        points: np.ndarray,
        index: np.ndarray | None = None,
        shape: tuple[int, int] | None = None,
        viewpoint: np.ndarray | None = None,
    ) -> Frame:
        points = np.asarray(points, dtype=np.float64)
        index = np.arange(len(points)) if index is None else np.asarray(index, np.int64)
        origin = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, np.float64)
        return cls(points, index, shape, origin)

    def __len__(self) -> int:
        return len(self.points)

    def take(self, keep: np.ndarray) -> Frame:
        """The frame's points where ``keep`` (a mask or indices), with their grid."""
        return Frame(self.points[keep], self.index[keep], self.shape, self.viewpoint, self.step)

    @property
    def rows(self) -> np.ndarray:
        return self.index // self.shape[1]

    @property
    def columns(self) -> np.ndarray:
        return self.index % self.shape[1]

    @property
    def grid_shape(self) -> tuple[int, int]:
        """(rows, columns) of an organized frame's own grid: every ``step``-th of the full one."""
        height, width = self.shape
        return (height + self.step - 1) // self.step, (width + self.step - 1) // self.step

    def cells(self, pick: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The row and column of each point (of those ``pick`` names) on the frame's own grid,
        from one division of their pixels."""
        rows, columns = np.divmod(self.index if pick is None else self.index[pick], self.shape[1])
        if self.step > 1:
            rows //= self.step
            columns //= self.step
        return rows, columns

    def cropped(self, low: np.ndarray, high: np.ndarray) -> Frame:
        """Only the points inside the box ``low``-``high`` (the request's ``roi``)."""
        inside = np.all((self.points >= low) & (self.points <= high), axis=1)
        return self.take(inside)

    def pixel_angle(self) -> float:
        """The angle between neighbouring pixels' rays (radians) of the full-resolution grid,
        from its own horizontal neighbours; for a cloud without a grid, from its spacing.
        Computed once a frame."""
        return self._pixel_angle

    @cached_property
    def _pixel_angle(self) -> float:
        if self.shape is None or len(self) < 2:
            return spacing_angle(self.points, self.viewpoint)
        index, points = self.index, self.points
        if np.any(index[1:] < index[:-1]):  # a frame's points come in pixel order: no sort
            order = np.argsort(index)
            index, points = index[order], points[order]
        # every k-th point with the next, some PIXEL_PAIRS pairs spread over the grid: all
        # pairs' median to 0.1 %, 5 ms where all took 27-170 ms on 1280 x 720
        # (docs/decisions.md#a-frames-body)
        first = np.arange(0, len(index) - 1, max(1, (len(index) - 1) // PIXEL_PAIRS))
        first = first[np.take(index, first + 1) - np.take(index, first) == self.step]
        if len(first) < 16:
            return spacing_angle(self.points, self.viewpoint)
        ends = []
        for chosen in (first, first + 1):
            rays = np.take(points, chosen, axis=0) - self.viewpoint
            rays /= lengths(rays)[:, None]  # each ray's length: its range
            ends.append(rays)
        cosine = np.einsum("ij,ij->i", *ends)
        return float(np.median(np.arccos(np.clip(cosine, -1.0, 1.0)))) / self.step

    def thinned(self, voxel: float) -> Frame:
        """At most about one point per ``voxel``: every k-th row and column of an organized
        frame (k from its pixels' footprint at the median range), one point a voxel of a
        cloud without a grid. Never denser than it was."""
        if len(self) == 0 or voxel <= 0:
            return self
        if self.shape is not None:
            footprint = self.pixel_angle() * float(np.median(self.ranges()))
            return self.every(int(voxel // max(footprint, 1e-12)))
        cells = np.floor(self.points / voxel).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        return self.take(np.sort(first))

    def every(self, step: int) -> Frame:
        """Every ``step``-th row and column of an organized frame's grid (itself for 1)."""
        if step <= 1:
            return self
        stride = self.step * step
        grid = np.zeros(self.shape, dtype=bool)  # the kept pixels, looked up: no // or % a point
        grid[::stride, ::stride] = True
        thin = self.take(np.take(grid.ravel(), self.index))
        return Frame(thin.points, thin.index, self.shape, self.viewpoint, stride)

    def at_most(self, count: int, rng: np.random.Generator) -> Frame:
        """A coarser copy of about ``count`` points at most: every k-th row and column of an
        organized frame, a random sample of a cloud without a grid."""
        if len(self) <= count:
            return self
        if self.shape is None:
            return self.take(subsample(self.points, count, rng))
        return self.every(int(np.ceil(np.sqrt(len(self) / count))))

    def ranges(self) -> np.ndarray:
        """(N,) each point's distance from the camera (read-only: computed once a frame, for
        the supports, the segments and the scene alike)."""
        return self._ranges

    @cached_property
    def _ranges(self) -> np.ndarray:
        ranges = distances(self.points, self.viewpoint)
        ranges.flags.writeable = False
        return ranges


def spacing_angle(points: np.ndarray, viewpoint: np.ndarray, sample: int = 512) -> float:
    """The median angle, seen from ``viewpoint``, between a point and its nearest neighbour."""
    if len(points) < 2:
        return 1e-3
    rng = np.random.default_rng(0)
    chosen = points[rng.choice(len(points), size=min(sample, len(points)), replace=False)]
    distance, _ = cKDTree(points).query(chosen, k=2)
    ranges = np.linalg.norm(chosen - viewpoint, axis=1)
    return float(np.median(distance[:, 1] / np.maximum(ranges, 1e-12)))
