"""Warps: identity, hand-computed shifts, the cached grid, kornia agreement, checks, gradcheck."""

from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck

from matl.geometry import (
    centre_rotation,
    normalised_grid,
    sample_by_normalised,
    sample_by_normalised_kornia,
    warp_image,
)
from tests.geometry.test_homography import SIZE, textured


def shift_norm(dx_px: float, size: tuple[int, int], batch: int = 1) -> torch.Tensor:
    """The normalised sampling homography that reads ``dx_px`` pixels to the right."""
    H = torch.eye(3).repeat(batch, 1, 1)
    H[:, 0, 2] = 2.0 * dx_px / (size[1] - 1)
    return H


def test_grid_is_cached_linspace() -> None:
    grid = normalised_grid(3, 4)
    assert grid.shape == (3, 12) and normalised_grid(3, 4) is grid
    assert torch.equal(grid[0, :4], torch.linspace(-1, 1, 4)) and torch.equal(grid[1, ::4], torch.linspace(-1, 1, 3))
    assert torch.equal(grid[2], torch.ones(12))
    assert normalised_grid(3, 4, dtype=torch.float64).dtype == torch.float64


def test_identity_sampling_is_identity() -> None:
    img = textured()
    eye = torch.eye(3)[None]
    assert torch.allclose(sample_by_normalised(img, eye), img, atol=1e-6)
    assert torch.allclose(sample_by_normalised_kornia(img, eye), img, atol=1e-5)
    assert torch.allclose(warp_image(img, eye), img, atol=1e-5)


def test_one_pixel_shift_hand_computed() -> None:
    img = torch.arange(2 * 5 * 6, dtype=torch.float32).reshape(1, 2, 5, 6)
    out = sample_by_normalised(img, shift_norm(1.0, (5, 6)))
    assert torch.allclose(out[..., :5], img[..., 1:], atol=1e-4)        # out(x) = img(x + 1)
    assert torch.equal(out[..., 5], torch.zeros(1, 2, 5))               # outside: zeros
    # the pixel-frame warp moves content the other way: out(x) = img(inv(dst_H_src) x) = img(x - 1)
    forward = torch.tensor([[[1.0, 0, 1.0], [0, 1.0, 0], [0, 0, 1.0]]])
    out = warp_image(img, forward)
    assert torch.allclose(out[..., 1:], img[..., :5], atol=1e-4)
    assert torch.allclose(out[..., 0], torch.zeros(1, 2, 5), atol=1e-4)


def test_point_at_infinity_is_left_undivided() -> None:
    # the row z = 0 at the centre column: x_norm = 0 maps to z = 0 (left undivided: u = 0, v = v)
    img = torch.rand(1, 1, 5, 5)
    H = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0], [1.0, 0, 0]]])
    out = sample_by_normalised(img, H)
    assert torch.isfinite(out).all()
    assert torch.allclose(out[0, 0, :, 2], img[0, 0, :, 2], atol=1e-6)


def test_package_sampler_equals_kornia_up_to_rounding() -> None:
    g = torch.Generator().manual_seed(2)
    images = torch.rand(4, 3, 24, 24, generator=g)
    H = torch.eye(3) + 0.15 * torch.randn(4, 3, 3, generator=g)
    H[1] *= 0.5  # a matrix scaled away from 1: the same warp (kornia rescales it first)
    assert torch.allclose(sample_by_normalised(images, H), sample_by_normalised_kornia(images, H), atol=1e-5)
    wide = torch.rand(2, 3, 20, 36, generator=g)  # a non-square image
    assert torch.allclose(sample_by_normalised(wide, H[:2]), sample_by_normalised_kornia(wide, H[:2]), atol=1e-5)
    # an explicit grid (a traced module's buffer) is the cached one
    grid = normalised_grid(24, 24).clone()
    assert torch.equal(sample_by_normalised(images, H, grid), sample_by_normalised(images, H))


def test_pixel_warp_is_the_normalised_sampling_by_its_inverse() -> None:
    img = textured(border=10)
    H = centre_rotation(torch.tensor([20.0]), SIZE) @ torch.tensor([[1.05, 0, -1.0], [0, 1.0, 2.0], [0, 0, 1.0]])
    norm = torch.tensor([[2.0 / (SIZE[1] - 1), 0, -1.0], [0, 2.0 / (SIZE[0] - 1), -1.0], [0, 0, 1.0]])
    src_H_dst_norm = norm @ torch.linalg.inv(H) @ torch.linalg.inv(norm)
    assert torch.allclose(warp_image(img, H), sample_by_normalised(img, src_H_dst_norm), atol=1e-4)


def test_bad_shapes_are_one_line_errors() -> None:
    img = torch.rand(2, 3, 8, 8)
    with pytest.raises(ValueError, match=r"images must be a \(B, C, H, W\)"):
        sample_by_normalised(img[0], torch.eye(3)[None])
    with pytest.raises(ValueError, match=r"must be \(2, 3, 3\), one per image"):
        sample_by_normalised(img, torch.eye(3)[None])
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        sample_by_normalised(img, torch.eye(4).expand(2, 4, 4))
    with pytest.raises(ValueError, match=r"grid must be \(3, 64\)"):
        sample_by_normalised(img, torch.eye(3).expand(2, 3, 3), normalised_grid(4, 4))
    with pytest.raises(ValueError, match="dst_H_src"):
        warp_image(img, torch.eye(2)[None])


def test_sampler_gradcheck_float64() -> None:
    g = torch.Generator().manual_seed(5)
    img = textured((8, 8), border=2).double().requires_grad_(True)
    H = (torch.eye(3, dtype=torch.float64) + 0.01 * torch.randn(3, 3, dtype=torch.float64, generator=g))
    H = H[None].requires_grad_(True)
    assert gradcheck(lambda i, h: sample_by_normalised(i, h), (img, H), eps=1e-6, atol=1e-4)
    assert gradcheck(lambda h: sample_by_normalised_kornia(img.detach(), h), (H,), eps=1e-6, atol=1e-4)
