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
* :class:`LearnedForeground` (``foreground=learned``): the visibility network
  (:mod:`matl.models.visibility`, ``python -m matl.train_foreground``) gives each pixel the probability that
  it shows the visible print of the crop's target product (background, neighbours cut by the crop's edge
  and occluders in front of it are out); it is thresholded, the largest connected component overlapping
  the crop's centre region is kept (and further parts of it an occluder split off), and holes are filled
  only where the probability is high, so an occluder's hole stays out. Its soft probability is
  :meth:`LearnedForeground.probability`. It runs in onnxruntime (torch where onnxruntime is missing).
  With ``grabcut_iterations`` the mask is GrabCut's started from that probability (what the network rules
  out is background, the rest probable foreground): the edge follows the crop's colours at full size
  where the network's 64 px map is blunt.
* ``retry_insets``: when the answer of a GrabCut-masked query does not verify (its pose does not explain
  the query: ``1 - ZNCC`` above ``verify_max``, :mod:`matl.inference.verify`), GrabCut runs again from
  rectangles inset by these fractions of the crop's side (:meth:`GrabCutForeground.retries`): a product
  whose colours resemble the background, or a neighbour the 2 px band did not seed, is separated by a
  wider band. Each mask is recognised and verified like the first, and the query keeps the answer that
  verifies best (the first one's if none does better). A query whose first answer verifies costs nothing.
  ``foreground=learned`` retries at other thresholds of the probability (``retry_thresholds``) and with
  GrabCut's masks from rectangles inset by ``retry_insets`` (0: the border band alone), which do not lean on
  the network.
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

import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from matl.geometry import warp_image
from matl.utils.errors import MatlError
from matl.utils.threads import thread_map

__all__ = ["FOREGROUNDS", "ForegroundStep", "GrabCutForeground", "LearnedForeground", "foreground_option",
           "mask_query", "pose_mask", "split_alpha"]

FOREGROUNDS = ("none", "grabcut", "learned")
#: values of ``foreground.runtime`` (``foreground=learned``)
LEARNED_RUNTIMES = ("onnxruntime", "torch")
#: largest difference accepted between the visibility network in onnxruntime and in torch (logits)
ONNX_TOLERANCE = 1e-4


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
        max_side: a crop whose longer side is larger is segmented on a copy resized to this many px (area
            averaging; the inset and the opening scaled with it) and its mask resized back (GrabCut's time grows
            with the pixels: seconds for a 1000 px crop); None: at the crop's own size.
    """

    inset_px: int = 2
    iterations: int = 2
    open_px: int = 1
    passes: int = 0
    alpha_band_px: int = 4
    black_level: float = 0.0
    black_fraction: float = 0.5
    seed: int = 0
    retry_insets: tuple[float, ...] = (0.08, 0.12)
    max_side: int | None = 200

    def __post_init__(self) -> None:
        if self.max_side is not None and (isinstance(self.max_side, bool) or int(self.max_side) < 16):
            raise MatlError(f"foreground grabcut: max_side={self.max_side}: use a side in px >= 16 (e.g. 200), or null "
                            "to segment every crop at its own size")
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

    @property
    def retrying(self) -> bool:
        """Whether a query whose answer does not verify is masked again (:meth:`retries`)."""
        return bool(self.retry_insets)

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
        insets = [max(int(self.inset_px), round(f * side)) for f in self.retry_insets]
        masks = thread_map(lambda inset: self.segment(rgb, inset), insets)  # over torch's threads
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
        factor = 1.0 if self.max_side is None else min(1.0, int(self.max_side) / max(h, w))
        if factor < 1.0:  # segmented small, the mask resized back
            size = (max(1, round(w * factor)), max(1, round(h * factor)))
            small = cv2.resize(np.ascontiguousarray(rgb, dtype=np.float32), size, interpolation=cv2.INTER_AREA)
            mask = self._segment_at(small, max(1, round(inset * factor)))
            if mask is None:
                return None
            mask = cv2.resize(mask, (w, h), interpolation=cv2.INTER_LINEAR) > 0.5
            return mask.astype(np.float32) if mask.any() else None
        return self._segment_at(rgb, inset)

    def _segment_at(self, rgb: np.ndarray, inset: int) -> np.ndarray | None:
        """:meth:`segment` of ``rgb`` as it is (its size, ``inset`` px)."""
        h, w = rgb.shape[:2]
        if h <= 2 * inset + 2 or w <= 2 * inset + 2:
            return None
        labels = np.full((h, w), cv2.GC_BGD, np.uint8)  # the rectangle: probable foreground inside, background out
        labels[inset:h - inset, inset:w - inset] = cv2.GC_PR_FGD
        if not _grabcut_labels(rgb, labels, int(self.iterations), int(self.seed)):
            return None  # a colour model without samples (e.g. a flat image)
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
        return _grabcut_alpha(rgb, alpha, int(self.alpha_band_px), int(self.iterations), int(self.seed))


def _grabcut_alpha(rgb: np.ndarray, alpha: np.ndarray, band: int, iterations: int, seed: int) -> np.ndarray:
    """An alpha ``(H, W)`` in [0, 1] of the float RGB ``(H, W, 3)`` pixels under it with its edge decided by GrabCut
    (``iterations``, ``seed``) within ``band`` px of it: ``(H, W)`` float32 in {0, 1}, or ``alpha`` itself with
    ``band`` 0, when the alpha has no pixel farther than the band inside or outside it, or GrabCut cannot run."""
    if band == 0:
        return alpha
    inside, outside_d, inside_d = _edge_distances(alpha)
    labels = np.where(inside, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
    labels[outside_d > band] = cv2.GC_BGD
    labels[inside_d > band] = cv2.GC_FGD
    if not (labels == cv2.GC_BGD).any() or not (labels == cv2.GC_FGD).any():
        return alpha
    if not _grabcut_labels(rgb, labels, iterations, seed):
        return alpha
    return ((labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)).astype(np.float32)


def _edge_distances(alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An alpha ``(H, W)``'s pixels above 0.5 (bool) and each pixel's distance, px, to the nearest pixel inside it
    (0 inside) and to the nearest outside it (0 outside): where its edge lies and how far."""
    inside = (alpha > 0.5).astype(np.uint8)
    return (inside > 0, cv2.distanceTransform(1 - inside, cv2.DIST_L2, 5),
            cv2.distanceTransform(inside, cv2.DIST_L2, 5))


def _grabcut_labels(rgb: np.ndarray, labels: np.ndarray, iterations: int, seed: int) -> bool:
    """GrabCut of a float RGB ``(H, W, 3)`` crop in [0, 1] from ``labels`` ``(H, W)`` uint8 (OpenCV's ``GC_*``
    values), updated in place; False where GrabCut cannot run (a colour model without samples). OpenCV's random
    generator is seeded with ``seed`` first (k-means of the colour models)."""
    bgr = np.ascontiguousarray((np.clip(rgb, 0.0, 1.0) * 255.0).round().astype(np.uint8)[..., ::-1])
    cv2.setRNGSeed(int(seed))
    try:
        cv2.grabCut(bgr, labels, None, np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64),
                    int(iterations), cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return False
    return True


@dataclass
class LearnedForeground:
    """The visibility network's mask of the crop's target product; see the module docstring.

    Args:
        weights: a visibility checkpoint (``python -m matl.train_foreground publish=<file>``); None: the one
            shipped in the package (:data:`matl.models.visibility.FOREGROUND_WEIGHTS`).
        size: the working size the crop is resized to (a multiple of 8); None: the one the network was
            trained at.
        threshold: probability above which a pixel is the product's.
        retry_thresholds: thresholds (each in (0, 1)) of the retries of a query whose first answer does not
            verify (empty: no retries); the recognizer runs them, they need verification.
        centre: side of the crop's centre region, a fraction of the crop's side: the kept component overlaps it.
        min_part: a further component overlapping the centre region is kept when its area is at least this
            fraction of the largest one's (an occluder across the product splits it; 1: the largest alone).
        hole_area: a hole (a region left out that does not reach the crop's border) is filled when it is at most
            this fraction of the mask's area ...
        hole_probability: ... and its mean probability is at least this (an occluder's hole is near 0: kept out).
        alpha_band_px: an RGBA query's alpha: the pixels within this many px of its edge are decided by the
            network's mask, or with ``grabcut_iterations`` by GrabCut (0: the alpha as given).
        passes: pose passes after the first answer (as :class:`GrabCutForeground`'s).
        black_level, black_fraction: a crop whose border band (2 px) has at least ``black_fraction`` of its pixels
            at most ``black_level`` already has its mask (background 0, the training convention): used as given
            (``black_fraction`` None: every crop goes through the network).
        runtime: ``onnxruntime`` (the network exported in memory and checked against torch) or ``torch``.
        threads: onnxruntime's intra-op threads; None: torch's thread count at each call.
        grabcut_iterations: > 0: the first mask is GrabCut's, started from the network's probability (pixels
            below ``background_below`` and the crop's ``band_px`` border band are background, the rest probable
            foreground) for this many iterations, then cleaned up as the network's own mask (its edge follows the
            crop's colours where the network's 64 px map is blunt; the occluders and neighbours the network rules
            out stay out). 0: the thresholded probability alone. The retries are ``retry_thresholds``' and
            ``retry_insets``' masks.
        background_below: probability below which a pixel is background for GrabCut.
        band_px: width of the border band seeded as background for GrabCut, px of the crop.
        max_side: GrabCut runs on a copy of a crop whose longer side is larger, resized to this side (None: at
            the crop's own size).
        seed: OpenCV's random seed, set before each GrabCut call.
        min_kept: GrabCut's mask is taken when its area is at least this share of the network's own mask's (a
            smaller one has taken the product's colours for the background's); else, or where GrabCut finds
            nothing centred, the network's own mask is.
        retry_insets: fractions of the crop's side (each in [0, 0.5)): more retries, each ``foreground=grabcut``'s
            mask (:class:`GrabCutForeground` with its defaults, no network) from the rectangle inset by that
            fraction (at least ``band_px``; 0: the border band alone); where the network has taken the wrong thing
            for the product, a mask that does not lean on it (empty: none).
    """

    weights: str | None = None
    size: int | None = None
    threshold: float = 0.5
    retry_thresholds: tuple[float, ...] = (0.3, 0.7)
    centre: float = 0.5
    min_part: float = 0.2
    hole_area: float = 0.05
    hole_probability: float = 0.2
    alpha_band_px: int = 4
    passes: int = 0
    black_level: float = 0.0
    black_fraction: float | None = 0.5
    runtime: str = "onnxruntime"
    threads: int | None = None
    grabcut_iterations: int = 1
    background_below: float = 0.03
    band_px: int = 2
    max_side: int | None = 200
    seed: int = 0
    min_kept: float = 0.3
    retry_insets: tuple[float, ...] = (0.0, 0.08, 0.12)

    def __post_init__(self) -> None:
        try:
            self.retry_insets = tuple(float(f) for f in self.retry_insets)
        except (TypeError, ValueError):
            self.retry_insets = (float("nan"),)  # reported below
        if not all(0.0 <= f < 0.5 for f in self.retry_insets):
            raise MatlError(f"foreground learned: retry_insets={list(self.retry_insets)}: use fractions of the crop's "
                            "side in [0, 0.5), e.g. [0.0, 0.08], or [] for no GrabCut retries")
        try:
            self.retry_thresholds = tuple(float(t) for t in self.retry_thresholds)
        except (TypeError, ValueError):
            self.retry_thresholds = (float("nan"),)  # reported below
        if not all(0.0 < t < 1.0 for t in self.retry_thresholds):
            raise MatlError(f"foreground learned: retry_thresholds={list(self.retry_thresholds)}: use probabilities in "
                            "(0, 1), e.g. [0.3, 0.7], or [] for no retries")
        if self.runtime not in LEARNED_RUNTIMES:
            raise MatlError(f"foreground learned: runtime={self.runtime!r}: use {' or '.join(LEARNED_RUNTIMES)}")
        checks = (("threshold", 0.0 < float(self.threshold) < 1.0, "a probability in (0, 1), e.g. 0.5"),
                  ("centre", 0.0 < float(self.centre) <= 1.0, "a fraction of the crop's side in (0, 1]"),
                  ("min_part", 0.0 < float(self.min_part) <= 1.0, "a fraction in (0, 1] (1: the largest alone)"),
                  ("hole_area", 0.0 <= float(self.hole_area) <= 1.0, "a fraction in [0, 1] (0: no hole filled)"),
                  ("hole_probability", 0.0 <= float(self.hole_probability) <= 1.0, "a probability in [0, 1]"),
                  ("alpha_band_px", int(self.alpha_band_px) >= 0, "px >= 0 (0: an RGBA alpha as given)"),
                  ("passes", int(self.passes) >= 0, "an integer >= 0"),
                  ("black_level", 0.0 <= float(self.black_level) < 1.0, "a level in [0, 1)"),
                  ("black_fraction", self.black_fraction is None or 0.0 < float(self.black_fraction) <= 1.0,
                   "a fraction in (0, 1], or null (every crop through the network)"),
                  ("threads", self.threads is None or int(self.threads) >= 1, "an integer >= 1, or null"),
                  ("size", self.size is None or (int(self.size) >= 16 and int(self.size) % 8 == 0),
                   "a multiple of 8 (>= 16), or null (the network's own)"),
                  ("grabcut_iterations", int(self.grabcut_iterations) >= 0, "an integer >= 0 (0: no GrabCut)"),
                  ("background_below", 0.0 <= float(self.background_below) < 1.0, "a probability in [0, 1)"),
                  ("band_px", int(self.band_px) >= 1, "px >= 1"),
                  ("max_side", self.max_side is None or int(self.max_side) >= 16, "px >= 16, or null"),
                  ("min_kept", 0.0 <= float(self.min_kept) <= 1.0, "a share in [0, 1] (0: GrabCut's mask always)"))
        for name, ok, rule in checks:
            if not ok:
                raise MatlError(f"foreground learned: {name}={getattr(self, name)} is invalid: use {rule}")
        from matl.models.visibility import load_visibility_net

        given = self.__dict__.pop("_given", None)  # from_network's network
        if given is not None:
            net = given if self.size is None or int(self.size) == given.size else _resized(given, int(self.size))
        else:
            net = load_visibility_net(self.weights, self.size)  # a missing or wrong file: one line, now
        self._net = net.eval()
        self._rectangle = GrabCutForeground(inset_px=int(self.band_px), max_side=self.max_side, seed=int(self.seed))
        self._sessions: dict[int, Any] = {}
        self._session_lock = threading.Lock()
        self._graph: bytes | None = None
        self.failure: str | None = None  # why onnxruntime is not used, when it is not

    @classmethod
    def from_network(cls, net: Any, **settings: Any) -> LearnedForeground:
        """The step around a :class:`~matl.models.visibility.VisibilityNet` in memory (``settings`` as the
        constructor's; ``weights`` then only names where it came from)."""
        step = cls.__new__(cls)
        step.__dict__["_given"] = net
        step.__init__(**settings)
        return step

    @property
    def retrying(self) -> bool:
        """Whether a query whose answer does not verify is masked again (:meth:`retries`)."""
        return bool(self.retry_thresholds) or bool(self.retry_insets)

    @property
    def working_size(self) -> int:
        """The side the crop is resized to."""
        return int(self._net.size)

    # ------------------------------------------------------------------------------ the network
    def _session(self) -> Any:
        """The onnxruntime session at the current thread count, or None (torch answers; ``failure`` says why)."""
        threads = int(self.threads) if self.threads is not None else torch.get_num_threads()
        with self._session_lock:  # the crops of a batch are masked in threads (matl.utils.threads)
            if self.runtime != "onnxruntime" or self.failure is not None:
                return None
            if self._graph is None:
                try:
                    self._graph = self._export()
                except Exception as error:  # onnx / onnxruntime missing, or an operator refused: torch answers
                    self.failure = f"{type(error).__name__}: {' '.join(str(error).split())[:300]}"
                    return None
            if threads not in self._sessions:
                self._sessions[threads] = _onnx_session(self._graph, threads)
            return self._sessions[threads]

    def _export(self) -> bytes:
        """The network as ONNX bytes, checked against torch on random images within :data:`ONNX_TOLERANCE`."""
        from matl.inference.export import onnx_bytes, require_onnxruntime

        require_onnxruntime()
        S = self.working_size
        example = torch.rand(3, 3, S, S, generator=torch.Generator().manual_seed(0))
        with torch.inference_mode(False), torch.no_grad():
            graph = onnx_bytes(self._net, example[:1], ("logits",))
            expected = self._net(example).numpy()
        diff = float(np.abs(_onnx_session(graph, 1).run(None, {"images": example.numpy()})[0] - expected).max())
        if not diff <= ONNX_TOLERANCE:
            raise RuntimeError(f"the visibility network in onnxruntime differs from torch by {diff:.3g}")
        return graph

    def prepare(self) -> str:
        """Export the network and open its onnxruntime session at the current thread count now rather than at the
        first crop (about a second); returns :attr:`runtime_in_use`."""
        return self.runtime_in_use

    @property
    def runtime_in_use(self) -> str:
        """What runs the network: ``onnxruntime`` or ``torch`` (asked for, or the fallback)."""
        return "onnxruntime" if self._session() is not None else "torch"

    def logits(self, rgb: np.ndarray) -> np.ndarray:
        """The network's logits ``(H, W)`` float32 of a float RGB ``(H, W, 3)`` crop in [0, 1]: the crop resized to
        the working size (area averaging; the aspect is not kept), the logits resized back (bilinear)."""
        if rgb.ndim != 3 or rgb.shape[-1] != 3:
            raise MatlError(f"foreground learned: expected an (H, W, 3) RGB crop, got shape {rgb.shape}")
        h, w = rgb.shape[:2]
        S = self.working_size
        small = cv2.resize(np.ascontiguousarray(rgb, dtype=np.float32), (S, S), interpolation=cv2.INTER_AREA)
        x = np.ascontiguousarray(np.clip(small, 0.0, 1.0).transpose(2, 0, 1)[None])
        session = self._session()
        if session is not None:
            out = session.run(None, {"images": x})[0][0, 0]
        else:
            with torch.no_grad():
                out = self._net(torch.from_numpy(x)).numpy()[0, 0]
        return cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR)

    def probability(self, rgb: np.ndarray) -> np.ndarray:
        """The probability ``(H, W)`` float32 in [0, 1] that each pixel of a float RGB ``(H, W, 3)`` crop shows the
        visible print of its target product (no threshold, no clean-up): what verification can weigh by."""
        return (1.0 / (1.0 + np.exp(-self.logits(rgb)))).astype(np.float32)

    # ------------------------------------------------------------------------------ masks
    def segments(self, rgb: np.ndarray) -> bool:
        """Whether the network runs on a float RGB ``(H, W, 3)`` crop: not on one whose 2 px border band is black
        (``black_level``, ``black_fraction``: already segmented; never with ``black_fraction`` None) nor on one under
        8 px."""
        h, w = rgb.shape[:2]
        if h < 8 or w < 8:
            return False
        if self.black_fraction is None:
            return True
        band = (rgb[:2], rgb[-2:], rgb[2:-2, :2], rgb[2:-2, -2:])  # the 2 px border band, each pixel once
        black = sum(int((b.max(-1) <= self.black_level).sum()) for b in band)
        return black / (2 * 2 * (h + w) - 16) < float(self.black_fraction)

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        """The alpha ``(H, W)`` float32 in {0, 1} of a float RGB ``(H, W, 3)`` crop in [0, 1]; every pixel for a crop
        that is already segmented (:meth:`segments`) or where nothing is found."""
        if not self.segments(rgb):
            return np.ones(rgb.shape[:2], np.float32)
        prob = self.probability(rgb)
        mask = self.mask(prob, float(self.threshold))
        if int(self.grabcut_iterations) > 0 and mask is not None:
            found = self._grabcut(rgb, prob)
            snapped = None if found is None else self.mask(prob, float(self.threshold), found)
            if snapped is not None and snapped.sum() >= float(self.min_kept) * mask.sum():
                mask = snapped
        return np.ones(rgb.shape[:2], np.float32) if mask is None else mask

    def _grabcut(self, rgb: np.ndarray, prob: np.ndarray) -> np.ndarray | None:
        """GrabCut's foreground ``(H, W)`` bool of a float RGB ``(H, W, 3)`` crop started from the network's
        probability ``(H, W)`` (``background_below``, ``band_px``; at most ``max_side``); None where GrabCut cannot
        run (nothing left as probable foreground, a colour model without samples)."""
        h, w = prob.shape
        factor = 1.0 if self.max_side is None else min(1.0, int(self.max_side) / max(h, w))
        band = max(1, round(int(self.band_px) * factor))
        if factor < 1.0:
            size = (max(1, round(w * factor)), max(1, round(h * factor)))
            rgb = cv2.resize(np.ascontiguousarray(rgb, dtype=np.float32), size, interpolation=cv2.INTER_AREA)
            prob = cv2.resize(prob, size, interpolation=cv2.INTER_AREA)
        labels = np.where(prob < float(self.background_below), cv2.GC_BGD, cv2.GC_PR_FGD).astype(np.uint8)
        labels[:band], labels[-band:], labels[:, :band], labels[:, -band:] = (cv2.GC_BGD,) * 4
        if not (labels == cv2.GC_PR_FGD).any() or not _grabcut_labels(rgb, labels, int(self.grabcut_iterations),
                                                                       int(self.seed)):
            return None
        found = ((labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)).astype(np.uint8)
        found = cv2.morphologyEx(found, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        if factor < 1.0:
            found = cv2.resize(found.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR) > 0.5
        return found.astype(bool)

    def retries(self, rgb: np.ndarray) -> list[np.ndarray]:
        """The masks ``(H, W)`` float32 in {0, 1} at each of ``retry_thresholds`` of a float RGB ``(H, W, 3)`` crop,
        then GrabCut's from each of ``retry_insets``; none for a crop used as given, none where nothing is found."""
        if not self.retrying or not self.segments(rgb):
            return []
        masks: list[np.ndarray | None] = []
        if self.retry_thresholds:
            prob = self.probability(rgb)
            masks += [self.mask(prob, t) for t in self.retry_thresholds]
        side = min(rgb.shape[:2])
        insets = [max(int(self.band_px), round(f * side)) for f in self.retry_insets]
        masks += thread_map(lambda inset: self._rectangle.segment(rgb, inset), insets)  # over torch's threads
        return [m for m in masks if m is not None]

    def mask(self, prob: np.ndarray, threshold: float, found: np.ndarray | None = None) -> np.ndarray | None:
        """The product's mask ``(H, W)`` float32 in {0, 1} from a probability map ``(H, W)``: above ``threshold``
        (or the pixels of ``found`` ``(H, W)`` bool, e.g. GrabCut's), the components that overlap the centre region
        (the largest, and those of at least ``min_part`` of its area), holes filled where small and probable
        (``hole_area``, ``hole_probability``); None when no component overlaps the centre region."""
        h, w = prob.shape
        above = prob > threshold if found is None else found
        count, labels, stats, _ = cv2.connectedComponentsWithStats(above.astype(np.uint8), connectivity=8)
        if count <= 1:
            return None
        y0, x0 = int((1.0 - float(self.centre)) / 2.0 * h), int((1.0 - float(self.centre)) / 2.0 * w)
        centre = labels[y0:max(y0 + 1, h - y0), x0:max(x0 + 1, w - x0)]  # the centre region's labels
        touching = np.unique(centre[centre > 0])
        if len(touching) == 0:
            return None
        area = stats[touching, cv2.CC_STAT_AREA]
        keep = np.zeros(count, bool)
        keep[touching[area >= float(self.min_part) * area.max()]] = True
        mask = keep[labels]  # a lookup per label: the kept components
        if self.hole_area > 0:
            mask = self._fill_probable_holes(mask, prob)
        return mask.astype(np.float32)

    def _fill_probable_holes(self, mask: np.ndarray, prob: np.ndarray) -> np.ndarray:
        """``mask`` ``(H, W)`` bool with each hole (a 4-connected region outside it that does not reach the border)
        filled when its area is at most ``hole_area`` x the mask's and its mean probability at least
        ``hole_probability``."""
        count, labels, stats, _ = cv2.connectedComponentsWithStats((~mask).astype(np.uint8), connectivity=4)
        if count <= 2:
            return mask
        edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        holes = np.setdiff1d(np.arange(1, count), edge)
        if len(holes) == 0:
            return mask
        small = holes[stats[holes, cv2.CC_STAT_AREA] <= float(self.hole_area) * mask.sum()]
        if len(small) == 0:
            return mask
        mean = np.bincount(labels.ravel(), weights=prob.ravel(), minlength=count) / np.maximum(
            stats[:, cv2.CC_STAT_AREA], 1)
        fill = np.zeros(count, bool)
        fill[small[mean[small] >= float(self.hole_probability)]] = True
        return mask | fill[labels] if fill.any() else mask

    def refine_alpha(self, rgb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        """An RGBA query's alpha ``(H, W)`` with the pixels within ``alpha_band_px`` of its edge decided by the
        network's mask, or with ``grabcut_iterations`` by GrabCut as :meth:`GrabCutForeground.refine_alpha` does
        (``rgb``: ``(H, W, 3)`` float in [0, 1], the pixels under the alpha); ``alpha`` itself with ``alpha_band_px``
        0."""
        band = int(self.alpha_band_px)
        if band == 0:
            return alpha
        if int(self.grabcut_iterations) > 0:
            return _grabcut_alpha(rgb, alpha, band, int(self.grabcut_iterations), int(self.seed))
        inside, outside_d, inside_d = _edge_distances(alpha)
        near = (outside_d <= band) & (inside_d <= band)
        found = self.probability(rgb) > float(self.threshold)
        return np.where(near, found, inside).astype(np.float32)


def _resized(net: Any, size: int) -> Any:
    """``net``'s weights in a :class:`~matl.models.visibility.VisibilityNet` of working size ``size``."""
    from matl.models.visibility import VisibilityNet

    other = VisibilityNet(**{**net.config, "size": size})
    other.load_state_dict(net.state_dict())
    return other.eval()


def _onnx_session(graph: bytes, threads: int) -> Any:
    """An onnxruntime CPU session of ``graph`` with ``threads`` intra-op threads (the query networks' options,
    :mod:`matl.inference.runtime`: pool threads spin during a call and stop when it returns)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = int(threads), 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "1")
    options.add_session_config_entry("session.force_spinning_stop", "1")
    return ort.InferenceSession(graph, options, providers=["CPUExecutionProvider"])


#: the foreground steps of RGB queries without a mask
ForegroundStep = GrabCutForeground | LearnedForeground


def mask_query(step: ForegroundStep | None, image: np.ndarray
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


def foreground_option(value: Any) -> ForegroundStep | None:
    """The foreground step of a ``foreground`` value: ``none`` or None (no step), ``grabcut`` or ``learned`` (the
    defaults), a :class:`GrabCutForeground` or :class:`LearnedForeground`, or a config node
    (``conf/foreground/*.yaml``: ``_target_`` null for none).

    Raises:
        MatlError: any other value, or a node with a bad setting.
    """
    if value is None or isinstance(value, (GrabCutForeground, LearnedForeground)):
        return value
    if isinstance(value, str):
        if value == "none":
            return None
        if value == "grabcut":
            return GrabCutForeground()
        if value == "learned":
            return LearnedForeground()
    elif isinstance(value, Mapping) and "_target_" in value:
        if value["_target_"] is None:
            return None
        from matl.utils.instantiate import instantiate_node

        step = instantiate_node(value, "foreground")
        if isinstance(step, (GrabCutForeground, LearnedForeground)):
            return step
    raise MatlError(f"foreground={value!r} is invalid: use {' or '.join(FOREGROUNDS)} (RGB queries without a mask)")
