"""What the camera of an organized frame saw along each ray: its depth image, and the pinhole
that made it, read back from the frame's own points (each pixel's x / z and y / z fit its
column and row), so that a pose can be checked against the free space the camera saw through.

A part placed at a pose shows some of its surface to the camera. Each such point lands on a
pixel: where the frame's depth there matches the point's, it is seen; where something nearer
hides it, it is occluded (no evidence either way); where the camera saw farther (a table
behind, another part), the part cannot be there: the camera saw through where it would be.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.engine.frame import Frame
from service.engine.tuning import PINHOLE_POINTS, PINHOLE_RESIDUAL_PX


@dataclass(frozen=True)
class DepthImage:
    focal: np.ndarray  # (2,) fx, fy in pixels of the (thinned) grid
    centre: np.ndarray  # (2,) cx, cy
    depth: np.ndarray  # (rows, columns) z of the frame's point at each pixel; NaN: none

    @classmethod
    def of(cls, frame: Frame) -> DepthImage | None:
        """The frame's depth image on its (thinned) grid; None for a frame without a grid, a
        camera that was not at the frame's origin looking along z, or one that is not a
        pinhole (``PINHOLE_RESIDUAL_PX``)."""
        if frame.shape is None or len(frame) < 16 or np.any(frame.viewpoint != 0):
            return None
        points = frame.points
        if np.any(points[:, 2] <= 0):
            return None
        rows, columns = frame.cells()
        # the pinhole from every k-th point: its 4 numbers need no more (a tenth of the time)
        every = slice(None, None, max(1, len(points) // PINHOLE_POINTS))
        pixel = np.stack([columns[every], rows[every]], axis=1).astype(np.float64)
        ratio = points[every, :2] / points[every, 2:3]
        focal, centre = np.zeros(2), np.zeros(2)
        for axis in range(2):  # pixel = f * x / z + c
            design = np.stack([ratio[:, axis], np.ones(len(ratio))], axis=1)
            (focal[axis], centre[axis]), *_ = np.linalg.lstsq(design, pixel[:, axis], rcond=None)
        residual = pixel - (ratio * focal + centre)
        if np.sqrt(np.mean(residual**2)) > PINHOLE_RESIDUAL_PX:
            return None
        depth = np.full(frame.grid_shape, np.nan)
        depth[rows, columns] = points[:, 2]
        return cls(focal, centre, depth)

    def depth_at(self, points: np.ndarray) -> np.ndarray:
        """(...) the frame's depth at the pixel each of ``points`` (..., 3) projects to; NaN off
        the image, behind the camera, or on a pixel without depth."""
        z = points[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            column = np.rint(points[..., 0] / z * self.focal[0] + self.centre[0])
            row = np.rint(points[..., 1] / z * self.focal[1] + self.centre[1])
            height, width = self.depth.shape
            inside = (z > 0) & (column >= 0) & (column < width) & (row >= 0) & (row < height)
            pixel = np.where(inside, row * width + column, 0).astype(np.intp)
        # one flat np.take, not a boolean gather and 2-D indexing: a fraction of their time
        return np.where(inside, np.take(self.depth, pixel), np.nan)

    def look(self, points: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
        """For points (..., 3) the camera should see, whether each is seen (the frame's depth
        at its pixel within ``tolerance`` of its own) and whether the camera saw through it
        (the frame's depth farther by more than ``tolerance``). Points off the image, behind
        the camera or on a pixel without depth are neither."""
        z = points[..., 2]
        observed = self.depth_at(points)
        with np.errstate(invalid="ignore"):
            seen = np.abs(observed - z) <= tolerance
            through = observed - z > tolerance
        return seen, through

    def agreement(
        self, points: np.ndarray, tolerance: float, through_weight: float = 1.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """For sets of points (..., P, 3) the camera should see: each set moved along z by the
        mean difference (within three tolerances) between the frame's depth and its own (its
        depth snapped onto the frame), then its share of points within ``tolerance`` of the
        frame's depth, weighed by how close (1 on it, 0 at the tolerance), less the share the
        camera saw through (``through_weight`` times that share); of the points not hidden by
        something nearer. The scores (...), and the depth shifts (...)."""
        z = points[..., 2]
        observed = self.depth_at(points)
        difference = observed - z
        near = np.abs(difference) <= 3 * tolerance  # NaN: False
        count = near.sum(axis=-1)
        total = np.where(near, difference, 0.0).sum(axis=-1)
        shift = np.where(count > 0, total / np.maximum(count, 1), 0.0)
        residual = difference - shift[..., None]
        with np.errstate(invalid="ignore"):
            weight = np.nan_to_num(np.clip(1 - np.abs(residual) / tolerance, 0, 1))
            through = residual > tolerance
            hidden = residual < -tolerance
        counted = np.maximum((~hidden).sum(axis=-1), 1)
        score = (weight.sum(axis=-1) - through_weight * through.sum(axis=-1)) / counted
        return score, shift
