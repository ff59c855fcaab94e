"""Geometry: identity, round trips, composition, conventions, gradcheck."""

from __future__ import annotations

import math

import torch
from torch.autograd import gradcheck

from matl.geometry import (
    HomographySampler,
    anchor_H_canon,
    centre_rotation,
    compose_query_H_canon,
    corner_error_px,
    frobenius_pose_error,
    normalised_to_pixel,
    pixel_to_normalised,
    rescale_homography,
    sample_by_normalised,
    transfer_points,
    warp_image,
)

SIZE = (40, 40)


def textured(size: tuple[int, int] = SIZE, border: int = 8, seed: int = 0) -> torch.Tensor:
    """Smooth random texture (bilinear resampling would wash out pixel noise) on a black border."""
    g = torch.Generator().manual_seed(seed)
    inner = (size[0] - 2 * border, size[1] - 2 * border)
    coarse = torch.rand(1, 3, max(inner[0] // 4, 2), max(inner[1] // 4, 2), generator=g)
    img = torch.zeros(1, 3, *size)
    img[..., border:-border, border:-border] = torch.nn.functional.interpolate(coarse, inner, mode="bilinear",
                                                                               align_corners=True)
    return img


def test_identity_warp_is_identity() -> None:
    img = textured()
    out = warp_image(img, torch.eye(3)[None])
    assert torch.allclose(out, img, atol=1e-5)
    out2 = sample_by_normalised(img, torch.eye(3)[None])
    assert torch.allclose(out2, img, atol=1e-5)


def test_warp_then_inverse_returns_image_inside_frame() -> None:
    img = textured(border=12)
    H = centre_rotation(torch.tensor([30.0]), SIZE) @ torch.tensor([[1.1, 0, -1.0], [0, 1.1, 2.0], [0, 0, 1.0]])
    back = warp_image(warp_image(img, H), torch.linalg.inv(H))
    inner = (slice(None), slice(None), slice(14, -14), slice(14, -14))
    # two bilinear resamplings blur a little; the content must come back in place
    assert (back[inner] - img[inner]).abs().mean() < 0.03
    assert (back[inner] - img[inner]).abs().mean() < 0.5 * (img[inner] - img[inner].mean()).abs().mean()


def test_rotation_convention_counter_clockwise_on_screen() -> None:
    img = torch.zeros(1, 3, *SIZE)
    img[..., 2:6, 15:25] = 1.0  # a bar at the top
    out = warp_image(img, centre_rotation(torch.tensor([90.0]), SIZE))
    ys, xs = torch.nonzero(out[0, 0] > 0.5, as_tuple=True)
    assert xs.max() < 10 and ys.min() >= 12 and ys.max() <= 27  # the top went to the left


def test_anchor_rotations() -> None:
    H = anchor_H_canon(4, SIZE, torch.float64)
    assert torch.allclose(H[0], torch.eye(3, dtype=torch.float64))
    assert torch.allclose(H[1] @ H[1] @ H[1] @ H[1], torch.eye(3, dtype=torch.float64), atol=1e-9)
    centre = torch.tensor([[[19.5, 19.5]]], dtype=torch.float64).expand(4, 1, 2)
    assert torch.allclose(transfer_points(H, centre), centre)


def test_pixel_normalised_round_trip() -> None:
    H = HomographySampler().sample(8, SIZE, torch.Generator().manual_seed(1))
    assert torch.allclose(normalised_to_pixel(pixel_to_normalised(H, SIZE), SIZE), H, atol=1e-9)
    # corner pixel centres map to +-1
    Hn = pixel_to_normalised(torch.eye(3, dtype=torch.float64)[None], SIZE)
    assert torch.allclose(Hn, torch.eye(3, dtype=torch.float64))


def test_pose_composition_matches_design_formula() -> None:
    g = torch.Generator().manual_seed(2)
    anchor_H_query = HomographySampler().sample(5, SIZE, g)
    anchor_k = anchor_H_canon(4, SIZE, torch.float64)[torch.tensor([0, 1, 2, 3, 1])]
    query_H_canon = compose_query_H_canon(torch.linalg.inv(anchor_H_query), anchor_k)
    expected = torch.linalg.inv(anchor_H_query) @ anchor_k
    expected = expected / expected[:, 2:3, 2:3]
    assert torch.allclose(query_H_canon, expected, atol=1e-9)
    assert torch.allclose(query_H_canon[:, 2, 2], torch.ones(5, dtype=torch.float64))


def test_errors_zero_for_equal_and_known_for_shift() -> None:
    H = HomographySampler().sample(3, SIZE, torch.Generator().manual_seed(3))
    assert torch.allclose(corner_error_px(H, H, SIZE), torch.zeros(3, dtype=torch.float64))
    shift = torch.tensor([[1.0, 0, 3.0], [0, 1.0, 4.0], [0, 0, 1.0]], dtype=torch.float64)[None]
    eye = torch.eye(3, dtype=torch.float64)[None]
    assert math.isclose(float(corner_error_px(shift, eye, SIZE)), 5.0)
    # a 3 px shift at 40 px is 2 * 3 / 39 in normalised units; H[2,2] = 1 leaves only that entry
    assert math.isclose(float(frobenius_pose_error(shift, eye, SIZE)), 2 * 5.0 / 39.0, rel_tol=1e-9)


def test_sampler_ranges_inside_and_deterministic() -> None:
    sampler = HomographySampler()
    footprint = torch.tensor([[12.0, 12.0], [27.0, 12.0], [27.0, 27.0], [12.0, 27.0]]).expand(64, 4, 2)
    a = sampler.sample(64, SIZE, torch.Generator().manual_seed(4), footprint)
    b = sampler.sample(64, SIZE, torch.Generator().manual_seed(4), footprint)
    assert torch.equal(a, b)
    mapped = transfer_points(a, footprint.double())
    assert mapped.min() >= -1e-6 and mapped.max() <= 39 + 1e-6
    assert torch.linalg.cond(pixel_to_normalised(a, SIZE)).max() < 10


def test_sampler_decomposition_pure_rotation() -> None:
    sampler = HomographySampler()
    params = torch.tensor([[0.0, 0.0, 90.0, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    assert torch.allclose(sampler.compose(params, SIZE), centre_rotation(torch.tensor([90.0], dtype=torch.float64),
                                                                          SIZE), atol=1e-9)


def test_rescale_homography_maps_corners() -> None:
    eye = torch.eye(3, dtype=torch.float64)
    H = rescale_homography(eye, (40, 40), (40, 40), (80, 60), (20, 30))
    pts = torch.tensor([[[0.0, 0.0], [59.0, 79.0]]], dtype=torch.float64)
    assert torch.allclose(transfer_points(H[None], pts), torch.tensor([[[0.0, 0.0], [29.0, 19.0]]],
                                                                      dtype=torch.float64))


def test_warp_gradcheck_float64() -> None:
    img = textured((8, 8), border=2).double()
    H = (torch.eye(3, dtype=torch.float64) + 0.01 * torch.randn(3, 3, dtype=torch.float64,
                                                              generator=torch.Generator().manual_seed(5)))
    H = H[None].requires_grad_(True)
    assert gradcheck(lambda h: sample_by_normalised(img, h), (H,), eps=1e-6, atol=1e-4)
