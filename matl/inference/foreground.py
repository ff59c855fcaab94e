"""The foreground of RGB queries that come without a mask (a detector's box on a real background).

The model is trained on queries whose background is exactly 0 outside the product (docs/design.md), so
an RGBA query's alpha is its mask (:func:`split_alpha`). An RGB crop of a cluttered scene has no mask;
the foreground step gives it one, and the query is then used exactly as an RGBA query with that alpha:

* :class:`GrabCutForeground` (``foreground=grabcut``): OpenCV's GrabCut, initialised with the
  rectangle ``inset_px`` inside the crop's border. The border band seeds the background colour model
  (a detector's box holds the product; what the box's edge cuts, a neighbour or the shelf, is
  background), the rest starts as probable foreground. The result is opened (``open_px``), the
  largest connected component that does not touch the crop's border is kept (the largest of all when
  every one touches it: a neighbour is cut by the edge, the product is held by the box) and its holes
  are filled.
* ``retry_insets``: when the answer of a GrabCut-masked query does not verify (its pose does not explain
  the query: ``1 - ZNCC`` above ``verify_max``, :mod:`matl.inference.verify`), GrabCut runs again from
  rectangles inset by these fractions of the crop's side (:meth:`GrabCutForeground.retries`): a product
  whose colours resemble the background, or a neighbour the 2 px band did not seed, is separated by a
  wider band. Each mask is recognised and verified like the first, and the query keeps the answer that
  verifies best (the first one's if none does better). A query whose first answer verifies costs nothing.
* ``passes`` pose passes (:func:`pose_mask`): the first answer's plane, warped by its pose
  ``query_H_canon`` into the query, is a mask of the product's true outline; the query is masked again
  with it (intersected with the GrabCut alpha, so background within the pose's error stays out) and
  recognised again. The last pass is the answer.

A crop whose border band is mostly black already (the training convention: background exactly 0;
``black_fraction`` of the band, as a product may reach into it) is used as given; ``foreground=none``
leaves every RGB query as it is. An RGBA query always uses its own alpha, with any foreground setting.
GrabCut's k-means initialisation draws from OpenCV's global random generator; it is seeded (``seed``)
before every call, so a query gets the same mask every time.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from matl.geometry import warp_image
from matl.utils.errors import MatlError

__all__ = ["FOREGROUNDS", "GrabCutForeground", "foreground_option", "mask_query", "pose_mask", "split_alpha"]

FOREGROUNDS = ("none", "grabcut")


def split_alpha(image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """A float ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA array in [0, 1] as RGB ``(H, W, 3)`` with transparent
    pixels set to 0, and the alpha ``(H, W)`` (None for RGB)."""
    if image.ndim == 3 and image.shape[-1] == 4:
        alpha = np.ascontiguousarray(image[..., 3], dtype=np.float32)
        return np.ascontiguousarray(image[..., :3] * alpha[..., None], dtype=np.float32), alpha
    return image, None


@dataclass
class GrabCutForeground:
    """GrabCut from a rectangle inset from the crop's border; see the module docstring.

    Args:
        inset_px: width of the border band seeded as background, px of the query file (at least 1).
        iterations: GrabCut iterations.
        open_px: radius of the morphological opening that drops thin strands and specks (0: none).
        passes: pose passes after the first answer (0: the GrabCut mask alone).
        alpha_band_px: an RGBA query's alpha seeds GrabCut, which decides the pixels within this many px
            of the alpha's edge (what is farther in or out stays as the alpha says; 0: the alpha as given).
        black_level, black_fraction: a crop with at least ``black_fraction`` of its border band's pixels
            at most ``black_level`` (0: the training convention, exactly black) already has its mask and is
            used as given (a product may reach into the band).
        seed: OpenCV's random seed, set before each call (k-means of the colour models).
        retry_insets: fractions of the crop's side (each in (0, 0.5)): the insets of the retries of a query
            whose first answer does not verify (empty: no retries). The recognizer runs them
            (:class:`matl.inference.api.Recognizer`); they need verification (``verify_top_k`` > 0).
    """

    inset_px: int = 2
    iterations: int = 5
    open_px: int = 1
    passes: int = 0
    alpha_band_px: int = 4
    black_level: float = 0.0
    black_fraction: float = 0.5
    seed: int = 0
    retry_insets: tuple[float, ...] = (0.08, 0.12)

    def __post_init__(self) -> None:
        try:
            self.retry_insets = tuple(float(f) for f in self.retry_insets)
        except (TypeError, ValueError):
            self.retry_insets = (float("nan"),)  # reported below
        if not all(0.0 < f < 0.5 for f in self.retry_insets):
            raise MatlError(f"foreground grabcut: retry_insets={list(self.retry_insets)}: use fractions of the crop's "
                            "side in (0, 0.5), e.g. [0.08, 0.12], or [] for no retries")
        if (int(self.inset_px) < 1 or int(self.iterations) < 1 or int(self.open_px) < 0 or int(self.passes) < 0
                or int(self.alpha_band_px) < 0 or not 0.0 <= float(self.black_level) < 1.0
                or not 0.0 < float(self.black_fraction) <= 1.0):
            raise MatlError(f"foreground grabcut: inset_px={self.inset_px}, iterations={self.iterations}, "
                            f"open_px={self.open_px}, passes={self.passes}, alpha_band_px={self.alpha_band_px}, "
                            f"black_level={self.black_level}, black_fraction={self.black_fraction}: use inset_px >= 1, "
                            "iterations >= 1, open_px >= 0, passes >= 0, alpha_band_px >= 0, black_level in [0, 1) "
                            "and black_fraction in (0, 1]")

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """The alpha ``(H, W)`` float32 in {0, 1} of a float RGB ``(H, W, 3)`` crop in [0, 1].

        A crop whose border band is black (``black_level``, ``black_fraction``), one too small for the
        band, or one where nothing is found, keeps every pixel.
        """
        mask = self.segment(rgb, int(self.inset_px))
        return np.ones(rgb.shape[:2], np.float32) if mask is None else mask

    def retries(self, rgb: np.ndarray) -> list[np.ndarray]:
        """The masks ``(H, W)`` float32 in {0, 1} of GrabCut from each of ``retry_insets`` (a fraction of the
        crop's shorter side, at least ``inset_px``) for a float RGB ``(H, W, 3)`` crop in [0, 1]; none for a crop
        that :meth:`__call__` uses as given, and none where GrabCut finds nothing."""
        side = min(rgb.shape[:2])
        masks = (self.segment(rgb, max(int(self.inset_px), round(f * side))) for f in self.retry_insets)
        return [m for m in masks if m is not None]

    def segments(self, rgb: np.ndarray) -> bool:
        """Whether GrabCut runs on a float RGB ``(H, W, 3)`` crop: not on one too small for the band nor on one
        whose border band is black (``black_level``, ``black_fraction``: already segmented)."""
        h, w = rgb.shape[:2]
        inset = int(self.inset_px)
        if h <= 2 * inset + 2 or w <= 2 * inset + 2:
            return False
        band = np.ones((h, w), bool)
        band[inset:h - inset, inset:w - inset] = False
        return float((rgb[band].max(-1) <= self.black_level).mean()) < self.black_fraction

    def segment(self, rgb: np.ndarray, inset: int) -> np.ndarray | None:
        """GrabCut's mask ``(H, W)`` float32 in {0, 1} of a float RGB ``(H, W, 3)`` crop, from the rectangle
        ``inset`` px inside its border; None where the crop keeps every pixel (:meth:`segments` is false, the
        rectangle is empty, GrabCut finds nothing)."""
        h, w = rgb.shape[:2]
        if not self.segments(rgb) or h <= 2 * inset + 2 or w <= 2 * inset + 2:
            return None
        bgr = np.ascontiguousarray((np.clip(rgb, 0.0, 1.0) * 255.0).round().astype(np.uint8)[..., ::-1])
        labels = np.zeros((h, w), np.uint8)
        background, foreground = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
        cv2.setRNGSeed(int(self.seed))
        try:
            cv2.grabCut(bgr, labels, (inset, inset, w - 2 * inset, h - 2 * inset), background, foreground,
                        int(self.iterations), cv2.GC_INIT_WITH_RECT)
        except cv2.error:  # a colour model without samples (e.g. a flat image)
            return None
        mask = ((labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)).astype(np.uint8)
        if self.open_px > 0:
            k = 2 * int(self.open_px) + 1
            mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((k, k), np.uint8))
        mask = _main_component(mask)
        if not mask.any():
            return None
        return _fill_holes(mask).astype(np.float32)


    def refine_alpha(self, rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        """An RGBA query's alpha ``(H, W)`` with its edge decided by GrabCut within ``alpha_band_px`` of it.

        Args:
            rgb: ``(H, W, 3)`` float in [0, 1], the pixels *under* the alpha (not multiplied by it).
            alpha: ``(H, W)`` in [0, 1].
        Returns:
            ``(H, W)`` float32: ``alpha`` itself with ``alpha_band_px`` 0, or when the alpha has no pixel
            farther than the band inside or outside it; else in {0, 1}.
        """
        band = int(self.alpha_band_px)
        inside = (alpha > 0.5).astype(np.uint8)
        if band == 0:
            return alpha
        outside_d = cv2.distanceTransform(1 - inside, cv2.DIST_L2, 5)
        inside_d = cv2.distanceTransform(inside, cv2.DIST_L2, 5)
        labels = np.where(inside > 0, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
        labels[outside_d > band] = cv2.GC_BGD
        labels[inside_d > band] = cv2.GC_FGD
        if not (labels == cv2.GC_BGD).any() or not (labels == cv2.GC_FGD).any():
            return alpha
        bgr = np.ascontiguousarray((np.clip(rgb, 0.0, 1.0) * 255.0).round().astype(np.uint8)[..., ::-1])
        cv2.setRNGSeed(int(self.seed))
        try:
            cv2.grabCut(bgr, labels, None, np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64),
                        int(self.iterations), cv2.GC_INIT_WITH_MASK)
        except cv2.error:
            return alpha
        return ((labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)).astype(np.float32)


def mask_query(step: GrabCutForeground | None, image: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A query as the model takes it, through the foreground step ``step`` (None: no step).

    Args:
        image: float ``(H, W, 3)`` RGB or ``(H, W, 4)`` RGBA in [0, 1].
    Returns:
        ``(masked, rgb, found)``: the query with its background 0 ``(H, W, 3)``; its pixels before any mask
        ``(H, W, 3)``; and the alpha ``(H, W)`` the step found for an RGB query (None for an RGBA query,
        or without a step).
    """
    rgb = np.ascontiguousarray(image[..., :3], dtype=np.float32)
    if image.shape[-1] == 4:
        alpha = np.ascontiguousarray(image[..., 3], dtype=np.float32)
        if step is not None:
            alpha = step.refine_alpha(rgb, alpha)
        return np.ascontiguousarray(rgb * alpha[..., None]), rgb, None
    if step is None:
        return rgb, rgb, None
    found = step(rgb)
    return np.ascontiguousarray(rgb * found[..., None]), rgb, found


def _main_component(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected component of ``mask`` ``(H, W)`` uint8 that does not touch the border (the
    largest of all if every one does); all zeros when there is none."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if count <= 1:
        return np.zeros_like(mask)
    h, w = mask.shape
    x, y, bw, bh, area = (stats[1:, i] for i in range(5))
    touches = (x == 0) | (y == 0) | (x + bw == w) | (y + bh == h)
    pool = np.flatnonzero(~touches) if (~touches).any() else np.arange(count - 1)
    best = 1 + int(pool[np.argmax(area[pool])])
    return (labels == best).astype(np.uint8)


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` ``(H, W)`` uint8 with every background region that does not reach the border filled."""
    _, labels = cv2.connectedComponents((1 - mask).astype(np.uint8), connectivity=4)
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    holes = np.isin(labels, edge, invert=True) & (labels > 0)
    return (mask.astype(bool) | holes).astype(np.uint8)


def pose_mask(canon: torch.Tensor, query_H_canon: torch.Tensor, size: int) -> torch.Tensor:
    """The planes' foreground in the query's model frame: ``(B, 1, S, S)`` in [0, 1] (bilinear edge).

    Args:
        canon: ``(B, 3, S, S)`` canonical images of the answered planes (background exactly 0).
        query_H_canon: ``(B, 3, 3)`` their poses, canonical model frame -> query model frame.
        size: ``S``.
    """
    mask = (canon.amax(1, keepdim=True) > 0).float()
    return warp_image(mask, query_H_canon.float(), (size, size)).clamp(0.0, 1.0)


def foreground_option(value: Any) -> GrabCutForeground | None:
    """The foreground step of a ``foreground`` value: ``none`` or None (no step), ``grabcut`` (the defaults),
    a :class:`GrabCutForeground`, or a config node (``conf/foreground/*.yaml``: ``_target_`` null for none).

    Raises:
        MatlError: any other value, or a node with a bad setting.
    """
    if value is None or isinstance(value, GrabCutForeground):
        return value
    if isinstance(value, str):
        if value == "none":
            return None
        if value == "grabcut":
            return GrabCutForeground()
    elif isinstance(value, Mapping) and "_target_" in value:
        if value["_target_"] is None:
            return None
        from matl.utils.instantiate import instantiate_node

        step = instantiate_node(value, "foreground")
        if isinstance(step, GrabCutForeground):
            return step
    raise MatlError(f"foreground={value!r} is invalid: use {' or '.join(FOREGROUNDS)} (RGB queries without a mask)")
