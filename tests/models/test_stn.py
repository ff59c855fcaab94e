"""The spatial transformer: identity start, the regress-compose-guard loop, the degeneracy guard."""

from __future__ import annotations

import torch
from torch import nn

from matl.geometry import normalised_to_pixel, sample_by_normalised_kornia
from matl.models.stn import HomographyRegressor, SpatialTransformer, regress_homography

S = 32


class ConstantRegressor(nn.Module):
    """Returns given normalised homographies whatever the images."""

    def __init__(self, H: torch.Tensor) -> None:
        super().__init__()
        self.H = H

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.H[: len(images)]


def test_stn_starts_at_identity() -> None:
    stn = SpatialTransformer(HomographyRegressor(image_size=S), image_size=S, iterations=2)
    images = torch.rand(2, 3, S, S)
    out = stn(images)
    assert torch.allclose(out.query_H_anchor, torch.eye(3).expand(2, 3, 3), atol=1e-6)
    assert torch.allclose(out.warped, images, atol=1e-5)
    assert not out.degenerate.any()


def test_loop_composes_each_regression_on_the_warp_so_far() -> None:
    A = torch.tensor([[[1.0, 0.1, 0.2], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]]).repeat(2, 1, 1)
    A[1, 1, 2] = -0.3
    images = torch.rand(2, 3, 8, 8)
    seen: list[torch.Tensor] = []

    def warp(x: torch.Tensor, H: torch.Tensor) -> torch.Tensor:
        assert x is images
        seen.append(H.clone())
        return x

    H, bad = regress_homography(ConstantRegressor(A), images, 3, 1e4, warp)
    assert torch.allclose(H, A @ A @ A) and not bad.any()
    assert len(seen) == 2 and torch.equal(seen[0], A) and torch.allclose(seen[1], A @ A)
    # one regression: no warp at all
    seen.clear()
    H, _ = regress_homography(ConstantRegressor(A), images, 1, 1e4, warp)
    assert torch.equal(H, A) and not seen


def test_degenerate_outputs_are_replaced_and_flagged() -> None:
    bad = torch.stack([torch.full((3, 3), float("nan")), torch.zeros(3, 3), torch.eye(3)])
    stn = SpatialTransformer(ConstantRegressor(bad), image_size=S)  # type: ignore[arg-type]
    images = torch.rand(3, 3, S, S)
    for out in (stn(images), stn.infer(images)):
        assert out.degenerate.tolist() == [True, True, False]
        assert torch.equal(out.query_H_anchor, torch.eye(3).expand(3, 3, 3))
        assert torch.isfinite(out.warped).all()


def test_forward_is_the_loop_then_the_kornia_warp() -> None:
    torch.manual_seed(0)
    stn = SpatialTransformer(HomographyRegressor(image_size=S), image_size=S, iterations=2)
    nn.init.normal_(stn.regressor.fc2.bias, std=0.05)
    images = torch.rand(2, 3, S, S)
    out = stn(images)
    H1 = stn.regressor(images)
    H = H1 @ stn.regressor(sample_by_normalised_kornia(images, H1))
    assert torch.equal(out.warped, sample_by_normalised_kornia(images, H))
    assert torch.equal(out.query_H_anchor, normalised_to_pixel(H, (S, S)))
