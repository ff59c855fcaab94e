"""Photometric verification of a recognised query: does the query, warped into the selected anchor's
frame by the predicted pose, look like the anchor?

The embedding distance says how close ``c(s(query))`` is to ``c(anchor)``; an unenrolled product can
still land near some enrolled one. Once the pose is known the two images can be compared pixel by
pixel: the query is warped into the anchor frame with ``anchor_H_query = inv(query_H_anchor)`` and
compared with the anchor over the anchor's foreground (its non-zero pixels: the canonical images are
zero outside the plane) where the warped query has data. The comparison is the zero-mean normalised
cross-correlation (ZNCC, :func:`zncc`): invariant to a gain and a bias per channel (exposure, white
balance), 1 for a perfect match, about 0 for unrelated content. Both images are first smoothed by a
Gaussian of ``blur_sigma`` px (a pose off by a pixel or two, and a query resampled from another
scale, keep their correlation). The open-set statistic built on it is ``1 - ZNCC`` (lower: more
alike), see :mod:`matl.inference.api`.

Two statistics (``statistic``):

* ``global``: one ZNCC over the anchor's whole plane where the query has data (the query's empty pixels left
  out with ``skip_empty``), at least :data:`MIN_COVERAGE` of the plane covered.
* ``patches``: over the part of the plane the query shows. The query's visibility in [0, 1] (its mask: an
  RGBA alpha, the foreground step's; ones when none) is warped into the anchor frame with the same pose;
  each pixel of the plane counts by it (times where the query has data). Two distances, the lower is the
  statistic: ``1 - ZNCC`` over the visible plane (:func:`weighted_zncc`: with a 0/1 visibility ``global``'s own),
  and a robust one: the anchor frame is cut into a grid of :data:`PATCH_CELLS` x :data:`PATCH_CELLS` patches;
  a patch counts when at least :data:`PATCH_FILL` of it is visible plane and the anchor is textured there (std
  at least :data:`PATCH_TEXTURE`), and gets its own ``1 - ZNCC``; the mean of the best :data:`PATCH_KEEP` of
  them (a trimmed mean, with at least :data:`MIN_PATCHES` usable patches), times :data:`PATCH_STRICTNESS`, so an
  occluder the mask missed costs only the patches it covers. With ``occluder_margin`` (the open set's second look,
  :meth:`~matl.inference.verification.Verifying._verified_past_occluders`) that many px of the visible plane are
  left out along the edges of what hides it (not the plane's own edge, :func:`away_from_hidden`): an occluder's drop
  shadow darkens the print beside it. A visible share of the plane below ``min_visible``
  is not a comparison (1, uncorrelated): such an answer does not verify and is judged by the open set's ratio
  test.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from numba import njit

from matl.data.gallery import WHOLE_CELL
from matl.geometry import pixel_to_normalised, sample_by_normalised

__all__ = ["LOOKALIKE_STATISTICS", "VERIFY_STATISTICS", "CandidateMemo", "CandidatePose", "Verification",
           "aligned_queries", "anchor_foreground", "away_from_hidden", "candidate_distances", "coarse_similarity",
           "difference_distances", "explained_distance", "hidden_share", "memo_poses", "patch_distances",
           "subject_share", "verification_distance", "verify_candidates", "weighted_zncc", "zncc"]

#: ``pose(queries, gallery_index, stn_H, warped, visibility or None, upscale or None) -> (query_H_anchor verified,
#: query_H_anchor an answer carries)`` of candidates (:func:`verify_candidates`)
CandidatePose = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None,
                          torch.Tensor | None], tuple[torch.Tensor, torch.Tensor]]

#: the statistics of :func:`verification_distance` (``verify_statistic``)
VERIFY_STATISTICS = ("patches", "global")
#: how two look-alike answers are told apart (``lookalike_statistic``): where their anchors differ
#: (:func:`difference_distances`) or by one ZNCC over the whole plane
LOOKALIKE_STATISTICS = ("difference", "global")
#: smallest foreground (pixels) a comparison needs; below it the pair counts as unrelated (ZNCC 0)
MIN_PIXELS = 16
#: smallest share of the anchor's plane a comparison must cover with query data (docs/decisions.md)
MIN_COVERAGE = 0.5
#: ``patches``: the anchor frame is cut into this many patches per side (docs/decisions.md)
PATCH_CELLS = 8
#: ``patches``: a patch counts when at least this share of its pixels is visible plane ...
PATCH_FILL = 0.5
#: ... and the anchor's std over them (blurred, channels pooled) is at least this (of 1)
PATCH_TEXTURE = 0.02
#: ``patches``: the share of the usable patches, best first, whose ``1 - ZNCC`` is averaged
PATCH_KEEP = 0.5
#: ``verify_shortlist``: the shortlist's anchors are compared with the query averaged over cells of this many px a side
COARSE_CELL = 4
#: ``verify_shortlist``: candidates taken from the shortlist by their pixels, beyond the ``top_k`` nearest
SHORTLIST_EXTRA = 4
#: ``verify_shortlist``: the largest ``1 - ZNCC`` that verifies a candidate taken by its pixels (docs/decisions.md)
SHORTLIST_VERIFY_MAX = 0.06
#: ``verify_shortlist``: a candidate taken by its pixels must cover at least this share of what the crop shows (its
#: subject, not a neighbour beside it; as ``uncover``'s default)
SHORTLIST_SUBJECT = 0.7
#: a query pixel is shown where its brightest channel is above this and its visibility above one half (a crop on
#: black shows its product, not its background)
SHOWN_LEVEL = 0.1
#: ``patches``: fewest usable patches the patches' part needs (a smaller plane is judged by its ZNCC alone)
MIN_PATCHES = 4
#: ``patches``: the patches' trimmed mean counts this many times over (it must be this much lower than ``verify_max``:
#: the best half of a plane's patches can match another product's that shares its layout)
PATCH_STRICTNESS = 3.5
#: ``patches``: smallest visible share of the anchor's plane a comparison needs (``verify_min_visible``)
MIN_VISIBLE = 0.3
#: ``patches``: the open set's second look (``verify_occluder_margin``) is for a plane at least this share of which its
#: crop does not show: a product partly hidden, not a whole one (the benchmark's occluders hide 0.1-0.5)
SECOND_LOOK_HIDDEN = 0.1
#: :func:`explained_distance`: the query frame is cut into this many cells per side (docs/decisions.md) ...
EXPLAINED_CELLS = 10
#: ... a cell counts when at least this share of it is the query's visible foreground ...
EXPLAINED_FILL = 0.3
#: ... and costs 1 unless the warped plane covers at least this share of that foreground
EXPLAINED_COVER = 0.5
#: :func:`difference_distances`: two anchors that differ by less than this (the sum over the compared pixels of their
#: mean absolute channel difference, of 1) are not told apart there (NaN)
DIFFERENCE_MIN = 0.5
#: ``lookalike_statistic=difference``: a look-alike whose plane, warped into the crop by its pose, overlaps the
#: answer's by less than this (intersection over union) lies elsewhere: it does not replace the answer
DIFFERENCE_OVERLAP = 0.85


def anchor_foreground(anchors: torch.Tensor, erode: int = 1) -> torch.Tensor:
    """``(B, 1, S, S)`` bool: the anchors' plane, pixels with any non-zero channel, eroded by ``erode`` px
    (the edge pixels mix plane and background).

    Args:
        anchors: ``(B, 3, S, S)`` float anchor images (zero outside the plane).
    """
    if erode > 0 and anchors.device.type == "cpu" and len(anchors):  # cv2.erode: the same min-filter, no border erosion
        plane = (anchors.detach().amax(1) > 0).to(torch.uint8).contiguous().numpy()
        kernel = np.ones((2 * erode + 1, 2 * erode + 1), np.uint8)
        eroded = np.stack([cv2.erode(p, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=1) for p in plane])
        return torch.from_numpy(eroded.reshape(plane.shape[0], 1, *plane.shape[1:])) > 0
    return _anchor_foreground_torch(anchors, erode)


def _anchor_foreground_torch(anchors: torch.Tensor, erode: int = 1) -> torch.Tensor:
    """:func:`anchor_foreground` in torch (a max-pooling of the negated mask): the GPU's and the reference."""
    mask = (anchors.amax(1, keepdim=True) > 0).float()
    if erode > 0:
        mask = -F.max_pool2d(-mask, 2 * erode + 1, stride=1, padding=erode)
    return mask > 0.5


def aligned_queries(queries: torch.Tensor, query_H_anchor: torch.Tensor, skip_empty: bool = False,
                    visibility: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The queries in their anchors' frames: ``(warped (B, 3, S, S), valid (B, 1, S, S) bool, seen)``.

    Args:
        queries: ``(B, 3, S, S)`` model-size query images.
        query_H_anchor: ``(B, 3, 3)`` pixel homographies, anchor pixel -> query pixel.
        skip_empty: also count as invalid what comes from query pixels that are 0 in every channel (the
            transparent part of an RGBA query, set to 0 when it was read: no data, not black print).
        visibility: ``(B, 1, S, S)`` the queries' visibility in [0, 1] (their masks), or None.
    Returns:
        ``warped(x) = query(query_H_anchor @ x)``, where that point lies inside the query (and, with
        ``skip_empty``, only among non-empty pixels), and the visibility warped alike ``(B, 1, S, S)`` (0 outside
        the query; None without ``visibility``).
    """
    query_H_anchor_norm = pixel_to_normalised(query_H_anchor.double(), tuple(queries.shape[-2:]))
    data = (queries.amax(1, keepdim=True) > 0).to(queries.dtype) if skip_empty else torch.ones_like(queries[:, :1])
    parts = [queries, data] if visibility is None else [queries, data, visibility.to(queries.device, queries.dtype)]
    warped = sample_by_normalised(torch.cat(parts, 1), query_H_anchor_norm)
    return warped[:, :3], warped[:, 3:4] > 0.999, None if visibility is None else warped[:, 4:5].clamp(0.0, 1.0)


@lru_cache(maxsize=8)
def _gaussian_kernel(sigma: float) -> torch.Tensor:
    """``(K,)`` the normalised 1-D Gaussian of ``sigma`` px, ``K = 2 round(3 sigma) + 1`` taps."""
    radius = round(3 * sigma)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    kernel = torch.exp(-x * x / (2.0 * sigma * sigma))
    return kernel / kernel.sum()


def gaussian_blur(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """``(B, C, H, W)`` images smoothed by a separable Gaussian of ``sigma`` px, borders reflected (the
    same as kornia's ``gaussian_blur2d`` with that kernel size, in two small convolutions).

    On the CPU (no gradient) each plane goes through ``cv2.sepFilter2D`` (border ``BORDER_REFLECT_101``: torch's
    ``reflect``), the same filter as :func:`_gaussian_blur_torch` up to float rounding and several times faster."""
    if images.device.type != "cpu" or images.requires_grad or images.dtype not in (torch.float32, torch.float64):
        return _gaussian_blur_torch(images, sigma)
    kernel = _gaussian_kernel(float(sigma)).numpy().astype(np.float32 if images.dtype == torch.float32 else np.float64)
    B, C, H, W = images.shape
    planes = images.detach().contiguous().numpy().reshape(B * C, H, W)
    out = np.empty_like(planes)
    for i in range(B * C):
        cv2.sepFilter2D(planes[i], -1, kernel, kernel, dst=out[i], borderType=cv2.BORDER_REFLECT_101)
    return torch.from_numpy(out.reshape(B, C, H, W))


def _gaussian_blur_torch(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """:func:`gaussian_blur` in torch (a padding and two grouped convolutions): the GPU's and the reference."""
    kernel = _gaussian_kernel(float(sigma)).to(images.device, images.dtype)
    channels, radius = images.shape[1], len(kernel) // 2
    x = F.pad(images, (radius, radius, radius, radius), mode="reflect")
    x = F.conv2d(x, kernel.view(1, 1, 1, -1).expand(channels, 1, 1, -1), groups=channels)
    return F.conv2d(x, kernel.view(1, 1, -1, 1).expand(channels, 1, -1, 1), groups=channels)


def zncc(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Zero-mean normalised cross-correlation of ``a`` and ``b`` over ``mask``, channels pooled.

    Each channel of each image loses its mean over the mask (a bias per channel); the correlation is
    ``sum(a' b') / sqrt(sum(a'^2) sum(b'^2))`` over mask pixels and channels (a common gain drops out;
    channels keep their relative contrast). Pairs with fewer than :data:`MIN_PIXELS` mask pixels or
    a flat image get 0.

    Args:
        a, b: ``(B, C, H, W)``; mask: ``(B, 1, H, W)`` bool.
    Returns:
        ``(B,)`` float64 in [-1, 1].
    """
    m = mask.double()
    count = m.sum((1, 2, 3))
    a, b = a.double(), b.double()
    mean_a = (a * m).sum((2, 3), keepdim=True) / count.clamp_min(1)[:, None, None, None]
    mean_b = (b * m).sum((2, 3), keepdim=True) / count.clamp_min(1)[:, None, None, None]
    da, db = (a - mean_a) * m, (b - mean_b) * m
    num = (da * db).sum((1, 2, 3))
    den = ((da * da).sum((1, 2, 3)) * (db * db).sum((1, 2, 3))).sqrt()
    ok = (count >= MIN_PIXELS) & (den > 1e-12)
    return torch.where(ok, num / den.clamp_min(1e-12), torch.zeros_like(num))


def patch_distances(a: torch.Tensor, b: torch.Tensor, weight: torch.Tensor, cells: int = PATCH_CELLS,
                    fill: float = PATCH_FILL, texture: float = PATCH_TEXTURE) -> torch.Tensor:
    """``1 - ZNCC`` of ``a`` and ``b`` in each patch of a ``cells`` x ``cells`` grid, pixels weighted by ``weight``.

    Each patch's ZNCC is :func:`zncc`'s over its pixels (weighted means per channel, channels pooled). A patch
    whose weights sum to less than ``fill`` of its area, or whose ``a`` has a (weighted, channels pooled) std
    below ``texture``, is not usable (NaN); one where ``b`` is flat gets ZNCC 0.

    Args:
        a: ``(B, C, H, W)`` the reference (the anchor); b: ``(B, C, H, W)`` the other (the warped query);
        weight: ``(B, 1, H, W)`` in [0, 1].
    Returns:
        ``(B, cells * cells)`` float64, NaN where a patch is not usable.
    """
    return _patch_distances(*_cell_correlations(a, b, weight, cells), a.shape[1], fill, texture)


def _patch_distances(count: torch.Tensor, var_a: torch.Tensor, corr: torch.Tensor, area: float, channels: int,
                     fill: float = PATCH_FILL, texture: float = PATCH_TEXTURE) -> torch.Tensor:
    """:func:`patch_distances` from the cells' :func:`_cell_correlations`."""
    usable = (count >= fill * area) & (var_a >= texture * texture * channels * count)
    return torch.where(usable, 1.0 - corr, torch.full_like(corr, float("nan"))).flatten(1)


def weighted_zncc(a: torch.Tensor, b: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``(B,)`` float64 ZNCC of ``a`` and ``b`` ``(B, C, H, W)`` with pixels weighted by ``weight`` ``(B, 1, H, W)``
    (weighted means per channel, channels pooled: :func:`zncc`'s with a 0/1 weight); 0 where the weights sum to
    fewer than :data:`MIN_PIXELS` or an image is flat."""
    return _weighted_zncc(*_cell_correlations(a, b, weight, 1)[:3])


def _weighted_zncc(count: torch.Tensor, var_a: torch.Tensor, corr: torch.Tensor) -> torch.Tensor:
    """:func:`weighted_zncc` from the one cell of :func:`_cell_correlations` (``(B, 1, 1)`` each)."""
    ok = (count >= MIN_PIXELS) & (var_a > 1e-12)
    return torch.where(ok, corr, torch.zeros_like(corr)).flatten(1)[:, 0]


def _cell_correlations(a: torch.Tensor, b: torch.Tensor, weight: torch.Tensor, cells: int
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """Per cell of a ``cells`` x ``cells`` grid over ``(B, C, H, W)`` images: ``(weight sum, a's weighted sum of
    squared deviations (channels pooled), the weighted correlation (0 where b is flat), the cell's area)``, each
    ``(B, cells, cells)`` float64."""
    count, sums, area = _cell_sums(a, b, weight, cells)
    return (*_correlations(count, sums), area)


def _cell_sums(a: torch.Tensor, b: torch.Tensor, weight: torch.Tensor, cells: int, torch_only: bool = False
               ) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Per cell of a ``cells`` x ``cells`` grid over ``(B, C, H, W)`` images: ``(weight sum (B, cells, cells),
    the weighted sums of a, b, a a, b b, a b (B, 5, C, cells, cells), the cell's area)``, float64 (cells of ``side``
    px cover the frame; the last row and column may be short, the area is a whole cell's). On the CPU one compiled
    pass (:func:`_cell_sums_kernel`), else (or ``torch_only``: the reference) pooled in torch."""
    B, C, H, W = a.shape
    side = -(-max(H, W) // cells)
    area = float(side * side)
    if not torch_only and a.device.type == "cpu" and not (a.requires_grad or b.requires_grad or weight.requires_grad):
        count, sums = _cell_sums_kernel(_numpy(a), _numpy(b), _numpy(weight), cells, side)
        return torch.from_numpy(count), torch.from_numpy(sums), area
    m, a, b = weight.double(), a.double(), b.double()
    count = _cell_totals(m, cells)[:, 0]                          # (B, cells, cells)
    products = torch.cat([m * a, m * b, m * a * a, m * b * b, m * a * b], 1)
    sums = _cell_totals(products, cells).view(B, 5, C, cells, cells)
    return count, sums, area


def _cell_totals(x: torch.Tensor, cells: int) -> torch.Tensor:
    """``(B, C, cells, cells)``: the sums of ``(B, C, H, W)`` over each cell of a ``cells`` x ``cells`` grid (cells of
    :func:`_cell_sums`' side, the frame zero-padded to whole cells)."""
    H, W = x.shape[-2:]
    side = -(-max(H, W) // cells)
    return F.avg_pool2d(F.pad(x, (0, cells * side - W, 0, cells * side - H)), side) * float(side * side)


def _correlations(count: torch.Tensor, sums: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(count, var_a, corr)`` of :func:`_cell_correlations` from :func:`_cell_sums`'s ``count`` and ``sums``."""
    C = sums.shape[2]
    n = count.clamp_min(1e-9)[:, None]
    sa, sb, saa, sbb, sab = sums.unbind(1)                        # (B, C, cells, cells)
    var_a = (saa - sa * sa / n).sum(1).clamp_min(0.0)
    var_b = (sbb - sb * sb / n).sum(1).clamp_min(0.0)
    cov = (sab - sa * sb / n).sum(1)
    den = (var_a * var_b).sqrt()
    textured_b = var_b > 1e-10 * C * count  # a std of 1e-5 is rounding, not texture
    corr = torch.where(textured_b & (den > 0), cov / den.clamp_min(1e-300), torch.zeros_like(cov))
    return count, var_a, corr


def _numpy(x: torch.Tensor) -> np.ndarray:
    """A CPU tensor as a C-contiguous float32 or float64 array (a view where it already is one)."""
    x = x.detach()
    if x.dtype not in (torch.float32, torch.float64):
        x = x.float()
    return x.contiguous().numpy()


@njit(cache=True, nogil=True, boundscheck=False)
def _cell_sums_kernel(a: np.ndarray, b: np.ndarray, weight: np.ndarray, cells: int, side: int
                      ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_cell_sums` in one pass over the pixels, accumulated in float64 (the products as torch forms them:
    ``(m a) a``, ``(m b) b``, ``(m a) b``); pixels of weight 0 add nothing and are skipped."""
    B, C, H, W = a.shape
    count = np.zeros((B, cells, cells))
    sums = np.zeros((B, 5, C, cells, cells))
    for i in range(B):
        for y in range(H):
            cy = y // side
            for x in range(W):
                m = np.float64(weight[i, 0, y, x])
                if m == 0.0:
                    continue
                cx = x // side
                count[i, cy, cx] += m
                for c in range(C):
                    av = np.float64(a[i, c, y, x])
                    bv = np.float64(b[i, c, y, x])
                    ma, mb = m * av, m * bv
                    sums[i, 0, c, cy, cx] += ma
                    sums[i, 1, c, cy, cx] += mb
                    sums[i, 2, c, cy, cx] += ma * av
                    sums[i, 3, c, cy, cx] += mb * bv
                    sums[i, 4, c, cy, cx] += ma * bv
    return count, sums


def _trimmed(distances: torch.Tensor, keep: float, least: int) -> torch.Tensor:
    """``(B,)`` the mean of the lowest ``keep`` share (at least one) of each row's finite values; 1 for a row with
    fewer than ``least`` of them."""
    finite = torch.isfinite(distances)
    usable = finite.sum(1)
    ranked = torch.where(finite, distances, torch.full_like(distances, float("inf"))).sort(1).values
    k = (usable.double() * keep).ceil().long().clamp_min(1)
    take = torch.arange(ranked.shape[1], device=ranked.device)[None, :] < k[:, None]
    mean = torch.where(take, ranked, torch.zeros_like(ranked)).sum(1) / k
    return torch.where(usable >= least, mean, torch.ones_like(mean))


def away_from_hidden(seen: torch.Tensor, plane: torch.Tensor, margin: int) -> torch.Tensor:
    """``seen`` ``(B, 1, S, S)`` in [0, 1] (a visibility in the anchor's frame) eroded by ``margin`` px from where it
    falls inside ``plane`` ``(B, 1, S, S)`` bool (an occluder's or the mask's edge), not from the plane's own edge
    (outside the plane counts as seen): the minimum over a ``2 margin + 1`` square."""
    around = torch.maximum(seen, (~plane).to(seen.dtype))
    return -F.max_pool2d(-around, 2 * margin + 1, stride=1, padding=margin)


def hidden_share(queries: torch.Tensor, query_H_anchor: torch.Tensor, anchors: torch.Tensor,
                 visibility: torch.Tensor | None = None, erode: int = 1) -> torch.Tensor:
    """``(B,)`` float64: the share of each anchor's plane (:func:`anchor_foreground`) that its query does not show
    under the pose: outside the query, on its empty (transparent) pixels or where its ``visibility`` ``(B, 1, S, S)``
    is at most 0.5 (None: everything in the query is visible). ``queries`` ``(B, 3, S, S)``, ``query_H_anchor``
    ``(B, 3, 3)`` pixel, ``anchors`` ``(B, 3, S, S)``."""
    _, valid, seen = aligned_queries(queries.float(), query_H_anchor.to(queries.device), True, visibility)
    plane = anchor_foreground(anchors.float(), erode).to(valid.device)
    shown = valid if seen is None else valid & (seen > 0.5)
    area = plane.sum((1, 2, 3)).double()
    return (1.0 - (plane & shown).sum((1, 2, 3)).double() / area.clamp_min(1.0)).cpu()


def verification_distance(queries: torch.Tensor, query_H_anchor: torch.Tensor, anchors: torch.Tensor,
                          blur_sigma: float = 1.0, erode: int = 1, skip_empty: bool = False,
                          min_coverage: float = MIN_COVERAGE, visibility: torch.Tensor | None = None,
                          statistic: str = "global", min_visible: float = MIN_VISIBLE,
                          occluder_margin: int = 0) -> torch.Tensor:
    """``1 - ZNCC`` of each query warped into its anchor's frame against the anchor (see the module docstring).

    Args:
        queries: ``(B, 3, S, S)`` model-size queries; query_H_anchor: ``(B, 3, 3)`` pixel, anchor -> query;
        anchors: ``(B, 3, S, S)`` the selected anchor of each query.
        blur_sigma: Gaussian smoothing of both images before the comparison, px (0: none).
        erode: the anchor's foreground is eroded by this many px.
        skip_empty: leave out what comes from the query's empty (all-zero) pixels (:func:`aligned_queries`).
        min_coverage: ``global``: the share of the anchor's (eroded) foreground the compared pixels must cover;
            a pose that puts most of the anchor over no query data is not compared (1, uncorrelated): a few
            pixels can correlate by chance.
        visibility: ``(B, 1, S, S)`` the queries' visibility in [0, 1] (``patches``; None: ones).
        statistic: ``global`` (one ZNCC over the plane) or ``patches`` (over the visible part, a trimmed mean of
            per-patch ``1 - ZNCC``); see the module docstring.
        min_visible: ``patches``: the smallest visible share of the anchor's plane that is compared.
        occluder_margin: ``patches``: px of the visible plane left out along the edges of what hides it
            (:func:`away_from_hidden`; 0: none).
    Returns:
        ``(B,)`` float64 in [0, 2]: 0 identical up to gain and bias, 1 uncorrelated.
    """
    if statistic not in VERIFY_STATISTICS:
        raise ValueError(f"statistic must be one of {', '.join(VERIFY_STATISTICS)}, got {statistic!r}")
    if len(queries) == 0:
        return torch.zeros(0, dtype=torch.float64)
    patches = statistic == "patches"
    warped, valid, seen = aligned_queries(queries.float(), query_H_anchor.to(queries.device), skip_empty,
                                          visibility if patches else None)
    anchors = anchors.float()
    plane = anchor_foreground(anchors, erode)
    if patches:
        if seen is not None and occluder_margin > 0:
            seen = away_from_hidden(seen, plane, int(occluder_margin))
        weight = (plane & valid).float() if seen is None else (plane & valid).float() * seen
        enough = weight.sum((1, 2, 3)) >= min_visible * plane.sum((1, 2, 3)).clamp_min(1)
    else:
        mask = plane & valid
        covered = mask.sum((1, 2, 3)) >= min_coverage * plane.sum((1, 2, 3))
    if blur_sigma > 0:  # one call for both
        warped, anchors = gaussian_blur(torch.cat([warped, anchors]), blur_sigma).split(len(anchors))
    if patches:
        # one pass over the pixels for both: the whole plane's sums are its patches' (warped as a, anchors as b)
        count, sums, area = _cell_sums(warped, anchors, weight, PATCH_CELLS)
        whole = 1.0 - _weighted_zncc(*_correlations(count.sum((1, 2), keepdim=True), sums.sum((3, 4), keepdim=True)))
        swapped = sums[:, [1, 0, 3, 2, 4]]                        # anchors as a, warped as b
        cells = _patch_distances(*_correlations(count, swapped), area, anchors.shape[1])
        robust = _trimmed(cells, PATCH_KEEP, MIN_PATCHES) * PATCH_STRICTNESS
        return torch.where(enough, torch.minimum(whole, robust), torch.ones_like(whole)).cpu()
    return (1.0 - zncc(warped, anchors, mask).masked_fill(~covered, 0.0)).cpu()


def explained_distance(queries: torch.Tensor, query_H_anchor: torch.Tensor, anchors: torch.Tensor,
                       visibility: torch.Tensor | None = None, cells: int = EXPLAINED_CELLS,
                       fill: float = EXPLAINED_FILL, cover: float = EXPLAINED_COVER) -> torch.Tensor:
    """How badly each anchor, warped into its query's frame by the pose, explains the query's visible foreground.

    :func:`verification_distance` compares in the anchor's frame, over the part of the plane a pose puts under the
    query's mask: two poses of one answer are compared over different pixels, and a pose that shrinks or slides the
    plane onto a few well-matching pixels of a partly hidden product can score better than the true one. Here the
    pixels are the query's own, the same for every pose: the query frame is cut into ``cells`` x ``cells`` cells; a
    cell counts when at least ``fill`` of it is visible foreground (weighted by that area); it costs 1 when the warped
    anchor's plane (eroded by 1 px) covers less than ``cover`` of its foreground (the pose leaves the query's
    product unexplained there), else ``1 - ZNCC`` of query and warped anchor over the covered foreground (channels
    pooled, no smoothing). An occluder the mask kept costs every pose alike.

    Args:
        queries: ``(B, 3, S, S)`` model-size queries; query_H_anchor: ``(B, 3, 3)`` pixel, anchor -> query;
        anchors: ``(B, 3, S, S)`` the anchors the poses are against (zero outside the plane).
        visibility: ``(B, 1, S, S)`` the queries' visibility in [0, 1] (visible above 0.5); None: the queries'
            non-empty pixels.
    Returns:
        ``(B,)`` float64 in [0, 2] (lower: explained better); 1 where no cell counts.
    """
    if len(queries) == 0:
        return torch.zeros(0, dtype=torch.float64)
    S = queries.shape[-1]
    anchors = anchors.to(queries.device, queries.dtype)
    plane = anchor_foreground(anchors).to(queries.dtype)
    anchor_H_query = torch.linalg.inv(query_H_anchor.double().to(queries.device))
    warped = sample_by_normalised(torch.cat([anchors, plane], 1),
                                  pixel_to_normalised(anchor_H_query, (S, S)).to(queries.dtype))
    seen = (queries.amax(1, keepdim=True) > 0) if visibility is None else visibility.to(queries.device) > 0.5
    covered = seen & (warped[:, 3:4] > 0.5)
    count, sums, area = _cell_sums(queries.contiguous(), warped[:, :3].contiguous(),
                                   covered.to(queries.dtype).contiguous(), cells)
    _, _, corr = _correlations(count, sums)
    shown = _cell_totals(seen.double(), cells)[:, 0]
    cost = torch.where(count >= cover * shown, 1.0 - corr, torch.ones_like(corr))
    weight = torch.where(shown >= fill * area, shown, torch.zeros_like(shown)).flatten(1)
    total = weight.sum(1)
    return torch.where(total > 0, (cost.flatten(1) * weight).sum(1) / total.clamp_min(1e-9),
                       torch.ones_like(total)).cpu()


def difference_distances(queries: torch.Tensor, query_H_anchor: torch.Tensor, anchors: torch.Tensor,
                         visibility: torch.Tensor | None = None, blur_sigma: float = 1.0
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """Which of two posed anchors explains its query better where the two anchors differ.

    Look-alikes (the same layout in another flavour name, colour band, pack size or badge) match a query equally
    well over most of the plane; a comparison over the whole plane drowns their difference in the shared print,
    the camera's noise and the pose's misfit. Here both anchors are warped into the query's frame by their poses
    and compared on the query's own pixels, those it shows (its visibility above one half, else its non-empty
    pixels) under both planes: each pixel counts by how much the two warped anchors differ there (their mean
    absolute channel difference after a Gaussian of ``blur_sigma`` px, as the query's), so the flavour text or the
    band decides and the shared layout does not. Each anchor explains the query through its own gain and bias per
    channel (least squares over those pixels: the camera's exposure and white balance), and its distance is the
    weighted mean squared residual.

    Args:
        queries: ``(B, 3, S, S)`` model-size queries.
        query_H_anchor: ``(B, 2, 3, 3)`` pixel, anchor -> query, of each query's two anchors.
        anchors: ``(B, 2, 3, S, S)`` the two anchors (zero outside the plane).
        visibility: ``(B, 1, S, S)`` the queries' visibility in [0, 1], or None.
        blur_sigma: Gaussian smoothing of the query and the warped anchors, px (0: none).
    Returns:
        ``(distances (B, 2), overlap (B,))`` float64: the distances (lower: explained better), NaN for both where the
        two anchors differ by less than :data:`DIFFERENCE_MIN` over the compared pixels (nothing to tell them apart
        by); the intersection over union of the two planes in the crop (look-alikes lie on one place, at least
        :data:`DIFFERENCE_OVERLAP`; two planes elsewhere differ by where they lie, not by their print).
    """
    B = len(queries)
    if query_H_anchor.shape[:2] != (B, 2) or anchors.shape[:2] != (B, 2):
        raise ValueError(f"difference_distances needs two poses and two anchors a query, got "
                         f"{tuple(query_H_anchor.shape)} and {tuple(anchors.shape)} for {B} queries")
    if B == 0:
        return torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, dtype=torch.float64)
    S = queries.shape[-1]
    queries = queries.float()
    flat = anchors.flatten(0, 1).to(queries.device, queries.dtype)
    plane = anchor_foreground(flat).to(queries.dtype)
    anchor_H_query = torch.linalg.inv(query_H_anchor.flatten(0, 1).double().to(queries.device))
    warped = sample_by_normalised(torch.cat([flat, plane], 1),
                                  pixel_to_normalised(anchor_H_query, (S, S)).to(queries.dtype)).view(B, 2, 4, S, S)
    seen = (queries.amax(1, keepdim=True) > 0) if visibility is None else visibility.to(queries.device) > 0.5
    first_plane, second_plane = warped[:, 0, 3:4] > 0.5, warped[:, 1, 3:4] > 0.5  # (B, 1, S, S) each
    region = (seen & first_plane & second_plane).to(queries.dtype)
    images = torch.cat([queries, warped[:, 0, :3], warped[:, 1, :3]])
    if blur_sigma > 0:
        images = gaussian_blur(images, blur_sigma)
    query, first, second = images.double().split(B)
    region = region.double()
    weight = (first - second).abs().mean(1, keepdim=True) * region
    total = weight.sum((1, 2, 3))
    count = region.sum((2, 3), keepdim=True).clamp_min(1.0)
    query_mean = (query * region).sum((2, 3), keepdim=True) / count
    distances = []
    for anchor in (first, second):
        anchor_mean = (anchor * region).sum((2, 3), keepdim=True) / count
        centred = (anchor - anchor_mean) * region
        gain = (centred * (query - query_mean)).sum((2, 3), keepdim=True) / (centred * centred).sum(
            (2, 3), keepdim=True).clamp_min(1e-12)
        residual = (query - query_mean - gain * (anchor - anchor_mean)) ** 2
        distances.append((residual.mean(1, keepdim=True) * weight).sum((1, 2, 3)) / total.clamp_min(1e-12))
    overlap = (first_plane & second_plane).sum((1, 2, 3)) / (first_plane | second_plane).sum((1, 2, 3)).clamp_min(1)
    distances = torch.stack(distances, 1).masked_fill((total < DIFFERENCE_MIN)[:, None], float("nan"))
    return distances.cpu(), overlap.double().cpu()


@dataclass
class Verification:
    """The verified answer of each query.

    Attributes:
        gallery_index: ``(Q,)`` int64 the chosen gallery anchor: the first candidate, nearest first, whose
            pose verifies, else the nearest one.
        query_H_anchor: ``(Q, 3, 3)`` pixel pose against it.
        feature_distance: ``(Q,)`` ``||c(anchor) - c(s(query))||`` of the chosen anchor.
        distance: ``(Q,)`` float64 ``1 - ZNCC`` of the chosen anchor (:func:`verification_distance`).
        verified: ``(Q,)`` bool, ``distance <= verify_max``.
        tried: ``(Q,)`` int64 candidates compared (including ``first``).
    """

    gallery_index: torch.Tensor
    query_H_anchor: torch.Tensor
    feature_distance: torch.Tensor
    distance: torch.Tensor
    verified: torch.Tensor
    tried: torch.Tensor


class CandidateMemo:
    """Candidates already posed (and compared) for a query, by the query's key and the candidate's gallery anchor: the
    look-alike rivals of one answer are each verified against much the same anchors (the nearest without the
    answer's product), and a candidate's pose and distance depend on the query and the anchor alone (each posed from
    the query's STN pose), so each pair is posed once. Entries: ``(verified pose (3, 3), answer's pose (3, 3),
    verification distance or None)``; valid for one set of verification settings and one gallery."""

    def __init__(self) -> None:
        self._pairs: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor, float | None]] = {}

    def __len__(self) -> int:
        return len(self._pairs)

    def get(self, key: int, anchor: int) -> tuple[torch.Tensor, torch.Tensor, float | None] | None:
        return self._pairs.get((key, anchor))

    def put(self, key: int, anchor: int, verified: torch.Tensor, answer: torch.Tensor,
            distance: float | None = None) -> None:
        self._pairs[(key, anchor)] = (verified, answer, distance)


def _posed_pairs(memo: CandidateMemo | None, keys: list[int] | None, anchors: torch.Tensor, start: torch.Tensor,
                 pose: Callable[[list[int]], tuple[torch.Tensor, torch.Tensor]],
                 compare: Callable[[list[int], torch.Tensor], torch.Tensor] | None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The poses and distances of ``P`` (query, candidate) pairs, the query of pair ``p`` keyed ``keys[p]`` in
    ``memo`` (None: no memo) and its candidate ``anchors[p]``: ``pose(pairs)`` poses the pairs listed (``(verified
    (n, 3, 3), answer's (n, 3, 3))``), ``compare(pairs, verified)`` compares them (``(n,)``; None: no distances);
    with a memo only the pairs it lacks, and what is posed or compared here is added to it.
    ``start`` ``(P, 3, 3)`` gives the dtype and device of the poses. Returns ``(verified (P, 3, 3), answer's
    (P, 3, 3), distance (P,) float64 or None)``."""
    every = list(range(len(anchors)))
    if memo is None or keys is None:
        verified, answer = pose(every)
        return verified, answer, None if compare is None else compare(every, verified).double().cpu()
    found = [memo.get(k, int(a)) for k, a in zip(keys, anchors.tolist(), strict=True)]
    missing = [p for p, f in enumerate(found) if f is None]
    verified, answer = start.clone(), start.clone()
    if missing:
        new_verified, new_answer = pose(missing)
        verified[missing], answer[missing] = new_verified.to(start), new_answer.to(start)
    for p, f in enumerate(found):
        if f is not None:
            verified[p], answer[p] = f[0].to(start), f[1].to(start)
    distance = None
    unknown = missing
    if compare is not None:
        distance = torch.tensor([0.0 if f is None or f[2] is None else f[2] for f in found], dtype=torch.float64)
        unknown = [p for p in every if found[p] is None or found[p][2] is None]
        if unknown:
            distance[unknown] = compare(unknown, verified[unknown]).double().cpu()
    for p in unknown:  # what was posed or compared here
        memo.put(keys[p], int(anchors[p]), verified[p], answer[p], None if distance is None else float(distance[p]))
    return verified, answer, distance


def memo_poses(memo: CandidateMemo, keys: list[int], anchors: torch.Tensor, start: torch.Tensor,
               pose: Callable[[list[int]], tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """The verified poses ``(P, 3, 3)`` (as ``start``'s dtype) of ``P`` (query, candidate) pairs, query ``keys[p]``
    and gallery anchor ``anchors[p]``: from ``memo`` where it has the pair, else by ``pose(pairs)`` (``(verified,
    answer's)`` of the pairs listed), which are added to it."""
    return _posed_pairs(memo, keys, anchors, start, pose, None)[0]


def _without_objects(gallery: Any, d: torch.Tensor, exclude_object: torch.Tensor | None) -> torch.Tensor:
    """Distances ``d`` ``(Q, G)`` to the gallery's anchors with those of each query's ``exclude_object`` ``(Q,)``
    at infinity (None: as they are)."""
    if exclude_object is None:
        return d
    own = gallery.object_index.to(d.device)[None, :] == exclude_object.to(d.device)[:, None]
    return d.masked_fill(own, float("inf"))


@torch.no_grad()
def verify_candidates(recognizer: Any, queries: torch.Tensor, top_k: int, verify_max: float, blur_sigma: float = 1.0,
                      first: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                      exclude_object: torch.Tensor | None = None, skip_empty: bool = False,
                      candidate_pose: CandidatePose | None = None, first_refined: bool = True,
                      visibility: torch.Tensor | None = None, upscale: torch.Tensor | None = None,
                      statistic: str = "global", min_visible: float = MIN_VISIBLE, shortlist: int = 0,
                      embedded: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
                      memo: CandidateMemo | None = None, keys: list[int] | None = None) -> Verification:
    """Verify the ``top_k`` nearest gallery anchors of each query; the first, nearest first, that verifies wins
    (with ``shortlist``: more candidates, and the closest that verifies wins).

    A candidate is posed as the recognizer poses its nearest anchor: the STN's ``query_H_anchor``, then
    the alignment stage against that candidate (when the model has one), or by ``candidate_pose`` (a refinement
    against the candidate), and verified by :func:`verification_distance`. The first candidate whose
    ``1 - ZNCC`` is at most ``verify_max`` is the answer; a query none of whose candidates verifies keeps
    its nearest anchor. The nearest candidate is verified first with the pose it came with; only the
    queries it does not verify go on, their other candidates posed and compared in one batch (a handful
    of calls however many candidates); with ``candidate_pose`` and ``first_refined=False`` the nearest is among
    them again, posed by ``candidate_pose``.

    Args:
        recognizer: a :class:`matl.models.recognizer.TensorRecognizer` (its networks, gallery and features).
        queries: ``(Q, 3, S, S)`` model-size queries on the recognizer's device.
        top_k: candidates per query (>= 1).
        verify_max: the largest ``1 - ZNCC`` that verifies.
        blur_sigma, skip_empty: as :func:`verification_distance`'s.
        first: ``(gallery_index (Q,), query_H_anchor (Q, 3, 3), feature distance (Q,))`` of an answer
            already computed (the recognizer's own, possibly refined), taken as the nearest candidate;
            None: the nearest candidate comes from the search here.
        exclude_object: ``(Q,)`` object index per query whose anchors are not candidates (the open-set
            calibration's impostors), or None.
        candidate_pose: ``(queries (T, 3, S, S), gallery_index (T,), stn_H (T, 3, 3), warped (T, 3, S, S),
            visibility (T, 1, S, S) or None, upscale (T,) or None) -> (verified (T, 3, 3), answer (T, 3, 3))``: the
            candidates' poses that are verified (``verify_refine``: the fast refinement against each candidate)
            and those an answer carries (the same, or the networks' pose when answers are not refined); None:
            the STN's, then the alignment stage's, for both.
        first_refined: whether ``first``'s pose was already refined (then the nearest is not posed again).
        visibility: ``(Q, 1, S, S)`` the queries' visibility in [0, 1] (their masks), or None (ones).
        upscale: ``(Q,)`` how many times each query's file was enlarged to the model's size, for
            ``candidate_pose`` (None: not known).
        statistic, min_visible: as :func:`verification_distance`'s.
        shortlist: ``verify_shortlist``: when above ``top_k``, a query whose nearest candidate does not verify
            also meets the :data:`SHORTLIST_EXTRA` anchors among its ``shortlist`` nearest (beyond the ``top_k``)
            whose pixels at the STN's pose look most like it (:func:`coarse_similarity`), each verifying within
            :data:`SHORTLIST_VERIFY_MAX` (one of many tried: a stricter bar) where its plane covers at least
            :data:`SHORTLIST_SUBJECT` of what the crop shows (:func:`subject_share`: the crop's subject, not a
            neighbour beside it); of the candidates that verify, the one with the lowest distance wins. 0 (or at
            most ``top_k``): the features' order alone.
        embedded: ``(STN query_H_anchor (Q, 3, 3), s(queries) (Q, 3, S, S), distances (Q, G) to every anchor)`` of
            these queries (:func:`candidate_distances` without exclusion) when already computed; None: computed here.
        memo: candidates already posed for these queries (:class:`CandidateMemo`, each query by ``keys[q]``): a pair
            in it is not posed again, and the pairs posed here are added (None: every pair posed).
    """
    g = recognizer.gallery
    n = len(queries)
    if memo is not None and (keys is None or len(keys) != n):
        raise ValueError(f"verify_candidates: a memo needs one key per query ({n}), got {keys}")
    if embedded is not None:  # (features, STN poses, warps, distances) as candidate_distances gives them
        embedded = (None, embedded[0], embedded[1], _without_objects(g, embedded[2], exclude_object))
    if first is None:  # the nearest (allowed) anchor, posed as the recognizer poses it
        if embedded is None:
            embedded = candidate_distances(recognizer, queries, exclude_object)
        _, stn_H, warped, d = embedded
        nearest_d, nearest = d.min(1)
        H = stn_H
        if getattr(recognizer, "align", None) is not None:
            H = recognizer.align.infer(queries, g.images[nearest], stn_H, warped).query_H_anchor
        first = (nearest, H, nearest_d)
    # copies: the answer is changed in place below, the caller's tensors (the prediction's) must stay as they are
    index, pose = first[0].cpu().long().clone(), first[1].cpu().double().clone()
    feature_distance = first[2].cpu().double().clone()
    compare = {"skip_empty": skip_empty, "statistic": statistic, "min_visible": min_visible}
    distance = verification_distance(queries, first[1], g.images[first[0]], blur_sigma, visibility=visibility,
                                     **compare)
    tried = torch.ones(n, dtype=torch.long)
    todo = torch.nonzero(distance > verify_max).flatten()
    if len(todo) == 0 or top_k <= 1:
        return Verification(index, pose, feature_distance, distance, distance <= verify_max, tried)
    x = queries[todo]
    seen = None if visibility is None else visibility[todo.to(visibility.device)]
    factor = None if upscale is None else torch.as_tensor(upscale)[todo]
    if embedded is None:
        _, stn_H, warped, d = candidate_distances(recognizer, x, None if exclude_object is None else
                                                   exclude_object[todo])
    else:
        stn_H, warped, d = (e[todo] for e in embedded[1:])
    again = candidate_pose is not None and not first_refined  # the nearest candidate, posed anew by the refinement
    if not again:
        d = d.scatter(1, index[todo, None].to(d.device), float("inf"))  # the nearest candidate, verified above
    k = features_k = min(top_k - (0 if again else 1), d.shape[1])
    cand_d, cand = d.topk(k, dim=1, largest=False)  # (T, k) nearest first
    limit = torch.full((len(todo), k), verify_max, dtype=torch.float64)  # (T, k) each candidate's verify_max
    widened = shortlist > top_k
    if widened:  # more candidates: the shortlist's others whose pixels at the STN's pose look most alike
        short_d, short = d.topk(min(shortlist, d.shape[1]), dim=1, largest=False)  # (T, m) nearest first
        pooled, plane = g.coarse_images(COARSE_CELL)
        at = short.to(pooled.device)
        score = coarse_similarity(warped, pooled[at], plane[at], COARSE_CELL).to(short_d.device)
        score[:, :k] = -float("inf")                                          # already candidates
        score = score.masked_fill(~torch.isfinite(short_d), -float("inf"))    # excluded products
        found, pick = score.topk(min(SHORTLIST_EXTRA, short.shape[1] - k), dim=1)
        cand_d = torch.cat([cand_d, short_d.gather(1, pick).masked_fill(~torch.isfinite(found), float("inf"))], 1)
        cand = torch.cat([cand, short.gather(1, pick)], 1)
        limit = torch.cat([limit, torch.full(pick.shape, min(verify_max, SHORTLIST_VERIFY_MAX), dtype=torch.float64)],
                          1)
        k = cand.shape[1]
    usable = torch.isfinite(cand_d).cpu()           # (T, k) an excluded product leaves fewer
    t, j = torch.nonzero(usable, as_tuple=True)     # every usable (query, candidate) pair, one batch
    anchors = g.images[cand[t, j]]
    seen_t = None if seen is None else seen[t.to(seen.device)]

    def posed_by(pairs: list[int]) -> tuple[torch.Tensor, torch.Tensor]:  # (verified, answer's) of the pairs
        at, H = t[pairs], stn_H[t[pairs]]
        if candidate_pose is not None:
            return candidate_pose(x[at], cand[at, j[pairs]], H, warped[at],
                                  None if seen_t is None else seen_t[pairs], None if factor is None else factor[at])
        if getattr(recognizer, "align", None) is not None:
            H = recognizer.align.infer(x[at], anchors[pairs], H, warped[at]).query_H_anchor
        return H, H

    def compared(pairs: list[int], H: torch.Tensor) -> torch.Tensor:
        return verification_distance(x[t[pairs]], H, anchors[pairs], blur_sigma,
                                     visibility=None if seen_t is None else seen_t[pairs], **compare)

    H, answer_H, pair_v = _posed_pairs(memo, None if keys is None else [keys[int(todo[q])] for q in t.tolist()],
                                       cand[t, j].cpu(), stn_H[t], posed_by, compared)
    v = torch.full((len(todo), k), float("inf"), dtype=torch.float64)
    v[t, j] = pair_v
    poses = torch.zeros(len(todo), k, 3, 3, dtype=torch.float64)
    poses[t, j] = answer_H.cpu().double()
    ok = v <= limit
    if widened:  # a candidate taken by its pixels is the crop's subject
        ti, tj = torch.nonzero(ok[:, features_k:], as_tuple=True)
        if len(ti):
            pair_of = torch.full((len(todo), k), -1, dtype=torch.long)  # (T, k) -> its row among the pairs
            pair_of[t, j] = torch.arange(len(t))
            pair = pair_of[ti, tj + features_k]
            share = subject_share(x[ti], H[pair], anchors[pair], None if seen is None else seen[ti.to(seen.device)])
            ok[ti, tj + features_k] = share.cpu() >= SHORTLIST_SUBJECT
    rows = torch.nonzero(ok.any(1)).flatten()
    # candidates of two orders: the one that verifies closest; of one: the first that verifies, nearest first
    col = (v[rows].masked_fill(~ok[rows], float("inf")).argmin(1) if widened
           else ok[rows].to(torch.int8).argmax(1))
    at = todo[rows]
    index[at] = cand[rows, col].cpu()
    pose[at] = poses[rows, col]
    feature_distance[at] = cand_d[rows, col].cpu().double()
    distance[at] = v[rows, col]
    tried[todo] += usable.sum(1)
    return Verification(index, pose, feature_distance, distance, distance <= verify_max, tried)


def coarse_similarity(warped: torch.Tensor, anchors: torch.Tensor, plane: torch.Tensor, cell: int) -> torch.Tensor:
    """``(T, M)`` ZNCC of each of ``warped`` ``(T, 3, S, S)`` (queries in the anchor frame at the STN's pose) with each
    of its ``M`` shortlisted anchors ``(T, M, 3, S / cell, S / cell)`` (:meth:`Gallery.coarse_images`, their
    whole-plane cells ``plane`` ``(T, M, 1, S / cell, S / cell)`` bool), both averaged over ``cell`` px cells: over
    the cells that are whole plane and where the query has data, per channel a gain and a bias left out; -1 where
    fewer than :data:`MIN_PIXELS` cells are compared."""
    pooled = F.avg_pool2d(warped.float(), cell)                                   # (T, 3, s, s)
    data = F.avg_pool2d((warped.amax(1, keepdim=True) > 0).float(), cell)        # (T, 1, s, s)
    mask = (plane & (data[:, None] > WHOLE_CELL)).float()                        # (T, M, 1, s, s)
    q = pooled[:, None].expand_as(anchors)
    count = mask.sum((2, 3, 4)).clamp(min=1.0)                                  # (T, M)
    n = mask.sum((3, 4)).clamp(min=1.0)                                         # (T, M, 1)

    def centred(x: torch.Tensor) -> torch.Tensor:
        return (x - (x * mask).sum((3, 4), keepdim=True) / n[..., None, None]) * mask

    a, b = centred(anchors), centred(q)
    corr = (a * b).sum((2, 3, 4)) / ((a * a).sum((2, 3, 4)) * (b * b).sum((2, 3, 4))).sqrt().clamp(min=1e-12)
    return corr.masked_fill(count < MIN_PIXELS, -1.0)


def shown_pixels(queries: torch.Tensor, visibility: torch.Tensor | None) -> torch.Tensor:
    """``(B, S, S)`` bool: the pixels the model-size queries ``(B, 3, S, S)`` show (brighter than
    :data:`SHOWN_LEVEL` in some channel, and visible above 0.5 in ``visibility`` ``(B, 1, S, S)`` when given)."""
    shown = queries.amax(1) > SHOWN_LEVEL
    if visibility is not None:
        shown &= visibility[:, 0].to(shown.device) > 0.5
    return shown


def covered_share(plane: torch.Tensor, shown: torch.Tensor) -> torch.Tensor:
    """``(B,)`` float: the share of each query's shown pixels ``(B, S, S)`` bool that its plane ``(B, S, S)`` bool
    covers (0 where nothing is shown)."""
    count = shown.flatten(1).sum(1).double()
    return torch.where(count > 0, (plane & shown).flatten(1).sum(1).double() / count.clamp_min(1.0),
                       torch.zeros_like(count))


def subject_share(queries: torch.Tensor, query_H_anchor: torch.Tensor, anchors: torch.Tensor,
                  visibility: torch.Tensor | None = None) -> torch.Tensor:
    """``(B,)`` the share of what each query shows (pixels brighter than :data:`SHOWN_LEVEL`, visible above one half)
    that its anchor's plane covers at the pose: near 1 for the crop's subject, low for a neighbour beside it; 0 where
    the query shows nothing.

    Args:
        queries: ``(B, 3, S, S)`` model-size queries; ``query_H_anchor``: ``(B, 3, 3)`` anchor pixel -> query pixel;
        anchors: ``(B, 3, S, S)`` (zero outside the plane); visibility: ``(B, 1, S, S)`` in [0, 1], or None (ones).
    """
    if len(queries) == 0:
        return torch.zeros(0, dtype=torch.float64)
    anchor_H_query = torch.linalg.inv(query_H_anchor.double())
    plane = (anchors.amax(1, keepdim=True) > 0).to(queries.dtype)
    covered = sample_by_normalised(plane, pixel_to_normalised(anchor_H_query, tuple(queries.shape[-2:])).to(
        plane.dtype))
    return covered_share(covered[:, 0] > 0.5, shown_pixels(queries, visibility))


def candidate_distances(recognizer: Any, queries: torch.Tensor, exclude_object: torch.Tensor | None
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(features, STN query_H_anchor, s(queries), distances (Q, G) to every anchor)``; anchors of
    ``exclude_object`` at infinity."""
    features, stn_H, _, warped = recognizer.embed_queries(queries)
    if stn_H is None:
        raise ValueError("verification needs a pose: the model has no STN")
    return features, stn_H, warped, _without_objects(recognizer.gallery, recognizer.gallery_distances(features),
                                                     exclude_object)
