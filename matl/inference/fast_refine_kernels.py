"""Compiled inner loops of :class:`~matl.inference.fast_refine.FastRefiner` (numba, one pass over the pixels each).

A Gauss-Newton iteration of the fast refiner is a handful of small array operations (a gain / bias fit, the
residuals, a robust loss, the normal equations over the textured pixels, an 8 x 8 damped solve, the
compositional update); at 100 x 100 px each is a few microseconds of work but costs as much again to call
from Python. These functions do each group in one compiled pass; the warp itself stays in OpenCV
(``cv2.warpPerspective``: its vectorised bilinear sampling is several times faster than a scalar loop).

Every function is pure (arrays in, new arrays out) and works in float64 internally; ``loss_code`` is the
index of the robust loss in :data:`LOSS_CODES`. The ``*_weighted`` variants take the query's visibility warped into
the anchor frame (``visible``, in [0, 1]): a pixel of the anchor's foreground counts by how visible the query is
there (the gain / bias fit and the loss alike), a pixel beside the foreground counts fully (the outline).
``cache=True`` keeps the machine code beside this file, so only the first run of an installation compiles (about
a second per function); :func:`warm_up` compiles them up front (a refined recognizer calls it at enrolment, so no
query pays for it).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["LOSS_CODES", "count_above", "evaluate", "evaluate_weighted", "lm_step", "luminance", "normal_equations",
           "normal_equations_weighted", "objective", "objective_weighted", "warm_up"]

#: the robust losses in the order of ``loss_code``
LOSS_CODES = ("l2", "huber", "cauchy")

_JIT = {"cache": True, "nogil": True, "boundscheck": False, "error_model": "numpy"}  # x / 0: inf or NaN, no exception
#: reductions may be reordered (vectorised); NaN and infinity keep their meaning (the loss guard relies on them)
_REDUCE = {**_JIT, "fastmath": {"reassoc", "contract", "arcp", "nsz"}}


@njit(**_REDUCE)
def luminance(image: np.ndarray, weights: np.ndarray, level: float) -> tuple[np.ndarray, float]:
    """A query's luminance and the std of its foreground.

    Args:
        image: ``(C, h, w)`` float32, ``C`` 3 (weighted by ``weights`` ``(3,)``) or 1 (taken as is).
        level: a pixel brighter than this is foreground.
    Returns:
        ``(gray (h, w) float32, std)``: the population std of ``gray`` over its pixels above ``level`` (0 if none).
    """
    _, h, w = image.shape
    gray = np.empty((h, w), dtype=np.float32)
    flat = gray.ravel()
    count = 0.0
    total = 0.0
    if image.shape[0] == 1:
        flat[:] = image[0].ravel()
    else:
        r, g, b = image[0].ravel(), image[1].ravel(), image[2].ravel()
        w0, w1, w2 = weights[0], weights[1], weights[2]
        for i in range(h * w):
            flat[i] = w0 * r[i] + w1 * g[i] + w2 * b[i]
    for i in range(h * w):  # without branches (a mask's edge is not predictable): 0 or 1 times each term
        inside = np.float64(flat[i] > level)
        count += inside
        total += inside * flat[i]
    if count == 0.0:
        return gray, 0.0
    mean = total / count
    spread = 0.0
    for i in range(h * w):
        spread += np.float64(flat[i] > level) * (flat[i] - mean) ** 2
    return gray, math.sqrt(spread / count)


@njit(**_REDUCE)
def objective(warped: np.ndarray, image: np.ndarray, fg: np.ndarray, region: np.ndarray, has_region: bool,
              mean: float, inv_var: float, inv_count: float, loss_code: int, delta: float
              ) -> tuple[float, np.ndarray, float]:
    """Sum of the robust loss of the residuals at one pose, the residuals and the gain.

    ``r = (warped - gain * image - bias * fg) * region`` with ``gain`` / ``bias`` the least-squares fit of
    ``warped`` by ``image`` over ``fg`` (``mean``, ``1 / var`` and ``1 / count`` of ``image`` over ``fg`` given);
    the loss of a residual is ``r^2 / 2`` (l2), Huber's (``|r| <= delta``: ``r^2 / 2``, else
    ``delta (|r| - delta / 2)``) or Cauchy's (``delta^2 / 2 log(1 + (r / delta)^2)``).

    Args:
        warped, image, fg: ``(h, w)`` float32, the query warped into the anchor frame, the anchor's luminance and
            its foreground indicator.
        region: ``(h, w)`` float32 0/1 pixels of the loss when ``has_region`` (else unused).
    Returns:
        ``(loss sum, r (h, w) float32, gain)``; the sum is ``inf`` when not finite.
    """
    flat_w, flat_a, flat_f = warped.ravel(), image.ravel(), fg.ravel()
    s_fw = 0.0
    s_aw = 0.0
    for i in range(flat_w.shape[0]):
        v = np.float64(flat_w[i])
        s_fw += flat_f[i] * v
        s_aw += flat_a[i] * v
    gain = (s_aw - mean * s_fw) * inv_var
    bias = s_fw * inv_count - gain * mean
    g32, b32 = np.float32(gain), np.float32(bias)
    r = warped - g32 * image - b32 * fg
    if has_region:
        r *= region
    flat = r.ravel()
    total = 0.0
    if loss_code == 0:
        for i in range(flat.shape[0]):
            total += np.float64(flat[i]) * flat[i]
        total *= 0.5
    elif loss_code == 1:  # min(|r|, d) (|r| - min(|r|, d) / 2): r^2 / 2 inside, d (|r| - d / 2) outside
        for i in range(flat.shape[0]):
            a = abs(np.float64(flat[i]))
            m = min(a, delta)
            total += m * (a - 0.5 * m)
    else:
        for i in range(flat.shape[0]):
            total += math.log1p((flat[i] / delta) ** 2)
        total *= 0.5 * delta * delta
    if not math.isfinite(total):
        total = math.inf
    return total, r, gain


@njit(inline="always")
def _robust_weight(value: float, loss_code: int, delta: float) -> float:
    """The robust loss's weight of a residual ``value``: 1 (l2), ``min(1, delta / |r|)`` (Huber) or
    ``1 / (1 + (r / delta)^2)`` (Cauchy). Inlined (numba IR) into its callers, which compile it with their flags."""
    w = 1.0
    if loss_code == 1:
        a = abs(value)
        if a > delta:
            w = delta / a
    elif loss_code == 2:
        w = 1.0 / (1.0 + (value / delta) ** 2)
    return w


@njit(inline="always")
def _gradient(sdT: np.ndarray, weighted: np.ndarray, gain: float) -> np.ndarray:
    """``b (8,)`` float64, ``sum_j weighted_j sd_j / gain`` (``sdT`` ``(8, n)``, ``weighted`` ``(n,)``)."""
    n = weighted.shape[0]
    b = np.zeros(8)
    for k in range(8):
        row = sdT[k]
        acc = 0.0
        for j in range(n):
            acc += row[j] * weighted[j]
        b[k] = acc / gain
    return b


@njit(inline="always")
def _hessian(weights: np.ndarray, sdT: np.ndarray, hessian: np.ndarray, correct: bool) -> np.ndarray:
    """``A (8, 8)`` float64, ``sum_j weights_j sd_j sd_j^T``: with ``correct`` the unweighted ``hessian`` less
    ``(1 - weights_j) sd_j sd_j^T`` on the pixels whose weight is not 1 (few of them), else summed afresh."""
    n = weights.shape[0]
    if correct:
        A = hessian.astype(np.float64)
        for j in range(n):
            if weights[j] != 1.0:
                for k in range(8):
                    sk = np.float64(sdT[k, j]) * (weights[j] - 1.0)
                    for m in range(k + 1):
                        A[k, m] += sk * sdT[m, j]
    else:
        A = np.zeros((8, 8))
        for k in range(8):
            for m in range(k + 1):
                acc = 0.0
                for j in range(n):
                    acc += np.float64(sdT[k, j]) * sdT[m, j] * weights[j]
                A[k, m] = acc
    for k in range(8):  # the lower triangle was accumulated
        for m in range(k):
            A[m, k] = A[k, m]
    return A


@njit(**_REDUCE)
def normal_equations(r: np.ndarray, index: np.ndarray, sdT: np.ndarray, hessian: np.ndarray, gain: float,
                     loss_code: int, delta: float) -> tuple[np.ndarray, np.ndarray]:
    """``(A (8, 8), b (8,))`` float64 of the iteratively re-weighted Gauss-Newton step ``A dp = b``.

    ``A = sum_j w_j sd_j sd_j^T`` and ``b = sum_j w_j r_j sd_j / gain`` over the textured pixels ``index``
    (``(n,)`` flat indices into ``r`` ``(h, w)``; ``sdT`` ``(8, n)`` their steepest-descent images), ``w`` the robust
    loss's weight (``l2``: 1; Huber: ``min(1, delta / |r|)``; Cauchy: ``1 / (1 + (r / delta)^2)``). ``hessian`` is the
    unweighted ``sd^T sd``: l2 returns it, Huber corrects it on the pixels beyond ``delta`` only.
    """
    flat = r.ravel()
    n = index.shape[0]
    weighted = np.empty(n)  # w_j r_j
    weights = np.empty(n)
    for j in range(n):
        value = np.float64(flat[index[j]])
        weights[j] = _robust_weight(value, loss_code, delta)
        weighted[j] = value * weights[j]
    b = _gradient(sdT, weighted, gain)
    if loss_code == 0:
        return hessian.astype(np.float64), b
    # Huber: the Hessian less (1 - w) of each pixel beyond delta (few of them)
    return _hessian(weights, sdT, hessian, loss_code == 1), b


@njit(**_JIT)
def evaluate(warped: np.ndarray, image: np.ndarray, fg: np.ndarray, region: np.ndarray, has_region: bool,
             mean: float, inv_var: float, inv_count: float, index: np.ndarray, sdT: np.ndarray, hessian: np.ndarray,
             loss_code: int, delta: float) -> tuple[float, float, np.ndarray, np.ndarray]:
    """:func:`objective` and the :func:`normal_equations` at its residuals in one call (the Gauss-Newton system
    of every evaluated pose: a rejected step wastes a few microseconds, an accepted one saves a call).

    Returns:
        ``(loss sum, gain, A (8, 8), b (8,))``.
    """
    total, r, gain = objective(warped, image, fg, region, has_region, mean, inv_var, inv_count, loss_code, delta)
    A, b = normal_equations(r, index, sdT, hessian, gain, loss_code, delta)
    return total, gain, A, b


@njit(**_REDUCE)
def objective_weighted(warped: np.ndarray, visible: np.ndarray, image: np.ndarray, fg: np.ndarray, inner: np.ndarray,
                       region: np.ndarray, has_region: bool, loss_code: int, delta: float
                       ) -> tuple[float, np.ndarray, float, np.ndarray]:
    """:func:`objective` with a per-pixel weight from the query's visibility.

    The visibility applies inside the foreground (``inner``: the foreground less a band along its outline, where a
    mask's edge is as likely wrong as right and the outline must keep its pull). The weight of a pixel is
    ``u = 1 - inner + inner * visible`` (times ``region`` when ``has_region``): an inner pixel counts as much as the
    query shows it, any other fully. The query's pixels are its print times its visibility (a mask applied, then
    warped and pyramided alike), so on an inner pixel the print is ``x = warped / visible`` (normalised convolution:
    a pixel half hidden at an occluder's edge is not half as bright; ``warped`` itself where ``visible`` is below
    1e-3, whose weight is nil), elsewhere ``x = warped``. The gain / bias fit is the least squares of ``x`` by
    ``gain * image + bias`` over ``fg * u``; the loss is ``sum u rho(r) + sum inner (1 - visible) rho(delta)``
    with ``r = x - gain * image - bias * fg`` (times ``region``): an inner pixel the query does not show costs as
    much as a residual of ``delta``, whatever the print there, so every pose is judged on every pixel and a pose
    cannot lower its loss by hiding the product. With ``visible`` all ones this is :func:`objective`.

    Args:
        warped, image, fg: as :func:`objective`'s; visible: ``(h, w)`` float32 in [0, 1], the query's visibility
            warped into the anchor frame by the same pose; inner: ``(h, w)`` float32 0/1, where it applies.
    Returns:
        ``(loss sum, r (h, w) float32, gain, u (h, w) float32)``; the sum is ``inf`` when not finite or when less
        than one pixel of the foreground is visible.
    """
    flat_v, flat_a, flat_f, flat_k = visible.ravel(), image.ravel(), fg.ravel(), inner.ravel()
    seen = warped.copy()  # the print where it is seen: warped / visible inside the foreground
    flat_w = seen.ravel()
    n = flat_w.shape[0]
    for i in range(n):
        if flat_k[i] > 0.0 and flat_v[i] >= 1e-3:
            flat_w[i] = flat_w[i] / flat_v[i]
    s_1 = 0.0
    s_a = 0.0
    s_aa = 0.0
    s_x = 0.0
    s_ax = 0.0
    for i in range(n):
        c = np.float64(flat_f[i]) * (1.0 - flat_k[i] + flat_k[i] * flat_v[i])
        a = np.float64(flat_a[i])
        x = np.float64(flat_w[i])
        s_1 += c
        s_a += c * a
        s_aa += c * a * a
        s_x += c * x
        s_ax += c * a * x
    weight = np.empty_like(warped)
    flat_u = weight.ravel()
    flat_r_region = region.ravel()
    hidden = 0.0  # foreground pixels not shown, weighted as the loss is
    for i in range(n):
        u = 1.0 - flat_k[i] + flat_k[i] * flat_v[i]
        h = np.float64(flat_k[i]) * (1.0 - flat_v[i])
        if has_region:
            u *= flat_r_region[i]
            h *= flat_r_region[i]
        flat_u[i] = u
        hidden += h
    if s_1 < 1.0:
        return math.inf, warped - warped, 0.0, weight
    var = s_aa - s_a * s_a / s_1
    gain = (s_ax - s_a * s_x / s_1) / var
    bias = (s_x - gain * s_a) / s_1
    g32, b32 = np.float32(gain), np.float32(bias)
    r = seen - g32 * image - b32 * fg
    flat = r.ravel()
    total = 0.0
    if loss_code == 0:
        for i in range(n):
            total += flat_u[i] * (np.float64(flat[i]) * flat[i])
        total *= 0.5
    elif loss_code == 1:
        for i in range(n):
            a = abs(np.float64(flat[i]))
            m = min(a, delta)
            total += flat_u[i] * (m * (a - 0.5 * m))
    else:
        for i in range(n):
            total += flat_u[i] * math.log1p((flat[i] / delta) ** 2)
        total *= 0.5 * delta * delta
    # rho(delta): delta^2 / 2 (l2, Huber), delta^2 / 2 log 2 (Cauchy)
    total += hidden * 0.5 * delta * delta * (math.log(2.0) if loss_code == 2 else 1.0)
    if not math.isfinite(total):
        total = math.inf
    return total, r, gain, weight


@njit(**_REDUCE)
def normal_equations_weighted(r: np.ndarray, weight: np.ndarray, index: np.ndarray, sdT: np.ndarray,
                              hessian: np.ndarray, gain: float, loss_code: int, delta: float
                              ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`normal_equations` with a per-pixel weight ``weight`` ``(h, w)`` (:func:`objective_weighted`'s ``u``)
    multiplied into the robust loss's: ``A = sum_j u_j w_j sd_j sd_j^T``, ``b = sum_j u_j w_j r_j sd_j / gain``. For
    ``l2`` and Huber the unweighted ``hessian`` is corrected on the pixels whose combined weight is not 1."""
    flat, flat_u = r.ravel(), weight.ravel()
    n = index.shape[0]
    weights = np.empty(n)  # u_j w_j
    weighted = np.empty(n)
    for j in range(n):
        value = np.float64(flat[index[j]])
        weights[j] = _robust_weight(value, loss_code, delta) * flat_u[index[j]]
        weighted[j] = value * weights[j]
    b = _gradient(sdT, weighted, gain)
    # l2 and Huber: the Hessian less (1 - u w) of each pixel whose combined weight is not 1
    return _hessian(weights, sdT, hessian, loss_code != 2), b


@njit(**_JIT)
def evaluate_weighted(warped: np.ndarray, visible: np.ndarray, image: np.ndarray, fg: np.ndarray, inner: np.ndarray,
                      region: np.ndarray, has_region: bool, index: np.ndarray, sdT: np.ndarray, hessian: np.ndarray,
                      loss_code: int, delta: float) -> tuple[float, float, np.ndarray, np.ndarray]:
    """:func:`objective_weighted` and :func:`normal_equations_weighted` at its residuals in one call (the hidden
    pixels' cost does not move with a small step: the Gauss-Newton system leaves it out).

    Returns:
        ``(loss sum, gain, A (8, 8), b (8,))``.
    """
    total, r, gain, weight = objective_weighted(warped, visible, image, fg, inner, region, has_region, loss_code,
                                                delta)
    A, b = normal_equations_weighted(r, weight, index, sdT, hessian, gain, loss_code, delta)
    return total, gain, A, b


@njit(**_JIT)
def lm_step(A: np.ndarray, b: np.ndarray, lam: float, H: np.ndarray, corner_J: np.ndarray, pixel_H_norm: np.ndarray,
            norm_H_pixel: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray, float]:
    """One Levenberg-Marquardt step of the inverse-compositional update.

    Solves ``(A + lam diag(A) + 1e-9 I) dp = b`` (Cholesky; the pseudo-inverse if that fails), composes
    ``H @ inv(I + D(dp))`` (normalised so that its ``[2, 2]`` is 1) and measures the step as the largest motion of an
    image corner, ``|dp @ corner_J|`` per corner (``corner_J`` ``(8, 8)`` in the level's pixels).

    Returns:
        ``(ok, candidate (3, 3), pixel_H_norm @ candidate @ norm_H_pixel, step px)``: the candidate normalised pose
        and its matrix in the level's pixels (the warp's); ``ok`` is False for a non-finite step.
    """
    D = A.copy()
    for k in range(8):
        D[k, k] += lam * A[k, k] + 1e-9
    L = np.zeros((8, 8))
    positive = True
    for k in range(8):
        s = D[k, k]
        for m in range(k):
            s -= L[k, m] * L[k, m]
        if not s > 0.0:
            positive = False
            break
        L[k, k] = math.sqrt(s)
        for i in range(k + 1, 8):
            t = D[i, k]
            for m in range(k):
                t -= L[i, m] * L[k, m]
            L[i, k] = t / L[k, k]
    if positive:
        z = np.empty(8)
        for k in range(8):
            t = b[k]
            for m in range(k):
                t -= L[k, m] * z[m]
            z[k] = t / L[k, k]
        dp = np.empty(8)
        for k in range(7, -1, -1):
            t = z[k]
            for m in range(k + 1, 8):
                t -= L[m, k] * dp[m]
            dp[k] = t / L[k, k]
    else:
        dp = np.linalg.pinv(D) @ b
    if not np.all(np.isfinite(dp)):
        return False, H, H, math.inf
    # inv(I + D(dp)) up to scale: the adjugate of [[1 + a, b, c], [d, 1 + e, f], [g, h, 1]]
    a, bb, c, d, e, f, g, hh = dp[0] + 1.0, dp[1], dp[2], dp[3], dp[4] + 1.0, dp[5], dp[6], dp[7]
    update = np.array([[e - f * hh, c * hh - bb, bb * f - c * e],
                       [f * g - d, a - c * g, c * d - a * f],
                       [d * hh - e * g, bb * g - a * hh, a * e - bb * d]])
    candidate = H @ update
    candidate = candidate / candidate[2, 2]
    motion = dp @ corner_J
    step = 0.0
    for corner in range(4):
        step = max(step, math.sqrt(motion[2 * corner] ** 2 + motion[2 * corner + 1] ** 2))
    return True, candidate, pixel_H_norm @ candidate @ norm_H_pixel, step


@njit(**_JIT)
def count_above(image: np.ndarray, mask: np.ndarray, level: float) -> int:
    """Pixels of ``image`` ``(h, w)`` float32 brighter than ``level`` where ``mask`` ``(h, w)`` uint8 is non-zero."""
    flat, where = image.ravel(), mask.ravel()
    count = 0
    for i in range(flat.shape[0]):
        count += (flat[i] > level) & (where[i] != 0)
    return count


def warm_up() -> None:
    """Compile (or load from the cache) every kernel for the argument types the refiner passes."""
    image = np.zeros((4, 4), dtype=np.float32)
    for channels in (1, 3):
        luminance(np.zeros((channels, 4, 4), dtype=np.float32), np.ones(3, dtype=np.float32), 0.0)
    # evaluate compiles objective and normal_equations for the same argument types (loss_code is one int type);
    # objective is also called on its own (the start's loss)
    evaluate(image, image, image, image, False, 0.0, 1.0, 1.0, np.zeros(1, dtype=np.int32),
             np.zeros((8, 1), dtype=np.float32), np.eye(8), 1, 1.0)
    objective(image, image, image, image, False, 0.0, 1.0, 1.0, 1, 1.0)
    evaluate_weighted(image, image, image, image, image, image, False, np.zeros(1, dtype=np.int32),
                      np.zeros((8, 1), dtype=np.float32), np.eye(8), 1, 1.0)
    objective_weighted(image, image, image, image, image, image, False, 1, 1.0)
    lm_step(np.eye(8), np.zeros(8), 1e-3, np.eye(3), np.eye(8), np.eye(3), np.eye(3))
    count_above(image, np.zeros((4, 4), dtype=np.uint8), 0.0)
