"""The paper's unsupervised losses (Sect. 3.2), one short function per equation.

``M_*`` are mapped clouds of shape (B, N, 2) whose rows correspond point by point.
"""

from __future__ import annotations

import torch


def mapping_loss(
    anchor: torch.Tensor, positive: torch.Tensor, negative: torch.Tensor, margin: float
) -> torch.Tensor:
    """Eq. (1), L_m: a point maps nearer to its jittered self than to a random other point.

    ``mean(max(eps + |M_a - M_p| - |M_a - M_n|, 0))``. ``negative`` is the mapping of
    the shuffled anchor, so row i of it belongs to some other point of the cloud.
    """
    near = (anchor - positive).norm(dim=-1)
    far = (anchor - negative).norm(dim=-1)
    return torch.clamp(margin + near - far, min=0).mean()


def pose_loss(
    anchor: torch.Tensor, rotated: torch.Tensor, shared: torch.Tensor | None = None
) -> torch.Tensor:
    """Eq. (2), L_p: the same points in another pose map to the same place, ``mean |M_a - M_i|``.

    ``shared`` (B, N) bool marks the rows that are the same point in both clouds; the mean
    runs over those alone (default: every row).
    """
    distance = (anchor - rotated).norm(dim=-1)
    if shared is None:
        return distance.mean()
    return (distance * shared).sum() / shared.sum().clamp(min=1)


def total_loss(
    anchor: torch.Tensor,
    positive: torch.Tensor,
    negative: torch.Tensor,
    rotated: torch.Tensor,
    margin: float,
    weight: float,
    shared: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eq. (3), ``f = L_m + lambda * L_p``; returns (f, L_m, L_p).

    ``shared`` (B, N) bool: the rows ``rotated`` holds in common with the anchor (default: all).
    """
    l_m = mapping_loss(anchor, positive, negative, margin)
    l_p = pose_loss(anchor, rotated, shared)
    return l_m + weight * l_p, l_m, l_p
