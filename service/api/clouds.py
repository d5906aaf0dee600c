"""What a file or body gives the engine: points, and, for an organized frame (a depth image,
a PCD or NPY of height > 1), where each came from in its pixel grid.

A missing pixel of an organized frame (NaN or infinity in a cloud file, 0 in a depth image)
is skipped, never an error: only the valid points are counted against the limits."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.errors import InvalidPoints


@dataclass(frozen=True)
class Cloud:
    points: np.ndarray  # (N, 3), not yet validated
    index: np.ndarray | None = None  # (N,) each point's pixel, row * width + column
    shape: tuple[int, int] | None = None  # (height, width) of the grid it came from


def organized(grid: np.ndarray, max_points: int, what: str) -> Cloud:
    """The valid pixels of an (H, W, 3) grid of points, counted against ``max_points``."""
    height, width = grid.shape[:2]
    flat = grid.reshape(-1, 3)
    valid = np.flatnonzero(np.isfinite(flat).all(axis=1))
    if len(valid) > max_points:
        raise InvalidPoints(
            f"the {what} has {len(valid)} valid points, more than the maximum of {max_points}: "
            "crop it, or send a region of interest"
        )
    return Cloud(flat[valid], valid.astype(np.int64), (height, width))
