"""Step 3b: the linear classifier of eq. (4) over the registered references.

``y_i = w_i . x + b_i`` on the flattened grid ``x``; the reported score is
eq. (4)'s normalisation, each class's positive output over the sum of them.
The weights are fitted in closed form by ridge regression to one-hot targets on
the grids of augmented views of every reference. The dual form costs
O(n^2 d) for n views of d = 4096 bins, so refitting after a registration takes
milliseconds for a hundred references, and nothing is trained iteratively.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LinearClassifier:
    labels: tuple[str, ...]
    weights: np.ndarray  # (C, d) float32
    bias: np.ndarray  # (C,) float32

    @classmethod
    def fit(
        cls, labels: list[str], view_grids: list[np.ndarray], ridge: float = 1e-3
    ) -> LinearClassifier:
        """Fit on ``view_grids[i]``, the (V_i, 64, 64) grids of views of ``labels[i]``."""
        features = np.concatenate([g.reshape(len(g), -1) for g in view_grids]).astype(np.float64)
        targets = np.zeros((len(features), len(labels)))
        row = 0
        for i, grids in enumerate(view_grids):
            targets[row : row + len(grids), i] = 1.0
            row += len(grids)
        feature_mean, target_mean = features.mean(axis=0), targets.mean(axis=0)
        x, y = features - feature_mean, targets - target_mean
        gram = x @ x.T
        gram[np.diag_indices_from(gram)] += ridge * np.trace(gram) / len(gram)
        weights = x.T @ np.linalg.solve(gram, y)  # (d, C)
        bias = target_mean - feature_mean @ weights
        return cls(tuple(labels), weights.T.astype(np.float32), bias.astype(np.float32))

    def decision(self, grid: np.ndarray) -> np.ndarray:
        """The raw linear outputs ``w_i . x + b_i``, one per label."""
        return self.weights @ grid.reshape(-1).astype(np.float32) + self.bias

    def scores(self, grid: np.ndarray) -> np.ndarray:
        """Eq. (4): each label's positive output divided by the sum of them."""
        positive = np.maximum(self.decision(grid), 0.0)
        total = positive.sum()
        return positive / total if total > 0 else np.full(len(self.labels), 1 / len(self.labels))
