"""The selection layer (paper Eq. 3): pick the anchor closest to the transformed positive."""

from __future__ import annotations

import torch
from torch import nn

from matl.losses.appearance import anchor_distances


class AnchorSelection(nn.Module):
    """``argmin_i L^a(I_i^a, s(I^p))`` over a bag of anchors.

    ``forward(anchors (B, N, 3, H, W), warped (B, 3, H, W)) -> (index (B,), distances (B, N))``.
    The index carries no gradient (Sec. 4.3: only the selected anchor contributes).
    """

    def forward(self, anchors: torch.Tensor, warped: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        distances = anchor_distances(anchors, warped)
        return distances.detach().argmin(dim=1), distances
