"""A camera's whole frame as ``Engine.detect`` sees it: the valid points, where each came from
in the request, the pixel grid when the frame is organized, and where the camera was.

An organized frame (a depth image, a PCD or NPY of height > 1) keeps its grid: a point's
``index`` is its pixel, ``row * width + col``, and its neighbours in the image are its
neighbours on the surface unless the depth jumps. A frame far denser than the decisions need
is thinned at once (``thinned``): every k-th row and column of an organized frame, one point a
voxel of any other, so that a camera's resolution costs little. A frame whose pixels are
missing in a pattern (a depth image registered to a larger colour image, an interlaced camera)
keeps a point in every block it thins to, and one with a point on one pixel in four or fewer is
thinned to its own density (docs/decisions.md#pixels-missing-in-a-pattern).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from service.engine import kernels
from service.engine.normalize import distances, lengths, subsample
from service.engine.tuning import (
    BLOCKS_HELD,
    DIRECT_PAIRS,
    PIXEL_PAIRS,
    SPARSE_GAP,
    SPARSE_SAMPLE,
    SPARSE_WINDOW,
)


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
        """The frame's points where ``keep`` (a mask or indices), with their grid. A mask is
        made indices first: np.take of rows of three is 4x faster than a mask's indexing."""
        keep = np.asarray(keep)
        if keep.dtype == bool:
            keep = np.flatnonzero(keep)
        points, index = np.take(self.points, keep, axis=0), np.take(self.index, keep)
        return Frame(points, index, self.shape, self.viewpoint, self.step)

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
        return self.take(inside_box(self.points, low, high))

    def pixel_angle(self) -> float:
        """The angle between neighbouring pixels' rays (radians) of the full-resolution grid,
        from its own horizontal neighbours (a ``patterned`` frame's: points a few pixels apart
        in a row, over their gaps); for a cloud without a grid, from its spacing. Computed once
        a frame."""
        return self._pixel_angle

    @cached_property
    def _pixel_angle(self) -> float:
        if self.shape is None or len(self) < 2:
            return spacing_angle(self.points, self.viewpoint)
        index, points = self._in_pixel_order
        apart = None
        if not self.patterned:
            first, gap = self._next_pairs
            first = first[gap == self.step]
        else:  # the next point along its row, a few pixels on, drawn at random: a pattern's
            # gaps (2, 1, 2, 1) alias with a fixed stride
            pairs = min(PIXEL_PAIRS, len(index) - 1)
            first = np.sort(np.random.default_rng(0).choice(len(index) - 1, pairs, replace=False))
            gap = np.take(index, first + 1) - np.take(index, first)
            width = self.shape[1]
            near = (gap % self.step == 0) & (gap <= SPARSE_GAP * self.step)
            near &= np.take(index, first + 1) // width == np.take(index, first) // width
            first, apart = first[near], gap[near] / self.step
        if len(first) < 16:
            return spacing_angle(self.points, self.viewpoint)
        angles = pair_angles(points, first, self.viewpoint)
        finite = np.isfinite(angles)  # a point at the camera itself has no ray
        if not finite.all():
            angles = angles[finite]
            apart = None if apart is None else apart[finite]
            if len(angles) < 16:
                return spacing_angle(self.points, self.viewpoint)
        if apart is None:
            return float(np.median(angles)) / self.step
        # a ray's angle does not depend on the depth: no outliers, and the gaps of a pattern
        # (2, 1, 2, 1 on a grid 1.5 times the camera's) average out
        return float(angles.sum() / apart.sum()) / self.step

    @cached_property
    def patterned(self) -> bool:
        """Whether the organized frame's pixels are missing in a pattern: fewer than
        ``DIRECT_PAIRS`` of a sample of its points have one on the next pixel of their row
        (a depth image registered to a larger colour image, an interlaced camera, a
        checkerboard of dropouts; docs/decisions.md#pixels-missing-in-a-pattern)."""
        if self.shape is None or len(self) < 2:
            return False
        _, gap = self._next_pairs
        return bool(np.count_nonzero(gap == self.step) < DIRECT_PAIRS * len(gap))

    @cached_property
    def _next_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Every k-th point (in pixel order) and its gap in pixels to the next, some
        PIXEL_PAIRS pairs spread over the grid: all pairs' median to 0.1 %, 5 ms where all
        took 27-170 ms on 1280 x 720 (docs/decisions.md#a-frames-body)."""
        index = self._sorted_index
        first = np.arange(0, len(index) - 1, max(1, (len(index) - 1) // PIXEL_PAIRS))
        return first, np.take(index, first + 1) - np.take(index, first)

    @cached_property
    def _in_pixel_order(self) -> tuple[np.ndarray, np.ndarray]:
        """The points' pixels and the points, in pixel order (a frame's come so: no sort)."""
        index, points = self.index, self.points
        if np.any(index[1:] < index[:-1]):
            order = np.argsort(index)
            index, points = index[order], points[order]
        return index, points

    def thinned(self, voxel: float) -> Frame:
        """At most about one point per ``voxel``: every k-th row and column of an organized
        frame (k from its pixels' footprint at the median range, or its ``sparse_step``), one
        point a voxel of a cloud without a grid. Never denser than it was."""
        if len(self) == 0 or voxel <= 0:
            return self
        if self.shape is not None:
            footprint = self.pixel_angle() * float(np.median(self.ranges()))
            return self.every(max(int(voxel // max(footprint, 1e-12)), self.sparse_step()))
        cells = np.floor(self.points / voxel).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        return self.take(np.sort(first))

    def every(self, step: int) -> Frame:
        """Every ``step``-th row and column of an organized frame's grid (itself for 1): the
        first pixel of each block of ``step`` x ``step``; where pixels are missing in a
        pattern, so that many blocks' first has no point, the first pixel each has a point on
        (docs/decisions.md#pixels-missing-in-a-pattern)."""
        if step <= 1:
            return self
        stride = self.step * step
        if self._firsts_held(stride) >= BLOCKS_HELD:
            grid = np.zeros(self.shape, dtype=bool)  # looked up: no // or % a point
            grid[::stride, ::stride] = True
        else:
            grid = _first_of_blocks(self._valid.reshape(self.shape), stride)
        thin = self.take(np.take(grid.ravel(), self.index))
        return Frame(thin.points, thin.index, self.shape, self.viewpoint, stride)

    def _firsts_held(self, stride: int) -> float:
        """Of a sample of the frame's points, the share whose block (``stride`` wide) has a
        point on its first pixel."""
        index = self._sorted_index
        chosen = index[:: max(1, len(index) // SPARSE_SAMPLE)]
        rows, columns = np.divmod(chosen, self.shape[1])
        firsts = (rows - rows % stride) * self.shape[1] + columns - columns % stride
        at = np.minimum(np.searchsorted(index, firsts), len(index) - 1)
        return float(np.mean(index[at] == firsts)) if len(chosen) else 1.0

    @property
    def _sorted_index(self) -> np.ndarray:
        """The points' pixels in order."""
        return self._in_pixel_order[0]

    @cached_property
    def _valid(self) -> np.ndarray:
        """(height * width,) whether each pixel of the organized frame's grid has a point."""
        valid = np.zeros(self.shape[0] * self.shape[1], dtype=bool)
        valid[self.index] = True
        return valid

    def sparse_step(self) -> int:
        """The stride of the grid on which an organized frame's points lie about as densely
        as a camera's pixels: 1, unless its pixels are missing in a pattern and a point lies
        on one pixel in four or fewer (a depth image registered to a colour image twice its
        size). From the median share of pixels with a point in windows put anywhere on the
        rows the frame's points span (those holding one)."""
        return self._sparse_step

    @cached_property
    def _sparse_step(self) -> int:
        if self.shape is None or len(self) < 16 or self.step > 1 or not self.patterned:
            return 1
        width = self.shape[1]
        low = int(self._sorted_index[0]) // width  # the rows the points span
        high = int(self._sorted_index[-1]) // width - SPARSE_WINDOW + 1
        if high <= low or width < SPARSE_WINDOW:
            return 1
        # anywhere, not about a point: in a regular pattern (a point every 2.1 pixels) a
        # window about one holds more than its share
        rng = np.random.default_rng(0)
        corners = rng.integers(low, high, SPARSE_SAMPLE) * width
        corners += rng.integers(0, width - SPARSE_WINDOW + 1, SPARSE_SAMPLE)
        offsets = np.arange(SPARSE_WINDOW)
        around = (offsets[:, None] * width + offsets[None, :]).ravel()
        shares = np.take(self._valid, corners[:, None] + around).mean(axis=1)
        shares = shares[shares > 0]  # windows on the frame's parts, not where it saw nothing
        if len(shares) < 16:
            return 1
        # the median window: those astride a part's outline or the frame's edge count less
        density = float(np.median(shares))
        # a point on about one pixel in s x s: stride s (a gap of one is linked across)
        return max(1, int(1.0 / np.sqrt(density) + 0.1))

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


def pair_angles(points: np.ndarray, first: np.ndarray, viewpoint: np.ndarray) -> np.ndarray:
    """(K,) the angle between the rays from ``viewpoint`` to the points ``first`` and ``first +
    1``; NaN where a point lies at the viewpoint. The cosines in one compiled pass where it
    can be (``kernels.pair_cosines``)."""
    if kernels.takes(points):
        cosine = kernels.pair_cosines(points, first, np.ascontiguousarray(viewpoint, np.float64))
    else:
        ends = []
        for chosen in (first, first + 1):
            rays = np.take(points, chosen, axis=0) - viewpoint
            with np.errstate(invalid="ignore", divide="ignore"):
                rays /= lengths(rays)[:, None]  # each ray's length: its range
            ends.append(rays)
        cosine = np.einsum("ij,ij->i", *ends)
    return np.arccos(np.clip(cosine, -1.0, 1.0))


def inside_box(points: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """(N,) whether each of ``points`` lies in the box ``low``-``high``, column by column: a
    reduction over rows of 3 is numpy's slow path (docs/decisions.md#a-frames-body)."""
    inside = np.ones(len(points), dtype=bool)
    for axis in range(3):
        column = points[:, axis]
        inside &= (column >= low[axis]) & (column <= high[axis])
    return inside


def cropped_reason(
    points: np.ndarray, roi: tuple[np.ndarray, np.ndarray], inside: int, least: int
) -> str:
    """Why a frame cropped to ``roi`` (low, high corners) is not searched: ``inside`` of its
    ``points`` lie in it, fewer than ``least``; where the points lie instead."""
    low, high = points.min(axis=0), points.max(axis=0)
    box = ", ".join(f"{a:.4g}..{b:.4g}" for a, b in zip(*roi, strict=True))
    span = ", ".join(f"{a:.3g}..{b:.3g}" for a, b in zip(low, high, strict=True))
    return (
        f"the region of interest (x, y, z: {box}) holds {inside} of the frame's {len(points)} "
        f"points, fewer than the {least} a part is searched on; the frame's points lie within "
        f"{span}, in the frame's own coordinates (the camera's, for a depth image)"
    )


def spacing_angle(points: np.ndarray, viewpoint: np.ndarray, sample: int = 512) -> float:
    """The median angle, seen from ``viewpoint``, between a point and its nearest neighbour."""
    if len(points) < 2:
        return 1e-3
    rng = np.random.default_rng(0)
    chosen = points[rng.choice(len(points), size=min(sample, len(points)), replace=False)]
    distance, _ = cKDTree(points).query(chosen, k=2)
    ranges = np.linalg.norm(chosen - viewpoint, axis=1)
    return float(np.median(distance[:, 1] / np.maximum(ranges, 1e-12)))


def _first_of_blocks(valid: np.ndarray, stride: int) -> np.ndarray:
    """(height, width) the first pixel, row by row, with a point (``valid``) of each block of
    ``stride`` x ``stride`` pixels that has one."""
    height, width = valid.shape
    tall, wide = -(-height // stride) * stride, -(-width // stride) * stride
    padded = np.zeros((tall, wide), dtype=bool)
    padded[:height, :width] = valid
    blocks = padded.reshape(tall // stride, stride, wide // stride, stride).swapaxes(1, 2)
    blocks = blocks.reshape(-1, stride * stride)
    held = np.flatnonzero(blocks.any(axis=1))
    pick = np.argmax(blocks[held], axis=1)  # the first True
    block_row, block_column = np.divmod(held, wide // stride)
    grid = np.zeros((tall, wide), dtype=bool)
    grid[block_row * stride + pick // stride, block_column * stride + pick % stride] = True
    return grid[:height, :width]
