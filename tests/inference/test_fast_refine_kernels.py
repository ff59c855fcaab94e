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


def _weighted_reference(warped: np.ndarray, visible: np.ndarray, image: np.ndarray, fg: np.ndarray,
                        inner: np.ndarray, region: np.ndarray | None
                        ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """The weighted objective written out: the print ``x = warped / visible`` on the inner foreground (where visible),
    gain and bias the least squares of ``x`` by ``gain * image + bias`` over ``fg * u``, the residuals' weights
    ``u = 1 - inner + inner * visible`` and the hidden pixels ``inner * (1 - visible)`` (both times ``region``)."""
    w, v, a, f, k = (x.astype(np.float64) for x in (warped, visible, image, fg, inner))
    x = np.where((k > 0) & (v >= 1e-3), w / np.maximum(v, 1e-3), w)
    u, hidden = 1.0 - k + k * v, k * (1.0 - v)
    c = f * u
    design = np.stack([a.ravel(), np.ones(a.size)], 1) * np.sqrt(c.ravel())[:, None]
    gain, bias = np.linalg.lstsq(design, x.ravel() * np.sqrt(c.ravel()), rcond=None)[0]
    if region is not None:
        u, hidden = u * region, hidden * region
    return gain, x - gain * a - bias * f, u, hidden


@pytest.mark.parametrize("loss", kernels.LOSS_CODES)
@pytest.mark.parametrize("with_region", [False, True])
def test_weighted_objective_is_the_visible_fit_and_the_weighted_loss(loss: str, with_region: bool) -> None:
    warped, image, fg, region = _images()
    visible = RNG.random((H_, W_), dtype=np.float32)
    visible[RNG.random((H_, W_)) > 0.7] = 0.0  # hidden pixels
    inner = fg * (RNG.random((H_, W_)) > 0.3).astype(np.float32)  # the foreground less its outline band
    gain, r, u, hidden = _weighted_reference(warped, visible, image, fg, inner, region if with_region else None)
    delta = 0.05
    total, out, fitted, weight = kernels.objective_weighted(warped, visible, image, fg, inner, region, with_region,
                                                            kernels.LOSS_CODES.index(loss), delta)
    assert fitted == pytest.approx(gain, rel=1e-5)
    np.testing.assert_allclose(out, r, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(weight, u, atol=1e-6)
    # a hidden pixel costs rho(delta), whatever its residual
    expected = (u * _rho(r, loss, delta)).sum() + hidden.sum() * float(_rho(np.array(delta), loss, delta))
    assert total == pytest.approx(expected, rel=1e-4)
    # everything visible: the unweighted objective, whose loss is a plain sum
    ones = np.ones_like(visible)
    count = fg.astype(np.float64).sum()
    mean = (image * fg).sum() / count
    var = (((image - mean) ** 2) * fg).sum()
    plain = kernels.objective(warped, image, fg, region, with_region, mean, 1.0 / var, 1.0 / count,
                              kernels.LOSS_CODES.index(loss), delta)
    weighted = kernels.objective_weighted(warped, ones, image, fg, inner, region, with_region,
                                          kernels.LOSS_CODES.index(loss), delta)
    assert weighted[0] == pytest.approx(plain[0], rel=1e-5) and weighted[2] == pytest.approx(plain[2], rel=1e-5)
    # nothing of the foreground visible: no fit, an infinite loss (never accepted)
    assert kernels.objective_weighted(warped, np.zeros_like(visible), image, fg, fg, region, False, 1,
                                      delta)[0] == np.inf
    # no inner foreground (a band as wide as the plane): the visibility changes nothing
    none = kernels.objective_weighted(warped, visible, image, fg, np.zeros_like(fg), region, with_region,
                                      kernels.LOSS_CODES.index(loss), delta)
    assert none[0] == pytest.approx(plain[0], rel=1e-5) and none[2] == pytest.approx(plain[2], rel=1e-5)


@pytest.mark.parametrize("loss", kernels.LOSS_CODES)
def test_weighted_normal_equations_multiply_the_pixel_weight_into_the_robust_one(loss: str) -> None:
    n = 40
    r = RNG.standard_normal((H_, W_)).astype(np.float32)
    u = RNG.random((H_, W_)).astype(np.float32)
    u[RNG.random((H_, W_)) > 0.6] = 1.0  # most pixels fully weighted: the Hessian correction path
    index = RNG.choice(H_ * W_, n, replace=False).astype(np.int32)
    sdT = RNG.standard_normal((8, n)).astype(np.float32)
    sd = sdT.astype(np.float64)
    delta, gain = 0.8, 1.3
    rs = r.ravel()[index].astype(np.float64)
    a = np.abs(rs)
    robust = {"l2": np.ones(n), "huber": np.minimum(1.0, delta / a), "cauchy": 1.0 / (1.0 + (rs / delta) ** 2)}[loss]
    weights = robust * u.ravel()[index]
    A, b = kernels.normal_equations_weighted(r, u, index, sdT, sd @ sd.T, gain, kernels.LOSS_CODES.index(loss), delta)
    np.testing.assert_allclose(A, (sd * weights) @ sd.T, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(b, sd @ (weights * rs) / gain, rtol=1e-9, atol=1e-9)
    # all weights 1: the unweighted equations
    ones = np.ones_like(u)
    plain = kernels.normal_equations(r, index, sdT, sd @ sd.T, gain, kernels.LOSS_CODES.index(loss), delta)
    same = kernels.normal_equations_weighted(r, ones, index, sdT, sd @ sd.T, gain, kernels.LOSS_CODES.index(loss),
                                             delta)
    np.testing.assert_allclose(same[0], plain[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(same[1], plain[1], rtol=1e-12, atol=1e-12)


def test_weighted_gradient_is_the_loss_derivative_in_float64() -> None:
    """``-gain^2 b`` is the derivative of the weighted loss along the steepest-descent images (gain and bias held):
    with ``r(p) = r - gain * sd^T p``, ``d/dp sum u rho(r(p)) = -gain sum u rho'(r) sd`` and ``b = sum u w r sd / gain``
    with ``w r = rho'(r)``; checked by central differences in float64."""
    n = H_ * W_
    r = (0.3 * RNG.standard_normal((H_, W_))).astype(np.float32)
    u = RNG.random((H_, W_)).astype(np.float32)
    index = np.arange(n, dtype=np.int32)
    sdT = RNG.standard_normal((8, n)).astype(np.float32)
    gain, delta = 0.9, 0.25
    for code, loss in enumerate(kernels.LOSS_CODES):
        _, b = kernels.normal_equations_weighted(r, u, index, sdT, np.zeros((8, 8)), gain, code, delta)

        def value(p: np.ndarray, code: int = code, loss: str = loss) -> float:
            rp = r.ravel().astype(np.float64) - gain * (sdT.astype(np.float64).T @ p)
            return float((u.ravel() * _rho(rp, loss, delta)).sum())

        step = 1e-6
        numeric = np.array([(value(step * e) - value(-step * e)) / (2 * step) for e in np.eye(8)])
        np.testing.assert_allclose(numeric, -gain * gain * b, rtol=1e-5, atol=1e-7)


def test_evaluate_weighted_is_the_weighted_objective_and_its_normal_equations() -> None:
    warped, image, fg, region = _images()
    visible = RNG.random((H_, W_), dtype=np.float32)
    n = 30
    index = RNG.choice(H_ * W_, n, replace=False).astype(np.int32)
    sdT = RNG.standard_normal((8, n)).astype(np.float32)
    hessian = sdT.astype(np.float64) @ sdT.T.astype(np.float64)
    for code in range(len(kernels.LOSS_CODES)):
        total, r, gain, weight = kernels.objective_weighted(warped, visible, image, fg, fg, region, True, code, 0.05)
        A, b = kernels.normal_equations_weighted(r, weight, index, sdT, hessian, gain, code, 0.05)
        fused = kernels.evaluate_weighted(warped, visible, image, fg, fg, region, True, index, sdT, hessian, code,
                                          0.05)
        assert fused[0] == total and fused[1] == gain
        assert np.array_equal(fused[2], A) and np.array_equal(fused[3], b)
