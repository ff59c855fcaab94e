"""The compiled inner loops of the fast refiner (matl.inference.fast_refine_kernels) against NumPy written out."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from matl.inference import fast_refine_kernels as kernels

RNG = np.random.default_rng(0)
H_, W_ = 7, 9


def _images() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    image = RNG.random((H_, W_), dtype=np.float32)
    fg = (RNG.random((H_, W_)) > 0.3).astype(np.float32)
    image *= fg
    warped = (0.8 * image + 0.1 * fg + 0.05 * RNG.standard_normal((H_, W_))).astype(np.float32)
    region = (RNG.random((H_, W_)) > 0.2).astype(np.float32)
    return warped, image, fg, region


def _rho(r: np.ndarray, loss: str, d: float) -> np.ndarray:
    a = np.abs(r)
    if loss == "l2":
        return 0.5 * r * r
    if loss == "huber":
        return np.where(a <= d, 0.5 * r * r, d * (a - 0.5 * d))
    return 0.5 * d * d * np.log1p((r / d) ** 2)


@pytest.mark.parametrize("loss", kernels.LOSS_CODES)
@pytest.mark.parametrize("with_region", [False, True])
def test_objective_is_the_gain_bias_fit_and_the_robust_loss(loss: str, with_region: bool) -> None:
    warped, image, fg, region = _images()
    w, a, f = warped.astype(np.float64), image.astype(np.float64), fg.astype(np.float64)
    count = f.sum()
    mean = (a * f).sum() / count
    var = (((a - mean) ** 2) * f).sum()
    gain = ((a * w).sum() - mean * (f * w).sum()) / var  # least squares of w by gain * a + bias over f
    bias = (f * w).sum() / count - gain * mean
    r = (w - gain * a - bias * f) * (region if with_region else 1.0)
    delta = 0.05
    total, out, fitted = kernels.objective(warped, image, fg, region, with_region, mean, 1.0 / var, 1.0 / count,
                                           kernels.LOSS_CODES.index(loss), delta)
    assert fitted == pytest.approx(gain, rel=1e-6)
    np.testing.assert_allclose(out, r, atol=1e-6)
    assert total == pytest.approx(_rho(r, loss, delta).sum(), rel=1e-5)
    # the fit is exact for an affine change of the anchor: no residual
    exact = (1.7 * image + 0.2 * fg).astype(np.float32)
    assert kernels.objective(exact, image, fg, region, False, mean, 1.0 / var, 1.0 / count, 0, delta)[0] < 1e-10


def test_objective_of_a_non_finite_image_is_infinite() -> None:
    warped, image, fg, region = _images()
    warped[0, 0] = np.nan
    assert kernels.objective(warped, image, fg, region, False, 0.5, 1.0, 0.1, 1, 0.1)[0] == np.inf


@pytest.mark.parametrize("loss", kernels.LOSS_CODES)
def test_normal_equations_are_the_weighted_least_squares_ones(loss: str) -> None:
    n = 40
    r = RNG.standard_normal((H_, W_)).astype(np.float32)
    index = RNG.choice(H_ * W_, n, replace=False).astype(np.int32)
    sdT = RNG.standard_normal((8, n)).astype(np.float32)
    sd = sdT.astype(np.float64)
    hessian = sd @ sd.T
    delta, gain = 0.8, 1.3
    rs = r.ravel()[index].astype(np.float64)
    a = np.abs(rs)
    weights = {"l2": np.ones(n), "huber": np.minimum(1.0, delta / a), "cauchy": 1.0 / (1.0 + (rs / delta) ** 2)}[loss]
    A, b = kernels.normal_equations(r, index, sdT, hessian, gain, kernels.LOSS_CODES.index(loss), delta)
    np.testing.assert_allclose(A, (sd * weights) @ sd.T, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(b, sd @ (weights * rs) / gain, rtol=1e-9, atol=1e-9)
    assert np.array_equal(A, A.T)


def test_evaluate_is_the_objective_and_its_normal_equations() -> None:
    warped, image, fg, region = _images()
    n = 30
    index = RNG.choice(H_ * W_, n, replace=False).astype(np.int32)
    sdT = RNG.standard_normal((8, n)).astype(np.float32)
    hessian = sdT.astype(np.float64) @ sdT.T.astype(np.float64)
    args = (warped, image, fg, region, True, 0.3, 2.0, 0.05)
    for code in range(len(kernels.LOSS_CODES)):
        total, r, gain = kernels.objective(*args, code, 0.05)
        A, b = kernels.normal_equations(r, index, sdT, hessian, gain, code, 0.05)
        fused = kernels.evaluate(*args, index, sdT, hessian, code, 0.05)
        assert fused[0] == total and fused[1] == gain
        assert np.array_equal(fused[2], A) and np.array_equal(fused[3], b)


def test_lm_step_solves_the_damped_system_and_composes_the_inverse_update() -> None:
    M = RNG.standard_normal((8, 8))
    A = M @ M.T + 8 * np.eye(8)
    b = 0.01 * RNG.standard_normal(8)
    H = np.array([[1.0, 0.1, 0.2], [0.05, 0.9, -0.1], [0.01, 0.02, 1.0]])
    corner_J = RNG.standard_normal((8, 8))
    lam = 0.1
    pixel_H_norm = np.array([[2.0, 0.0, 3.0], [0.0, 2.0, 3.0], [0.0, 0.0, 1.0]])
    norm_H_pixel = np.linalg.inv(pixel_H_norm)
    ok, candidate, M, step = kernels.lm_step(A, b, lam, H, corner_J, pixel_H_norm, norm_H_pixel)
    dp = np.linalg.solve(A + lam * np.diag(np.diag(A)) + 1e-9 * np.eye(8), b)
    update = np.eye(3) + np.append(dp, 0.0).reshape(3, 3)
    expected = H @ np.linalg.inv(update)
    assert ok
    np.testing.assert_allclose(candidate, expected / expected[2, 2], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(M, pixel_H_norm @ candidate @ norm_H_pixel, rtol=1e-12)
    motion = (dp @ corner_J).reshape(4, 2)
    assert step == pytest.approx(np.linalg.norm(motion, axis=1).max(), rel=1e-10)
    # a zero step is the identity update; a singular system falls back to the pseudo-inverse
    eye = np.eye(3)
    assert np.allclose(kernels.lm_step(A, np.zeros(8), lam, H, corner_J, eye, eye)[1], H / H[2, 2])
    singular = np.zeros((8, 8))
    singular[0, 0] = 1.0
    ok, candidate, _, _ = kernels.lm_step(singular, np.eye(8)[0], 0.0, eye, corner_J, eye, eye)
    assert ok and np.isfinite(candidate).all()
    assert not kernels.lm_step(A, np.full(8, np.nan), lam, H, corner_J, eye, eye)[0]


def test_luminance_and_foreground_std_match_opencv() -> None:
    rgb = RNG.random((3, H_, W_), dtype=np.float32)
    rgb[:, :2] = 0.0  # a black band: background
    weights = np.array([0.299, 0.587, 0.114], dtype=np.float32)
    gray, std = kernels.luminance(rgb, weights, 1e-3)
    expected = rgb[0] * weights[0] + rgb[1] * weights[1] + rgb[2] * weights[2]
    np.testing.assert_allclose(gray, expected, rtol=1e-6)
    assert std == pytest.approx(float(cv2.meanStdDev(expected, mask=(expected > 1e-3).view(np.uint8))[1][0, 0]),
                                rel=1e-5)
    one, std_one = kernels.luminance(rgb[:1], weights, 1e-3)
    assert np.array_equal(one, rgb[0]) and std_one > 0
    assert kernels.luminance(np.zeros((1, 3, 3), np.float32), weights, 1e-3)[1] == 0.0


def test_count_above_counts_bright_pixels_inside_the_mask_as_opencv() -> None:
    image = RNG.random((H_, W_), dtype=np.float32)
    image[3, 4] = np.nan  # not brighter than anything
    mask = (RNG.random((H_, W_)) > 0.5).astype(np.uint8) * 3  # any non-zero value is inside
    expected = cv2.countNonZero(cv2.bitwise_and((image > 0.4).view(np.uint8), (mask > 0).view(np.uint8)))
    assert kernels.count_above(image, mask, 0.4) == expected > 0
    assert kernels.count_above(image, np.zeros_like(mask), 0.0) == 0
