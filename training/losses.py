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


def pose_loss(anchor: torch.Tensor, rotated: torch.Tensor) -> torch.Tensor:
    """Eq. (2), L_p: the same points in another pose map to the same place, ``mean |M_a - M_i|``."""
    return (anchor - rotated).norm(dim=-1).mean()


def total_loss(
    anchor: torch.Tensor,
    positive: torch.Tensor,
    negative: torch.Tensor,
    rotated: torch.Tensor,
    margin: float,
    weight: float,
    anchor_shared: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eq. (3), ``f = L_m + lambda * L_p``; returns (f, L_m, L_p).

    ``anchor_shared`` are the anchor's rows that ``rotated`` holds too (default: all).
    """
    l_m = mapping_loss(anchor, positive, negative, margin)
    l_p = pose_loss(anchor if anchor_shared is None else anchor_shared, rotated)
    return l_m + weight * l_p, l_m, l_p
