"""Appearance losses (paper Eq. 1, 2, 4).

Decision: ``||I^a - s(I^p)||_1`` is taken as the *mean* absolute difference over pixels and
channels rather than the sum, so that ``lam`` keeps its meaning at any image size.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def appearance_distance(anchors: torch.Tensor, warped: torch.Tensor, levels: int = 1,
                        mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute difference over the last 3 dims: ``(..., 3, H, W) x (..., 3, H, W) -> (...)``.

    ``levels > 1`` averages the L1 over an image pyramid (2x2 average pooling per level; beyond
    the paper, which uses ``levels=1``): coarse levels see a misaligned object's overlap with the
    anchor, which widens the basin in which the STN gets a useful gradient.

    ``mask`` (beyond the paper; ``model.appearance_mask=foreground``): ``(..., 1, H, W)`` weights in
    [0, 1] (a foreground mask), broadcast over the channels. Both images are multiplied by it and each
    level's term is the mean of ``|anchors * mask - warped * mask|`` over *all* pixels and channels (the
    image area, as the unmasked loss): a pixel outside the mask adds 0, so the masked value is the
    unmasked one less what the background would cost, and ``lam`` keeps the paper's scale. The masked
    images are average-pooled from level to level, so a pixel outside the mask changes no level. A mask
    of ones gives exactly the unmasked value; an empty mask gives 0. There is no division by the mask:
    a normaliser that depends on a mask moved by a predicted homography (the backward term's) lets the
    loss ignore how much of the product the mask still covers, and its gradient grows as ``1 / area^2``
    when the prediction shrinks the mask (docs/decisions.md).
    """
    if levels < 1:
        raise ValueError(f"appearance levels must be >= 1, got {levels}")
    if mask is not None:
        _check_mask(mask, anchors)
        anchors, warped = anchors * mask, warped * mask
    total = _level_distance(anchors, warped)
    for _ in range(levels - 1):
        anchors, warped = _half(anchors), _half(warped)
        total = total + _level_distance(anchors, warped)
    return total / levels


def _level_distance(anchors: torch.Tensor, warped: torch.Tensor) -> torch.Tensor:
    return (anchors - warped).abs().mean(dim=(-3, -2, -1))


def select_anchors(distances: torch.Tensor, masks: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 3: the index ``(B,)`` of the anchor nearest in appearance, from ``distances`` ``(B, N)``.

    With ``masks`` ``(B, N, 1, H, W)`` (the anchors' own foregrounds, data, not a prediction) each
    anchor's image-area distance is divided by its foreground share before the comparison, so that an
    anchor is not chosen for showing less product; an anchor with an empty mask is never chosen unless
    all are. Without masks this is ``distances.argmin(dim=1)``.
    """
    if masks is None:
        return distances.argmin(dim=1)
    share = masks.detach().mean(dim=(-3, -2, -1))                           # (B, N)
    per_foreground = torch.where(share > 0, distances.detach() / share.clamp_min(torch.finfo(share.dtype).tiny),
                                 torch.full_like(share, float("inf")))
    return per_foreground.argmin(dim=1)


def _check_mask(mask: torch.Tensor, images: torch.Tensor) -> None:
    if (not isinstance(mask, torch.Tensor) or mask.ndim != images.ndim or mask.shape[-3] != 1
            or mask.shape[-2:] != images.shape[-2:]):
        shape = tuple(mask.shape) if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ValueError(f"appearance mask must be (..., 1, H, W) for images {tuple(images.shape)}, got {shape}")
    try:
        torch.broadcast_shapes(mask.shape, images.shape)
    except RuntimeError:
        raise ValueError(f"appearance mask {tuple(mask.shape)} does not match images {tuple(images.shape)}") from None


def anchor_distances(anchors: torch.Tensor, warped: torch.Tensor, levels: int = 1,
                     masks: torch.Tensor | None = None) -> torch.Tensor:
    """``L^a(I_i^a, s(I^p))`` of each anchor of a bag (paper Eq. 3's argument):
    ``(anchors (B, N, 3, H, W), warped (B, 3, H, W)) -> (B, N)``.

    The one computation behind the multiple-anchor loss, the selection layer and the recognizer's
    ``anchor_choice=appearance``; ``levels`` as in :func:`appearance_distance`. ``masks``: ``(B, N, 1, H, W)``
    foreground of each anchor; each anchor's distance is then over its own foreground (image-area
    normalised, :func:`appearance_distance`; Eq. 3 compares them per unit of foreground,
    :func:`select_anchors`).
    """
    if anchors.ndim != 5 or warped.ndim != 4 or anchors.shape[0] != warped.shape[0]:
        raise ValueError(f"anchors must be (B, N, 3, H, W) and warped (B, 3, H, W), got "
                         f"{tuple(anchors.shape)} and {tuple(warped.shape)}")
    if masks is not None and tuple(masks.shape) != (*anchors.shape[:2], 1, *anchors.shape[-2:]):
        raise ValueError(f"anchor masks must be (B, N, 1, H, W) = {(*anchors.shape[:2], 1, *anchors.shape[-2:])} "
                         f"for anchors {tuple(anchors.shape)}, got {tuple(masks.shape)}")
    return appearance_distance(anchors, warped[:, None].expand_as(anchors), levels, masks)


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

    ``forward(anchors (B, N, 3, H, W), warped (B, 3, H, W), masks (B, N, 1, H, W) | None) -> (loss,
    selected (B,))``; the selection is Eq. 3, so the loss equals Eq. 4 on the selected anchor. N = 1 is
    Eq. 1. With ``masks`` each anchor's L1 is over its own foreground (:func:`appearance_distance`) and
    the selection compares them per unit of foreground (:func:`select_anchors`).

    Args:
        levels: pyramid levels of :func:`appearance_distance` (paper: 1).
    """

    def __init__(self, levels: int = 1) -> None:
        super().__init__()
        self.levels = levels

    def forward(self, anchors: torch.Tensor, warped: torch.Tensor, masks: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        distances = anchor_distances(anchors, warped, self.levels, masks)  # (B, N)
        if masks is None:
            best, selected = distances.min(dim=1)
            return best.mean(), selected
        selected = select_anchors(distances, masks)
        return distances.gather(1, selected[:, None]).mean(), selected
