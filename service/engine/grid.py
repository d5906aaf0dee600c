"""Step 3, grid: bin the mapped 2-D coordinates into the paper's 64x64 grid (Sect. 3.3).

Each mapped point adds one unit to its bin. Two choices the paper leaves open:
- the grid's extent: the paper rounds (u, v) to integers, which ties the grid to
  the network's output range; we centre the mapped coordinates on their mean and
  divide by ``SPAN`` times their RMS radius, so the grid does not depend on the
  output's absolute scale (which drifts between trainings and objects);
- the total: the grid is divided by the number of points, so a cloud with 10 %
  of the points gives the same picture as the whole one, only noisier.
"""

from __future__ import annotations

import numpy as np

GRID_SIZE = 64
SPAN = 2.5  # the grid covers +-SPAN RMS radii around the mean mapped coordinate


def grid(mapped: np.ndarray) -> np.ndarray:
    """(GRID_SIZE, GRID_SIZE) float32 grid of mapped coordinates (N, 2), summing to 1."""
    mapped = np.asarray(mapped, dtype=np.float64)
    centred = mapped - mapped.mean(axis=0)
    rms = np.sqrt((centred**2).sum(axis=1).mean()) or 1.0
    unit = centred / (SPAN * rms)  # the grid spans [-1, 1]
    bins = np.rint((unit + 1.0) * 0.5 * (GRID_SIZE - 1)).astype(np.int64)
    np.clip(bins, 0, GRID_SIZE - 1, out=bins)
    flat = np.bincount(bins[:, 0] * GRID_SIZE + bins[:, 1], minlength=GRID_SIZE * GRID_SIZE)
    return (flat / len(mapped)).reshape(GRID_SIZE, GRID_SIZE).astype(np.float32)
