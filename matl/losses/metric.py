"""Metric-learning losses with one signature: ``loss(anchor, positive, negatives, negative_mask=None)``.

Shapes: ``anchor`` and ``positive`` ``(B, D)``; ``negatives`` ``(B, M, D)``; ``negative_mask``
``(B, M)`` bool, False where a slot holds no valid negative. ``anchor`` is the selected anchor's
embedding ``c(I^a_*)``, ``positive`` is ``c(s(I^p))`` and ``negatives`` are ``c(s(I^n_j))``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def _check(anchor: torch.Tensor, positive: torch.Tensor, negatives: torch.Tensor) -> None:
    if anchor.ndim != 2 or positive.shape != anchor.shape or negatives.ndim != 3 \
            or negatives.shape[0] != anchor.shape[0] or negatives.shape[2] != anchor.shape[1]:
        raise ValueError(f"expected anchor/positive (B, D) and negatives (B, M, D), got "
                         f"{tuple(anchor.shape)}, {tuple(positive.shape)}, {tuple(negatives.shape)}")


class TripletLoss(nn.Module):
    """Eq. 7: ``max(||a - p||^2 - ||a - n||^2 + m, 0)``, averaged over valid (anchor, negative) pairs."""

    def __init__(self, margin: float = 0.2) -> None:
        super().__init__()
        if margin < 0:
            raise ValueError(f"loss.margin must be >= 0, got {margin}")
        self.margin = margin

    def forward(self, anchor: torch.Tensor, positive: torch.Tensor, negatives: torch.Tensor,
                negative_mask: torch.Tensor | None = None) -> torch.Tensor:
        _check(anchor, positive, negatives)
        d_pos = (anchor - positive).pow(2).sum(-1, keepdim=True)         # (B, 1)
        d_neg = (anchor[:, None] - negatives).pow(2).sum(-1)             # (B, M)
        hinge = F.relu(d_pos - d_neg + self.margin)
        if negative_mask is None:
            return hinge.mean()
        weights = negative_mask.to(hinge.dtype)
        return (hinge * weights).sum() / weights.sum().clamp_min(1.0)


class NCELoss(nn.Module):
    """Eq. 9: InfoNCE with the positive's cosine similarity to the selected anchor against M negatives.

    ``-log(exp(sim(p, a)/tau) / (exp(sim(p, a)/tau) + sum_j exp(sim(p, n_j)/tau)))``.

    ``temperature_scaled`` (default, beyond the paper) multiplies it by ``tau``: its gradient with
    respect to the cosine similarities is then bounded by 1 like the triplet loss's, whatever ``tau``.
    Unscaled, at tau = 0.07 and the paper's SGD lr 0.01 (momentum 0.9), c() collapsed within 30 steps
    (every embedding the same, loss stuck at log(M + 1)); docs/decisions.md.
    """

    def __init__(self, tau: float = 0.07, temperature_scaled: bool = True) -> None:
        super().__init__()
        if tau <= 0:
            raise ValueError(f"loss.tau must be > 0, got {tau}")
        self.tau = tau
        self.scale = tau if temperature_scaled else 1.0

    def forward(self, anchor: torch.Tensor, positive: torch.Tensor, negatives: torch.Tensor,
                negative_mask: torch.Tensor | None = None) -> torch.Tensor:
        _check(anchor, positive, negatives)
        p = F.normalize(positive, dim=-1)
        sim_pos = (p * F.normalize(anchor, dim=-1)).sum(-1, keepdim=True)           # (B, 1)
        sim_neg = torch.einsum("bd,bmd->bm", p, F.normalize(negatives, dim=-1))      # (B, M)
        if negative_mask is not None:
            sim_neg = sim_neg.masked_fill(~negative_mask, float("-inf"))
        logits = torch.cat([sim_pos, sim_neg], dim=1) / self.tau
        return self.scale * (torch.logsumexp(logits, dim=1) - logits[:, 0]).mean()
