"""Step 3b: the linear classifier of eq. (4) over the registered references.

``y_i = w_i . x + b_i`` on the flattened grid ``x``; the reported score is
eq. (4)'s normalisation, each class's positive output over the sum of them.
Grids are smoothed by a Gaussian of ``blur`` bins and pooled 2x2 (to 32x32) before
the linear map: both are linear, so this is still eq. (4) on the 64x64 grid, with
smoothed weights. Smoothing lets a sparse cloud's scattered bins vote for their
neighbours; pooling what smoothing made redundant makes the fit four times cheaper.
The weights are fitted in closed form by ridge regression to one-hot targets on
the grids of augmented views of every reference: one (d x d) solve for d = 1024
pooled bins, whose cost grows only linearly with the number of views, so a
registration refits the whole gallery without any iterative training.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from service.grid import GRID_SIZE

POOL = 2  # bins pooled per side after smoothing


@dataclass(frozen=True)
class LinearClassifier:
    labels: tuple[str, ...]
    weights: np.ndarray  # (C, d) float32
    bias: np.ndarray  # (C,) float32
    blur: float = 0.0  # Gaussian smoothing of the grid, in bins

    @classmethod
    def fit(
        cls,
        labels: list[str],
        view_features: list[np.ndarray],
        ridge: float = 1e-3,
        blur: float = 0.0,
    ) -> LinearClassifier:
        """Fit on ``view_features[i]``: ``classifier_input(view grids of labels[i], blur)``.

        The features are computed once per reference (they depend on nothing else),
        so a refit after a registration costs only the solve.
        """
        features = np.concatenate(view_features)
        targets = np.zeros((len(features), len(labels)))
        row = 0
        for i, rows in enumerate(view_features):
            targets[row : row + len(rows), i] = 1.0
            row += len(rows)
        feature_mean, target_mean = features.mean(axis=0), targets.mean(axis=0)
        x, y = features - feature_mean, (targets - target_mean).astype(np.float32)
        scatter = (x.T @ x).astype(np.float64)  # (d, d): the cost grows linearly with the views
        # the ridge is relative to the features' variance, with a floor for a gallery of one
        # view (zero scatter), where the solve would otherwise be singular
        scatter[np.diag_indices_from(scatter)] += ridge * (np.trace(scatter) / len(scatter) or 1.0)
        weights = np.linalg.solve(scatter, (x.T @ y).astype(np.float64)).astype(np.float32)
        bias = target_mean - feature_mean @ weights
        weights = weights.T.astype(np.float32)
        return cls(tuple(labels), weights, bias.astype(np.float32), blur)

    def decision(self, grid: np.ndarray) -> np.ndarray:
        """The raw linear outputs ``w_i . x + b_i``, one per label."""
        return self.weights @ classifier_input(grid, self.blur)[0] + self.bias

    def scores(self, grid: np.ndarray) -> np.ndarray:
        """Eq. (4): each label's positive output divided by the sum of them."""
        positive = np.maximum(self.decision(grid), 0.0)
        total = positive.sum()
        return positive / total if total > 0 else np.full(len(self.labels), 1 / len(self.labels))


def classifier_input(grids: np.ndarray, blur: float) -> np.ndarray:
    """(V, 1024) float32 features of one (64, 64) grid or a (V, 64, 64) stack: smoothed, pooled."""
    grids = np.asarray(grids, dtype=np.float32).reshape(-1, GRID_SIZE, GRID_SIZE)
    if blur > 0:
        grids = gaussian_filter(grids, sigma=(0, blur, blur), mode="constant")
    half = GRID_SIZE // POOL
    return (
        grids.reshape(len(grids), half, POOL, half, POOL).sum(axis=(2, 4)).reshape(len(grids), -1)
    )
