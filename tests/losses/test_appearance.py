"""The appearance loss over the anchor's foreground (``model.appearance_mask=foreground``), by hand."""

from __future__ import annotations

import math

import pytest
import torch

from matl.geometry import warp_image
from matl.losses import MultiAnchorAppearanceLoss, anchor_distances, appearance_distance
from matl.losses.appearance import select_anchors
from matl.losses.metric import TripletLoss
from matl.models.feature import FeatureNet
from matl.models.module import MATLModule
from matl.models.stn import HomographyRegressor, SpatialTransformer


def test_masked_distance_hand_computed() -> None:
    anchor = torch.zeros(1, 3, 2, 2)
    warped = torch.zeros(1, 3, 2, 2)
    warped[0, :, 0, 0] = 0.6   # inside the mask: |0 - 0.6| in every channel
    warped[0, :, 1, 1] = 0.9   # outside the mask: free
    mask = torch.tensor([[[[1.0, 1.0], [0.0, 0.0]]]])  # the top row: 2 of 4 pixels
    # the image area normalises (as unmasked), not the mask: a mask's mean moved by a predicted warp
    # made the term blind to how much of the product it covered, with a 1 / area^2 gradient
    # level 0: (0.6 + 0 + 0 + 0) / 4 pixels = 0.15
    assert math.isclose(float(appearance_distance(anchor, warped, mask=mask)), 0.15, rel_tol=1e-6)
    # level 1: masked images pooled: anchor 0, warped (0.6 + 0 + 0 + 0) / 4 = 0.15 -> 0.15
    assert math.isclose(float(appearance_distance(anchor, warped, levels=2, mask=mask)), 0.15, rel_tol=1e-6)
    # unmasked, for contrast: (0.6 + 0.9) / 4 = 0.375 at level 0, |0 - 1.5 / 4| = 0.375 at level 1
    assert math.isclose(float(appearance_distance(anchor, warped, levels=2)), 0.375, rel_tol=1e-6)
    # a fractional mask weighs each pixel: mean |0.5 * 0.6| over 4 pixels
    soft = torch.tensor([[[[0.5, 1.0], [0.0, 0.0]]]])
    assert math.isclose(float(appearance_distance(anchor, warped, mask=soft)), 0.5 * 0.6 / 4, rel_tol=1e-6)
    # an empty mask costs nothing (no division by zero)
    assert float(appearance_distance(anchor, warped, mask=torch.zeros(1, 1, 2, 2))) == 0.0


@pytest.mark.parametrize("levels", [1, 3])
def test_a_mask_of_ones_is_exactly_the_unmasked_loss(levels: int) -> None:
    g = torch.Generator().manual_seed(0)
    anchors, warped = torch.rand(2, 4, 3, 9, 9, generator=g), torch.rand(2, 3, 9, 9, generator=g)
    ones = torch.ones(2, 4, 1, 9, 9)
    assert torch.equal(anchor_distances(anchors, warped, levels, ones), anchor_distances(anchors, warped, levels))
    loss = MultiAnchorAppearanceLoss(levels)
    (masked, sel_masked), (plain, sel_plain) = loss(anchors, warped, ones), loss(anchors, warped)
    assert torch.equal(masked, plain) and torch.equal(sel_masked, sel_plain)


@pytest.mark.parametrize("levels", [1, 3])
def test_background_outside_the_mask_changes_nothing(levels: int) -> None:
    g = torch.Generator().manual_seed(1)
    anchor = torch.zeros(2, 3, 12, 12)
    anchor[:, :, 3:9, 2:10] = torch.rand(2, 3, 6, 8, generator=g)
    mask = (anchor.amax(dim=1, keepdim=True) > 0).float()
    warped = anchor + 0.1 * torch.rand(2, 3, 12, 12, generator=g)
    cluttered = torch.where(mask.bool(), warped, torch.rand(2, 3, 12, 12, generator=g))  # new background only
    before = appearance_distance(anchor, warped, levels, mask)
    assert torch.equal(appearance_distance(anchor, cluttered, levels, mask), before)
    unmasked = appearance_distance(anchor, warped, levels)
    assert not torch.allclose(appearance_distance(anchor, cluttered, levels), unmasked)


def test_selection_uses_each_anchors_own_foreground() -> None:
    """Eq. 3 with masks: anchor 0 matches the query on its small foreground, anchor 1 is worse inside its
    own; unmasked, anchor 1 wins because the query's texture lies on anchor 0's black background."""
    warped = torch.full((1, 3, 4, 4), 0.5)
    anchors = torch.zeros(1, 2, 3, 4, 4)
    anchors[0, 0, :, :1, :1] = 0.5                 # one matching pixel, the rest background
    anchors[0, 1] = 0.3                            # everywhere, 0.2 off
    masks = (anchors.amax(dim=2, keepdim=True) > 0).float()
    assert MultiAnchorAppearanceLoss()(anchors, warped)[1].tolist() == [1]
    loss, selected = MultiAnchorAppearanceLoss()(anchors, warped, masks)
    assert selected.tolist() == [0] and float(loss) == 0.0


def test_mask_shapes_are_checked() -> None:
    anchors, warped = torch.rand(2, 4, 3, 8, 8), torch.rand(2, 3, 8, 8)
    with pytest.raises(ValueError, match=r"anchor masks must be \(B, N, 1, H, W\)"):
        anchor_distances(anchors, warped, 1, torch.ones(2, 4, 3, 8, 8))
    with pytest.raises(ValueError, match=r"appearance mask must be \(\.\.\., 1, H, W\)"):
        appearance_distance(warped, warped, 1, torch.ones(2, 1, 4, 4))


def masked_model_and_anchor(S: int, levels: int, box: tuple[int, int, int, int], seed: int
                            ) -> tuple[MATLModule, torch.Tensor, torch.Tensor, torch.Generator]:
    """A symmetric, foreground-masked MATL model at ``S`` px, an anchor with a random print on the
    ``(y0, y1, x0, x1)`` box of a black image, its mask, and the generator that drew the print (for more draws)."""
    torch.manual_seed(0)
    stn = SpatialTransformer(HomographyRegressor(image_size=S), image_size=S)
    model = MATLModule(FeatureNet(), stn, TripletLoss(), image_size=S, appearance="symmetric",
                       appearance_levels=levels, appearance_mask="foreground")
    g = torch.Generator().manual_seed(seed)
    y0, y1, x0, x1 = box
    anchor = torch.zeros(1, 3, S, S)
    anchor[:, :, y0:y1, x0:x1] = torch.rand(1, 3, y1 - y0, x1 - x0, generator=g)
    return model, anchor, (anchor.amax(dim=1, keepdim=True) > 0).float(), g


def test_backward_term_uses_the_anchors_mask_warped_into_the_positive() -> None:
    """``appearance=symmetric`` + masks: the backward term compares the anchor warped into the positive's frame
    with the positive over the anchor's foreground warped the same way: the positive's background is free."""
    S = 16
    model, anchor, mask, g = masked_model_and_anchor(S, 2, (4, 12, 5, 11), seed=2)
    H = torch.tensor([[[1.0, 0.0, 2.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]]])  # anchor -> positive: a shift
    positive = warp_image(anchor, H)
    mask_in_positive = warp_image(mask, H)
    expected = appearance_distance(warp_image(anchor, H), positive, 2, mask_in_positive).mean()
    assert torch.equal(model.backward_appearance(anchor, positive, H, mask), expected)
    assert float(expected) < 1e-6
    clutter = torch.where(mask_in_positive > 0, positive, torch.rand(1, 3, S, S, generator=g))
    assert torch.equal(model.backward_appearance(anchor, clutter, H, mask), expected)
    assert float(model.backward_appearance(anchor, clutter, H, None)) > 0.05


def test_selection_compares_anchors_per_unit_of_foreground() -> None:
    """The image-area distances favour an anchor showing less product; Eq. 3 divides by each anchor's own
    foreground share first. Anchor 0: 0.2 off on 1 of 16 pixels (0.0125 over the image, 0.2 per foreground
    pixel); anchor 1: 0.1 off everywhere (0.1 either way). An empty anchor is never chosen."""
    warped = torch.full((1, 3, 4, 4), 0.5)
    anchors = torch.zeros(1, 3, 3, 4, 4)
    anchors[0, 0, :, :1, :1] = 0.3
    anchors[0, 1] = 0.4
    masks = (anchors.amax(dim=2, keepdim=True) > 0).float()   # anchor 2: empty mask, distance 0
    distances = anchor_distances(anchors, warped, 1, masks)
    assert torch.allclose(distances, torch.tensor([[0.2 / 16, 0.1, 0.0]]))
    loss, selected = MultiAnchorAppearanceLoss()(anchors, warped, masks)
    assert selected.tolist() == [1] and math.isclose(float(loss), 0.1, rel_tol=1e-6)
    assert select_anchors(distances, masks).tolist() == [1]


def test_backward_term_gradient_stays_bounded_as_the_warped_mask_shrinks() -> None:
    """Regression: the backward term's mask is the anchor's foreground moved by the predicted homography. The
    former normaliser (that moved mask's mean) kept the term's value as the prediction shrank the footprint
    (nothing paid for losing the product) while its gradient grew as 1 / area^2: training drove |det H| to
    0 and the step blew up (NaN at lam 10). Now the value shrinks with the footprint and the gradient
    with respect to the scale stays within that of an unshrunk pose."""
    S = 32
    model, anchor, mask, g = masked_model_and_anchor(S, 3, (8, 24, 6, 26), seed=3)
    positive = torch.rand(1, 3, S, S, generator=g)
    centre = (S - 1) / 2

    def term(scale: float) -> tuple[float, float]:
        s = torch.tensor(scale, requires_grad=True)
        one, zero = torch.ones(()), torch.zeros(())
        # query_H_anchor: the anchor scaled by s about the image centre
        H = torch.stack([torch.stack([s, zero, centre * (1 - s)]), torch.stack([zero, s, centre * (1 - s)]),
                         torch.stack([zero, zero, one])])[None]
        value = model.backward_appearance(anchor, positive, H, mask)
        value.backward()
        return float(value.detach()), float(s.grad.abs())

    value_full, grad_full = term(1.0)
    for scale in (0.3, 0.1, 0.04):
        value, grad = term(scale)
        assert math.isfinite(grad) and grad <= 2 * grad_full, (scale, grad, grad_full)
        assert value < value_full * 3 * scale, (scale, value, value_full)
