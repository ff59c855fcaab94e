"""SIFT + RANSAC + ECC baseline (beyond the paper): RANSAC's homography refined by direct alignment.

The strongest classical pipeline a practitioner would build on row (d): recognise and register a
query exactly as :class:`matl.baselines.sift.SiftRansacMatcher` does (same features, ratio test,
RANSAC voting, so the same gallery index and inlier count), then refine ``query_H_anchor`` by
maximising the enhanced correlation coefficient (ECC, Evangelidis & Psarakis, PAMI 2008) between
the matched gallery image and the query with OpenCV's ``MOTION_HOMOGRAPHY`` ECC, starting from
RANSAC's estimate.

* **Template and mask.** The template is the matched gallery (anchor) image in grey (float BT.601
  luma); its mask is the anchor's foreground: a pixel brighter than ``FOREGROUND`` in any channel.
  Gallery images come from RGBA renders or photos with the background exactly 0 (RGB multiplied by
  alpha), and only their RGB reaches a matcher, so the foreground is read off the image, by the same
  rule as the photometric refiner (``matl/inference/refine.py``). The correlation is thus measured
  on the product only. The template mask needs ``cv2.findTransformECCWithMask`` (newer OpenCV
  releases, 5.0 here); an older OpenCV gets a one-line error at construction. (``findTransformECC``
  masks only the *input*: carrying the anchor's mask into the query by RANSAC's homography and
  passing it there was worse than RANSAC alone on validation queries, so it is not offered.)
* **Direction.** ECC finds ``W`` with ``input(W x) ~ template(x)``: ``W`` maps template pixels to
  input pixels. With the anchor as template and the query as input, ``W`` *is* ``query_H_anchor``
  (anchor pixels -> query pixels), no inverse. OpenCV's pixel convention is the project's:
  ``(0, 0)`` the centre of the top-left pixel.
* **Coarse to fine** (``levels`` > 1): Gaussian pyramids by ``cv2.pyrDown``, whose pixel ``i``
  sits at pixel ``2 i`` of the level below, so a homography moves between levels by
  ``S H S^-1`` with ``S = diag(1/2, 1/2, 1)``.
* **Guard.** RANSAC's homography is kept, bit for bit, when ECC fails at any level (``cv2.error``,
  which includes OpenCV's non-convergence errors, or a non-finite or degenerate matrix) or when the
  refined homography moves any anchor image corner by more than ``max_corner_shift_px`` query
  pixels from RANSAC's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from matl.baselines.keypoints import MatchResult, check_image_batch, to_gray_float
from matl.baselines.sift import SiftRansacMatcher

__all__ = ["FOREGROUND", "EccRefinement", "EccRefiner", "SiftEccMatcher", "corner_shift_px", "foreground_masks"]

FOREGROUND = 1e-3  # a pixel brighter than this in any channel is foreground (backgrounds are exactly 0)


def foreground_masks(images: torch.Tensor) -> np.ndarray:
    """``(B, H, W)`` uint8 masks (1 on the foreground) of RGB images ``(B, 3, H, W)`` in [0, 1]."""
    return (images > FOREGROUND).any(dim=1).to(torch.uint8).numpy()


def _scale_homography(H: np.ndarray, factor: float) -> np.ndarray:
    """``S H S^-1`` with ``S = diag(factor, factor, 1)``: ``H`` in pixels of an image resized by ``factor``."""
    S = np.diag([factor, factor, 1.0])
    S_inv = np.diag([1.0 / factor, 1.0 / factor, 1.0])
    return S @ H @ S_inv


def _corners(size: tuple[int, int]) -> np.ndarray:
    """The 4 corner pixel centres ``(3, 4)`` homogeneous of an image of ``size`` (H, W)."""
    h, w = size
    return np.array([[0.0, w - 1.0, w - 1.0, 0.0], [0.0, 0.0, h - 1.0, h - 1.0], [1.0, 1.0, 1.0, 1.0]])


def corner_shift_px(H_a: np.ndarray, H_b: np.ndarray, size: tuple[int, int]) -> float:
    """Largest distance (px) between the 4 corners of an image of ``size`` mapped by ``H_a`` and ``H_b``.

    ``inf`` where either homography sends a corner to (or beyond) infinity.
    """
    c = _corners(size)
    a, b = H_a @ c, H_b @ c
    if not (np.all(a[2] > 1e-12) or np.all(a[2] < -1e-12)) or not (np.all(b[2] > 1e-12) or np.all(b[2] < -1e-12)):
        return float("inf")
    shift = np.linalg.norm(a[:2] / a[2] - b[:2] / b[2], axis=0).max()
    return float(shift) if np.isfinite(shift) else float("inf")


@dataclass
class EccRefinement:
    """The result of refining one homography.

    Attributes:
        query_H_anchor: ``(3, 3)`` float64, ``H[2, 2] == 1``; the input homography itself unless
            ``outcome == "refined"``.
        outcome: ``"refined"`` (ECC's estimate kept), ``"failed"`` (``cv2.error`` or a non-finite /
            degenerate result at some level) or ``"rejected"`` (a corner moved too far).
        corner_shift_px: the largest corner move of ECC's estimate (NaN when it failed).
    """

    query_H_anchor: np.ndarray
    outcome: str
    corner_shift_px: float


class EccRefiner:
    """``cv2.findTransformECCWithMask`` with ``MOTION_HOMOGRAPHY``, coarse to fine, guarded (module docstring).

    Args:
        iterations: ECC iterations per pyramid level (``criteria.maxCount``).
        epsilon: ECC stops at a level once the correlation coefficient changes by less than this.
        gauss_filter_size: odd size of the Gaussian blur ECC applies to both images and masks
            (1: no blur).
        levels: pyramid levels (1: full resolution only).
        max_corner_shift_px: ECC's estimate is rejected if it moves any anchor image corner by
            more than this many query pixels from the starting homography.
    """

    def __init__(self, iterations: int = 50, epsilon: float = 1e-6, gauss_filter_size: int = 5, levels: int = 1,
                 max_corner_shift_px: float = 10.0) -> None:
        if int(iterations) < 1:
            raise ValueError(f"ecc iterations must be >= 1, got {iterations}")
        if int(gauss_filter_size) < 1 or int(gauss_filter_size) % 2 == 0:
            raise ValueError(f"ecc gauss_filter_size must be a positive odd integer, got {gauss_filter_size}")
        if int(levels) < 1:
            raise ValueError(f"ecc levels must be >= 1, got {levels}")
        if not max_corner_shift_px > 0:
            raise ValueError(f"max_corner_shift_px must be > 0, got {max_corner_shift_px}")
        if not hasattr(cv2, "findTransformECCWithMask"):
            raise ValueError(f"ECC with a template mask needs cv2.findTransformECCWithMask, which OpenCV "
                             f"{cv2.__version__} lacks: install a newer opencv-python-headless (5.0 has it)")
        self.iterations = int(iterations)
        self.epsilon = float(epsilon)
        self.gauss_filter_size = int(gauss_filter_size)
        self.levels = int(levels)
        self.max_corner_shift_px = float(max_corner_shift_px)

    def _pyramid(self, image: np.ndarray) -> list[np.ndarray]:
        """Finest first, ``levels`` images (fewer if an image would get smaller than 8 px)."""
        out = [image]
        while len(out) < self.levels and min(out[-1].shape[:2]) >= 16:
            out.append(cv2.pyrDown(out[-1]))
        return out

    def _ecc(self, template: np.ndarray, query: np.ndarray, mask: np.ndarray, H: np.ndarray) -> np.ndarray:
        """One ECC run at one level; returns ECC's ``(3, 3)`` float64 warp. Raises ``cv2.error``."""
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, self.iterations, self.epsilon)
        warp = H.astype(np.float32)  # ECC wants a float32 warp
        everywhere = np.ones(query.shape[:2], np.uint8)  # every query pixel is valid
        _, warp = cv2.findTransformECCWithMask(template, query, mask, everywhere, warp, cv2.MOTION_HOMOGRAPHY,
                                               criteria, self.gauss_filter_size)
        return np.asarray(warp, dtype=np.float64)

    def __call__(self, template: np.ndarray, template_mask: np.ndarray, query: np.ndarray,
                 query_H_anchor: np.ndarray) -> EccRefinement:
        """Refine ``query_H_anchor`` of one query.

        Args:
            template: ``(h, w)`` float32 grey anchor image.
            template_mask: ``(h, w)`` uint8, non-zero on the anchor's foreground.
            query: ``(H, W)`` float32 grey query image.
            query_H_anchor: ``(3, 3)`` starting homography (anchor pixels -> query pixels).
        """
        start = np.asarray(query_H_anchor, dtype=np.float64)
        templates, masks, queries = self._pyramid(template), self._pyramid(template_mask), self._pyramid(query)
        levels = min(len(templates), len(queries))
        H = _scale_homography(start, 0.5 ** (levels - 1))
        for level in reversed(range(levels)):
            if level < levels - 1:
                H = _scale_homography(H, 2.0)
            try:
                H = self._ecc(templates[level], queries[level], masks[level], H)
            except cv2.error:
                return EccRefinement(start, "failed", float("nan"))
            if not np.isfinite(H).all() or abs(H[2, 2]) < 1e-12:
                return EccRefinement(start, "failed", float("nan"))
            H = H / H[2, 2]
        shift = corner_shift_px(H, start, template.shape[:2])
        if not shift <= self.max_corner_shift_px:
            return EccRefinement(start, "rejected", shift)
        return EccRefinement(H, "refined", shift)


class SiftEccMatcher(SiftRansacMatcher):
    """SIFT + RANSAC (:class:`SiftRansacMatcher`, unchanged) followed by ECC refinement of the pose.

    Args:
        ecc_iterations, ecc_epsilon, ecc_gauss_filter_size, ecc_levels, max_corner_shift_px: the
            :class:`EccRefiner`'s ``iterations``, ``epsilon``, ``gauss_filter_size``, ``levels`` and
            ``max_corner_shift_px``.
        **sift: the arguments of :class:`SiftRansacMatcher` (recognition and RANSAC's homography).
    """

    def __init__(self, ecc_iterations: int = 50, ecc_epsilon: float = 1e-6, ecc_gauss_filter_size: int = 5,
                 ecc_levels: int = 1, max_corner_shift_px: float = 10.0, **sift: Any) -> None:
        super().__init__(**sift)
        self.refiner = EccRefiner(ecc_iterations, ecc_epsilon, ecc_gauss_filter_size, ecc_levels, max_corner_shift_px)
        self.templates: np.ndarray | None = None
        self.template_masks: np.ndarray | None = None

    def index_gallery(self, gallery: torch.Tensor) -> None:
        """SIFT features of every gallery image ``(G, 3, H, W)``, plus its grey template and foreground."""
        super().index_gallery(gallery)
        gallery = check_image_batch(gallery, "gallery")
        self.templates = to_gray_float(gallery.float())[:, 0].numpy().astype(np.float32)
        self.template_masks = foreground_masks(gallery)

    def refine(self, query: torch.Tensor, gallery_index: int, query_H_anchor: np.ndarray) -> EccRefinement:
        """ECC refinement of one query ``(3, H, W)`` against gallery image ``gallery_index``."""
        if self.templates is None or self.template_masks is None:
            raise RuntimeError(f"{type(self).__name__}.refine called before index_gallery(gallery)")
        grey = to_gray_float(query[None].float())[0, 0].numpy().astype(np.float32)
        return self.refiner(self.templates[gallery_index], self.template_masks[gallery_index], grey, query_H_anchor)

    def match(self, queries: torch.Tensor) -> MatchResult:
        """SIFT + RANSAC's recognition of queries ``(Q, 3, H, W)``, with each matched pose refined by ECC."""
        result = super().match(queries)
        queries = check_image_batch(queries, "queries")
        homs = result.query_H_anchor.clone()
        for i, g in enumerate(result.gallery_index.tolist()):
            if g >= 0:
                homs[i] = torch.from_numpy(self.refine(queries[i], g, homs[i].numpy()).query_H_anchor)
        return MatchResult(gallery_index=result.gallery_index, query_H_anchor=homs, inliers=result.inliers)
