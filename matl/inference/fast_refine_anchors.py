"""The anchor side of the fast refiner (:mod:`matl.inference.fast_refine`): what it precomputes per gallery anchor.

* :class:`AnchorLevel`: one anchor at one pyramid level: its luminance, foreground, loss region, the band-eroded
  foreground the query's visibility weighs, the steepest-descent images ``sd = grad(A) dW/dp`` at the pixels that
  carry a gradient and the Gauss-Newton Hessian ``sd^T sd`` (none of them depends on the query).
* :class:`AnchorTemplates`: a gallery's levels, per anchor (finest first), with ``region=auto``'s foreground levels
  and outside masks and the anchors at other resolutions computed so far.
* :func:`anchor_levels`: one anchor's levels for each region kind, from its luminance and foreground; and the
  helpers the query side shares with it: the pyramid (:func:`image_pyramid`), the luminance of a batch
  (:func:`luminance`), the blur (:func:`blurred`), the frame of a level (:func:`norm_H_pixel`: level pixels ->
  full-resolution normalised coordinates, ``align_corners=True``) and ``region=auto``'s outside mask
  (:func:`outside_mask`).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from matl.inference import fast_refine_kernels as kernels

__all__ = ["CORNERS", "FOREGROUND", "LUMA", "AnchorLevel", "AnchorTemplates", "anchor_levels", "blurred",
           "image_pyramid", "luminance", "norm_H_pixel", "outside_mask"]

FOREGROUND = 1e-3  # an anchor pixel brighter than this in any channel is foreground (backgrounds are 0)
LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)  # ITU-R BT.601, as PhotometricRefiner
#: the normalised image corners, homogeneous ``(4, 3)``
CORNERS = np.array([[-1.0, -1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 1.0, 1.0], [-1.0, 1.0, 1.0]])


def _corner_jacobian() -> np.ndarray:
    """``(8, 8)``: ``p @ J`` is the first-order motion ``(x0, y0, x1, y1, ...)`` of the 4 normalised corners
    under ``I + D(p)``."""
    rows = []
    for x, y in CORNERS[:, :2]:
        rows.append([x, y, 1.0, 0.0, 0.0, 0.0, -x * x, -x * y])
        rows.append([0.0, 0.0, 0.0, x, y, 1.0, -x * y, -y * y])
    return np.array(rows).T


_CORNER_J = _corner_jacobian()


@dataclass
class AnchorLevel:
    """What one anchor contributes at one pyramid level (``n`` pixels carry a gradient).

    Attributes:
        image: ``(h, w)`` float32 luminance, 0 off the foreground.
        fg: ``(h, w)`` float32 foreground indicator ``F`` (the gain / bias fit's support).
        region: ``(h, w)`` float32 0/1 pixels of the loss (``region=foreground``); None: all (``frame``).
        inner: ``(h, w)`` float32 0/1 the foreground less a band along its outline (``visibility_band``), where the
            query's visibility weighs the pixels.
        size: ``(h, w)`` of the level.
        count: pixels of ``F``; ``mean`` ``A``'s mean over them, ``var`` ``sum_F (A - mean)^2``.
        total: ``sum(region)``: the loss is a mean over these pixels.
        index: ``(n,)`` int32 flat pixel indices where ``sd`` is non-zero (inside the region).
        sdT: ``(8, n)`` float32 steepest-descent images ``d A(W(x; p)) / dp`` at ``p = 0`` (normalised ``p``),
            transposed.
        hessian: ``(8, 8)`` float64 ``sd^T sd``.
        norm_H_pixel: ``(3, 3)`` this level's pixels -> full-resolution normalised coordinates.
        pixel_H_norm: its inverse.
    """

    image: np.ndarray
    fg: np.ndarray
    region: np.ndarray | None
    inner: np.ndarray
    size: tuple[int, int]
    count: float
    mean: float
    var: float
    total: float
    index: np.ndarray
    sdT: np.ndarray
    hessian: np.ndarray
    norm_H_pixel: np.ndarray
    pixel_H_norm: np.ndarray
    #: derived once (not arguments): ``1 / var``, ``1 / count``, and
    #: ``corner_J`` ``(8, 8)``: ``dp @ corner_J`` is the motion of the 4 corners in this level's pixels
    inv_var: float = field(init=False, repr=False)
    inv_count: float = field(init=False, repr=False)
    corner_J: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        h, w = self.size
        self.inv_var = 1.0 / max(self.var, 1e-12)
        self.inv_count = 1.0 / max(self.count, 1.0)
        self.corner_J = _CORNER_J * np.array([(w - 1) / 2.0, (h - 1) / 2.0] * 4)

    @property
    def nbytes(self) -> int:
        arrays = (self.image, self.fg, self.inner, self.index, self.sdT, self.hessian)
        return sum(a.nbytes for a in arrays) + (self.region.nbytes if self.region is not None else 0)


@dataclass
class AnchorTemplates:
    """:class:`~matl.inference.fast_refine.FastRefiner`'s data of a gallery: per anchor, one :class:`AnchorLevel`
    per level, finest first.

    A large gallery's (more anchors than the refiner's ``precompute``) are computed anchor by anchor when a query
    first needs them (:meth:`~matl.inference.fast_refine.FastRefiner.anchor_levels`): ``anchors[k]`` is None until
    then, and again once ``k`` is the least recently used of more than ``keep`` computed anchors.

    Attributes:
        anchors: one list of levels per anchor (None: not computed, a large gallery's).
        image_size: ``(H, W)`` of the anchors.
        seconds: time taken to compute them at enrolment.
    """

    anchors: list[list[AnchorLevel] | None]
    image_size: tuple[int, int]
    seconds: float = field(default=0.0)
    #: ``region=auto``: per anchor, its ``region=foreground`` levels (None otherwise)
    foreground: list[list[AnchorLevel]] | None = None
    #: ``region=auto``: per anchor, ``(H, W)`` uint8 1 where the anchor frame is farther than ``auto_band`` px
    #: from the anchor's foreground (None otherwise)
    outside: list[np.ndarray] | None = None
    #: the anchor images ``(G, 3, H, W)`` they were computed from (a reference: an anchor at another resolution is
    #: computed from them when first needed)
    source: torch.Tensor | None = None
    #: ``(anchor, side) -> (levels, foreground levels, outside)`` of anchors at another resolution, least recently
    #: used first
    resampled: OrderedDict = field(default_factory=OrderedDict, repr=False)
    #: a large gallery's: at most this many anchors computed at first need are kept (None: all computed at enrolment)
    keep: int | None = None
    #: those anchors, least recently used first
    computed: OrderedDict = field(default_factory=OrderedDict, repr=False)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def __len__(self) -> int:
        return len(self.anchors)

    def held(self, k: int) -> tuple[list[AnchorLevel] | None, list[AnchorLevel] | None, np.ndarray | None]:
        """Anchor ``k``'s ``(levels, region=auto's foreground levels, outside mask)`` as held (None where not)."""
        return (self.anchors[k], None if self.foreground is None else self.foreground[k],
                None if self.outside is None else self.outside[k])

    @property
    def nbytes(self) -> int:
        """Memory held, bytes."""
        held = sum(level.nbytes for anchor in self.anchors if anchor is not None for level in anchor)
        held += sum(level.nbytes for anchor in self.foreground or () if anchor is not None for level in anchor)
        held += sum(level.nbytes for levels, fg, _ in self.resampled.values() for level in (*levels, *(fg or ())))
        held += sum(out.nbytes for _, _, out in self.resampled.values() if out is not None)
        return held + sum(mask.nbytes for mask in self.outside or () if mask is not None)


def image_pyramid(image: np.ndarray, levels: int, min_size: int) -> list[np.ndarray]:
    """Finest first; level ``l``'s pixel ``i`` is centred on the full image's pixel ``2^l i`` (``cv2.pyrDown``)."""
    out = [image]
    while len(out) < levels and min(out[-1].shape) // 2 >= min_size:
        out.append(cv2.pyrDown(out[-1]))
    return out


def luminance(images: torch.Tensor) -> list[tuple[np.ndarray, float]]:
    """``(B, 3, H, W)`` (or ``(B, 1, H, W)``) -> per image, its ``(H, W)`` float32 luminance and the std of its
    foreground (pixels above ``FOREGROUND``)."""
    array = images.detach()
    array = (array if array.dtype == torch.float32 and array.device.type == "cpu" else array.float().cpu()).numpy()
    return [kernels.luminance(image, LUMA, FOREGROUND) for image in array]


def norm_H_pixel(level: int, size: tuple[int, int]) -> np.ndarray:
    """``(3, 3)``: pyramid level ``level``'s pixels -> normalised coordinates of the full image ``size`` ``(H, W)``
    (``align_corners=True``)."""
    H, W = size
    f = float(2 ** level)
    return np.array([[2.0 * f / (W - 1), 0.0, -1.0], [0.0, 2.0 * f / (H - 1), -1.0], [0.0, 0.0, 1.0]])


def blurred(image: np.ndarray, blur: float) -> np.ndarray:
    """``image`` ``(H, W)`` under a Gaussian of std ``blur`` px (zeros outside), or itself (``blur=0``)."""
    if blur <= 0:
        return image
    return cv2.GaussianBlur(image, (0, 0), blur, borderType=cv2.BORDER_CONSTANT)


def outside_mask(fg: np.ndarray, band: int) -> np.ndarray:
    """``region=auto``'s ``(H, W)`` uint8 mask of an anchor: 1 where its frame is farther than ``band`` px from its
    foreground ``fg`` ``(H, W)`` (non-zero pixels)."""
    size = 2 * band + 1
    kernel = np.ones((size, size), np.uint8)
    return (cv2.dilate((fg > 0).astype(np.uint8), kernel) == 0).astype(np.uint8)


def anchor_levels(gray: np.ndarray, fg: np.ndarray, kinds: Sequence[str], levels: int, min_size: int, erode: int,
                  visibility_band: int, blur: float) -> list[list[AnchorLevel]]:
    """One anchor's levels for each region kind in ``kinds`` (``frame`` / ``foreground``), finest first; the
    pyramid and the gradients are computed once for all of them.

    Args:
        gray: ``(H, W)`` float32 luminance of the anchor.
        fg: ``(H, W)`` float32 its foreground indicator.
        kinds: the region kinds, one list of levels each.
        levels, min_size: the pyramid's levels and its smallest side (:func:`image_pyramid`).
        erode: ``foreground`` kinds: pixels by which the foreground is eroded at every level.
        visibility_band: px at full resolution (halved per level, at least 1) along the outline left out of
            :attr:`AnchorLevel.inner` (0: none).
        blur: std in px of a Gaussian applied to the luminance first (:func:`blurred`).
    """
    size = gray.shape
    gray = blurred(gray, blur)
    out: list[list[AnchorLevel]] = [[] for _ in kinds]
    masks = image_pyramid(fg, levels, min_size)
    kernel = np.ones((2 * erode + 1, 2 * erode + 1), np.uint8)
    for level, image in enumerate(image_pyramid(gray, levels, min_size)):
        h, w = image.shape
        mask = (masks[level] > FOREGROUND).astype(np.float32)  # the blurred support at coarse levels
        image = image * mask
        padded = np.pad(image, 1, mode="edge")  # central differences, one-sided at the border
        gx = (padded[1:-1, 2:] - padded[1:-1, :-2]) * 0.5
        gy = (padded[2:, 1:-1] - padded[:-2, 1:-1]) * 0.5
        level_norm_H_pixel = norm_H_pixel(level, size)
        pixel_H_norm = np.linalg.inv(level_norm_H_pixel)
        gx, gy = gx / level_norm_H_pixel[0, 0], gy / level_norm_H_pixel[1, 1]  # per normalised unit
        textured = (gx != 0) | (gy != 0)
        band = max(1, round(visibility_band / 2 ** level)) if visibility_band > 0 else 0
        inner = (cv2.erode(mask, np.ones((2 * band + 1, 2 * band + 1), np.uint8), borderType=cv2.BORDER_CONSTANT,
                           borderValue=0) if band else mask).astype(np.float32)
        for kind_levels, kind in zip(out, kinds, strict=True):
            region = None
            if kind != "frame":
                region = cv2.erode(mask, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) if erode \
                    else mask.copy()
            inside = textured if region is None else textured & (region > 0)
            index = np.flatnonzero(inside).astype(np.int32)
            x = (index % w) * level_norm_H_pixel[0, 0] - 1.0
            y = (index // w) * level_norm_H_pixel[1, 1] - 1.0
            gxs, gys = gx.ravel()[index], gy.ravel()[index]
            radial = gxs * x + gys * y
            sd = np.stack([gxs * x, gxs * y, gxs, gys * x, gys * y, gys, -radial * x, -radial * y])  # (8, n)
            fit = mask if region is None else region  # the gain / bias fit's support: the loss's foreground
            count = float(fit.sum())
            mean = float((image * fit).sum() / max(count, 1.0))
            var = float(((image - mean) ** 2 * fit).sum())
            kind_levels.append(AnchorLevel(
                np.ascontiguousarray(image if region is None else image * region, dtype=np.float32),
                np.ascontiguousarray(fit, dtype=np.float32),
                None if region is None else np.ascontiguousarray(region, dtype=np.float32),
                np.ascontiguousarray(inner), (int(h), int(w)),
                count, mean, var, float(max(h * w if region is None else region.sum(), 1.0)), index,
                np.ascontiguousarray(sd, dtype=np.float32), sd @ sd.T, level_norm_H_pixel, pixel_H_norm))
    return out
