"""The DPC-MN mapping network of the paper's Fig. 2, and nothing else.

    points (B, N, 3)
      |-- per-point branch: 1x1 conv 3->64->128->256, ReLU       -> features (B, N, 256)
      '-- global branch:    1x1 conv 3->64->128->256, ReLU,
                            average pool over the points          -> (B, 256)
                            linear 256->512, reshape              -> matrix (B, 256, 2)
    mapped = features @ matrix                                     -> (B, N, 2)

Choices the paper leaves open, and why:
- Widths 64-128-256 in both branches: the figure fixes only the 256-d point feature
  and the 512-d (256x2) matrix; 64-128 are PointNet's first widths.
- Two separate branches (the figure draws the global branch from the input), so
  the matrix sees the whole shape while each point's feature sees only that point.
- No activation after the last linear layer: the caption says "all layers" are
  ReLU, but a ReLU there would zero half the matrix and confine every output to
  one quadrant; the matrix is a projection and needs both signs.
- No normalisation layers: the figure shows none, and the input is already centred
  and scaled (``service.engine.normalize``), so the network needs no running statistics
  and the ONNX graph is the same in training and serving.
- The input is the cloud centred on its centroid and divided by its radius, and
  (``canonical=True`` in the config, the shipped default) rotated into its
  principal-axes frame first; that step runs in numpy before the network, in
  the service and in training alike.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn


@dataclass
class ModelConfig:
    widths: tuple[int, ...] = (64, 128, 256)  # per-point and global 1x1 conv widths
    out_dim: int = 2  # the mapped coordinate (u, v)

    def to_dict(self) -> dict:
        return asdict(self)


def pointwise_mlp(widths: tuple[int, ...]) -> nn.Sequential:
    """1x1 convolutions with ReLU: the same small network applied to every point."""
    layers: list[nn.Module] = []
    previous = 3
    for width in widths:
        layers += [nn.Conv1d(previous, width, kernel_size=1), nn.ReLU()]
        previous = width
    return nn.Sequential(*layers)


class DPCMN(nn.Module):
    def __init__(self, config: ModelConfig | None = None):
        super().__init__()
        self.config = config or ModelConfig()
        feature_dim = self.config.widths[-1]
        self.point_branch = pointwise_mlp(self.config.widths)
        self.global_branch = pointwise_mlp(self.config.widths)
        self.to_matrix = nn.Linear(feature_dim, feature_dim * self.config.out_dim)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) normalised points -> (B, N, 2) mapped coordinates."""
        x = points.transpose(1, 2)  # (B, 3, N)
        features = self.point_branch(x)  # (B, 256, N)
        pooled = self.global_branch(x).mean(dim=2)  # (B, 256): symmetric in the points
        matrix = self.to_matrix(pooled).view(-1, features.shape[1], self.config.out_dim)
        return torch.bmm(features.transpose(1, 2), matrix)  # (B, N, 2)
