"""Losses against hand-computed values; the selection layer picks the true nearest anchor."""

from __future__ import annotations

import math

import pytest
import torch

from matl.losses import (
    AppearanceLoss,
    MultiAnchorAppearanceLoss,
    NCELoss,
    TripletLoss,
    anchor_distances,
    appearance_distance,
)
from matl.models.selection import AnchorSelection


def test_appearance_distance_is_mean_l1() -> None:
    a = torch.zeros(1, 3, 2, 2)
    b = torch.zeros(1, 3, 2, 2)
    b[0, 0, 0, 0] = 1.2  # one of 12 values differs by 1.2
    assert math.isclose(float(appearance_distance(a, b)), 0.1, rel_tol=1e-6)
    assert math.isclose(float(AppearanceLoss()(a, b)), 0.1, rel_tol=1e-6)


def test_multi_anchor_appearance_takes_min_and_selects() -> None:
    warped = torch.full((2, 3, 2, 2), 0.5)
    anchors = torch.stack([torch.full((3, 3, 2, 2), v) for v in (0.0, 0.4, 1.0)])  # (3 values, N=3 ...)
    anchors = torch.stack([torch.full((3, 2, 2), v) for v in (0.0, 0.4, 1.0)])[None].repeat(2, 1, 1, 1, 1)
    anchors[1, 2] = 0.55
    loss, selected = MultiAnchorAppearanceLoss()(anchors, warped)
    assert selected.tolist() == [1, 2]
    assert math.isclose(float(loss), (0.1 + 0.05) / 2, rel_tol=1e-5)


def test_anchor_distances_hand_computed_with_a_pyramid() -> None:
    warped = torch.zeros(1, 3, 2, 2)
    anchors = torch.zeros(1, 2, 3, 2, 2)
    anchors[0, 1, :, 0, 0] = 0.8   # one pixel of 4: level 0 L1 = 0.2; the 2x2 average (0.2) at level 1: 0.2
    assert torch.allclose(anchor_distances(anchors, warped), torch.tensor([[0.0, 0.2]]))
    assert torch.allclose(anchor_distances(anchors, warped, levels=2), torch.tensor([[0.0, 0.2]]))
    anchors[0, 1, :, 0, 1] = -0.8  # cancels at level 1: (0.4 + 0) / 2
    assert torch.allclose(anchor_distances(anchors, warped, levels=2), torch.tensor([[0.0, 0.2]]))
    assert torch.allclose(anchor_distances(anchors, warped), torch.tensor([[0.0, 0.4]]))
    with pytest.raises(ValueError, match=r"anchors must be \(B, N, 3, H, W\)"):
        anchor_distances(anchors[0], warped)


def test_selection_layer_picks_true_nearest_anchor() -> None:
    g = torch.Generator().manual_seed(0)
    anchors = torch.rand(5, 4, 3, 8, 8, generator=g)
    truth = torch.tensor([3, 0, 2, 1, 3])
    warped = anchors[torch.arange(5), truth] + 0.01 * torch.randn(5, 3, 8, 8, generator=g)
    index, distances = AnchorSelection()(anchors, warped)
    assert index.tolist() == truth.tolist()
    assert distances.shape == (5, 4)


def test_triplet_loss_hand_computed() -> None:
    a = torch.tensor([[0.0, 0.0], [0.0, 0.0]])
    p = torch.tensor([[1.0, 0.0], [0.1, 0.0]])
    n = torch.tensor([[[0.0, 1.5]], [[0.0, 2.0]]])
    # row 0: 1 - 2.25 + 0.5 = -0.75 -> 0; with margin 2: 0.75. row 1: 0.01 - 4 + 2 -> 0
    assert float(TripletLoss(margin=0.5)(a, p, n)) == 0.0
    assert math.isclose(float(TripletLoss(margin=2.0)(a, p, n)), 0.75 / 2, rel_tol=1e-6)
    mask = torch.tensor([[True], [False]])
    assert math.isclose(float(TripletLoss(margin=2.0)(a, p, n, mask)), 0.75, rel_tol=1e-6)


def test_nce_loss_hand_computed() -> None:
    a = torch.tensor([[1.0, 0.0]])
    p = torch.tensor([[1.0, 0.0]])
    n = torch.tensor([[[0.0, 1.0], [-1.0, 0.0]]])
    tau = 0.5
    expected = -math.log(math.exp(1 / tau) / (math.exp(1 / tau) + math.exp(0) + math.exp(-1 / tau)))
    assert math.isclose(float(NCELoss(tau, temperature_scaled=False)(a, p, n)), expected, rel_tol=1e-6)
    mask = torch.tensor([[True, False]])
    expected_masked = -math.log(math.exp(2) / (math.exp(2) + 1.0))
    assert math.isclose(float(NCELoss(tau, temperature_scaled=False)(a, p, n, mask)), expected_masked, rel_tol=1e-6)
    # the default (temperature-scaled) is Eq. 9 times tau
    assert math.isclose(float(NCELoss(tau)(a, p, n)), tau * expected, rel_tol=1e-6)
