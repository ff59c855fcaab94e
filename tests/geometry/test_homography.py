"""Homographies: round trips, composition, conventions, the degeneracy rule (warps: test_warp.py)."""

from __future__ import annotations

import math

import torch
from kornia.geometry.conversions import denormalize_homography

from matl.geometry import (
    HomographySampler,
    anchor_H_canon,
    centre_rotation,
    compose_query_H_canon,
    corner_error_px,
    degenerate_homographies,
    degenerate_matrix,
    frobenius_pose_error,
    guard_homographies,
    normalisation_matrices,
    normalised_to_pixel,
    pixel_to_normalised,
    rescale_homography,
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


def test_normalised_to_pixel_is_kornias_arithmetic_bit_for_bit() -> None:
    g = torch.Generator().manual_seed(6)
    for size in ((32, 32), (100, 100), (64, 64), (20, 36), (1, 5)):
        for dtype in (torch.float32, torch.float64):
            H = (torch.eye(3) + 0.1 * torch.randn(5, 3, 3, generator=g)).to(dtype).requires_grad_(True)
            ref = denormalize_homography(H, size, size)
            ref = ref / ref[:, 2:3, 2:3]
            out = normalised_to_pixel(H, size)
            assert torch.equal(out, ref), (size, dtype)
            weights = torch.randn(5, 3, 3, generator=g).to(dtype)
            grad_out, = torch.autograd.grad((out * weights).sum(), H)
            grad_ref, = torch.autograd.grad((ref * weights).sum(), H)
            assert torch.equal(grad_out, grad_ref)
    pixel_H_norm, norm_H_pixel = normalisation_matrices((5, 9))
    assert normalisation_matrices((5, 9))[0] is pixel_H_norm  # cached
    expected = torch.tensor([[[0.25, 0.0, -1.0], [0.0, 0.5, -1.0], [0.0, 0.0, 1.0]]])
    assert torch.equal(norm_H_pixel, expected) and torch.allclose(pixel_H_norm @ norm_H_pixel, torch.eye(3))
    # no batch dimension, and matrices passed in (a traced module's buffers)
    H = torch.eye(3) * 2.0
    assert torch.equal(normalised_to_pixel(H, (5, 9), (pixel_H_norm, norm_H_pixel)), torch.eye(3))


def test_degeneracy_rule_hand_computed() -> None:
    H = torch.stack([
        torch.eye(3),                                  # condition 1
        torch.diag(torch.tensor([1.0, 1e-4, 1.0])),    # condition exactly 1e4: degenerate (at least the limit)
        torch.diag(torch.tensor([1.0, 2e-4, 1.0])),    # 5e3: kept
        torch.zeros(3, 3),                             # zero matrix
        torch.full((3, 3), float("nan")),              # non-finite
        torch.tensor([[1.0, float("inf"), 0], [0, 1, 0], [0, 0, 1]]),
    ])
    assert degenerate_homographies(H, 1e4).tolist() == [False, True, False, True, True, True]
    assert degenerate_homographies(H.double(), 1e3).tolist() == [False, True, True, True, True, True]
    # the single-matrix NumPy rule (a query's pose in the onnxruntime path and the fast refiner) agrees
    assert [degenerate_matrix(h, 1e4) for h in H.double().numpy()] == [False, True, False, True, True, True]
    assert [degenerate_matrix(h, 1e3) for h in H.double().numpy()] == [False, True, True, True, True, True]


def test_guard_replaces_degenerate_by_identity_and_keeps_the_gradient_of_the_rest() -> None:
    H = torch.stack([torch.full((3, 3), float("nan")), torch.zeros(3, 3), torch.eye(3) * 1.1]).requires_grad_(True)
    out, bad = guard_homographies(H, 1e4)
    assert bad.tolist() == [True, True, False]
    assert torch.equal(out[:2], torch.eye(3).expand(2, 3, 3)) and torch.equal(out[2], torch.eye(3) * 1.1)
    out.sum().backward()
    assert torch.equal(H.grad, torch.stack([torch.zeros(3, 3), torch.zeros(3, 3), torch.ones(3, 3)]))
    # a given identity (a traced graph's constant) is the one used
    eye = torch.eye(3) * 1.0
    assert torch.equal(guard_homographies(H.detach(), 1e4, eye)[0][0], eye)


def test_compose_query_H_canon_small_cpu_batches_equal_the_torch_products() -> None:
    """A few float64 CPU queries take a NumPy shortcut: the same products and scaling as the torch path (any
    batch, gradients), a matrix with H[2, 2] ~ 0 left unscaled by both."""
    g = torch.Generator().manual_seed(3)
    a = torch.eye(3, dtype=torch.float64) + 0.1 * torch.randn(5, 3, 3, generator=g, dtype=torch.float64)
    b = torch.eye(3, dtype=torch.float64) + 0.1 * torch.randn(5, 3, 3, generator=g, dtype=torch.float64)
    b[2] = torch.eye(3, dtype=torch.float64)
    a[2, 2, :] = torch.tensor([0.1, 0.2, 0.0], dtype=torch.float64)  # (a @ b)[2, 2] = 0: not scaled
    fast = compose_query_H_canon(a, b)
    reference = compose_query_H_canon(a.requires_grad_(True), b).detach()  # with a gradient: the torch path
    assert torch.allclose(fast, reference, rtol=1e-12, atol=1e-12) and fast.dtype == torch.float64
    assert torch.allclose(fast[2], a[2].detach() @ b[2])
    assert torch.allclose(fast[[0, 1, 3, 4], 2, 2], torch.ones(4, dtype=torch.float64))
