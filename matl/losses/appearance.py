"""Appearance losses (paper Eq. 1, 2, 4).

Decision: ``||I^a - s(I^p)||_1`` is taken as the *mean* absolute difference over pixels and
channels rather than the sum, so that ``lam`` keeps its meaning at any image size.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def appearance_distance(anchors: torch.Tensor, warped: torch.Tensor, levels: int = 1) -> torch.Tensor:
    """Mean absolute difference over the last 3 dims: ``(..., 3, H, W) x (..., 3, H, W) -> (...)``.

    ``levels > 1`` averages the L1 over an image pyramid (2x2 average pooling per level; beyond
    the paper, which uses ``levels=1``): coarse levels see a misaligned object's overlap with the
    anchor, which widens the basin in which the STN gets a useful gradient.
    """
    if levels < 1:
        raise ValueError(f"appearance levels must be >= 1, got {levels}")
    total = (anchors - warped).abs().mean(dim=(-3, -2, -1))
    for _ in range(levels - 1):
        anchors, warped = _half(anchors), _half(warped)
        total = total + (anchors - warped).abs().mean(dim=(-3, -2, -1))
    return total / levels


def anchor_distances(anchors: torch.Tensor, warped: torch.Tensor, levels: int = 1) -> torch.Tensor:
    """``L^a(I_i^a, s(I^p))`` of each anchor of a bag (paper Eq. 3's argument):
    ``(anchors (B, N, 3, H, W), warped (B, 3, H, W)) -> (B, N)``.

    The one computation behind the multiple-anchor loss, the selection layer and the recognizer's
    ``anchor_choice=appearance``; ``levels`` as in :func:`appearance_distance`.
    """
    if anchors.ndim != 5 or warped.ndim != 4 or anchors.shape[0] != warped.shape[0]:
        raise ValueError(f"anchors must be (B, N, 3, H, W) and warped (B, 3, H, W), got "
                         f"{tuple(anchors.shape)} and {tuple(warped.shape)}")
    return appearance_distance(anchors, warped[:, None].expand_as(anchors), levels)


def _half(images: torch.Tensor) -> torch.Tensor:
    pooled = F.avg_pool2d(images.reshape(-1, *images.shape[-3:]), 2, ceil_mode=True)
    return pooled.reshape(*images.shape[:-2], *pooled.shape[-2:])


class AppearanceLoss(nn.Module):
    """Single-anchor appearance loss, Eq. 1: ``mean_b L^a(I^a_b, s(I^p_b))``.

    ``forward(anchor (B, 3, H, W), warped (B, 3, H, W)) -> scalar``.
    """

    def forward(self, anchor: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
        return appearance_distance(anchor, warped).mean()


class MultiAnchorAppearanceLoss(nn.Module):
    """Multiple-anchor appearance loss, Eq. 2: ``mean_b min_i L^a(I^a_{b,i}, s(I^p_b))``.

    ``forward(anchors (B, N, 3, H, W), warped (B, 3, H, W)) -> (loss, selected (B,))``; the
    selection is Eq. 3, so the loss equals Eq. 4 on the selected anchor. N = 1 is Eq. 1.

    Args:
        levels: pyramid levels of :func:`appearance_distance` (paper: 1).
    """

    def __init__(self, levels: int = 1) -> None:
        super().__init__()
        self.levels = levels

    def forward(self, anchors: torch.Tensor, warped: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        distances = anchor_distances(anchors, warped, self.levels)  # (B, N)
        best, selected = distances.min(dim=1)
        return best.mean(), selected
