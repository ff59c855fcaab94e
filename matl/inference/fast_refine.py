"""Fast photometric pose refinement (``refiner=fast``, the default of ``refine=true``).

The query is aligned to the anchor the recognizer selected by minimising a robust photometric
loss, as :class:`~matl.inference.refine.PhotometricRefiner` does, but built so that one query costs a
few hundred microseconds on one CPU core:

* **Inverse compositional Gauss-Newton** (Baker and Matthews): the linearisation is taken about the
  *anchor*, so its image gradients, the steepest-descent images ``sd = grad(A) dW/dp`` and the
  Gauss-Newton Hessian ``sd^T sd`` do not depend on the query. They are computed once per gallery
  anchor and pyramid level (:meth:`FastRefiner.anchor_templates`: when the refined recognizer is built
  over a gallery, i.e. at enrolment) and looked up per query. The update is
  ``query_H_anchor <- query_H_anchor @ inv(I + D(dp))`` in normalised coordinates
  (``align_corners=True`` of the full-resolution image, so one matrix serves every level).
* **Objective** (``region=frame``: the photometric refiner's own): ``mean rho(r)`` over
  the anchor frame with ``r = (Iq(H x) - gain * A(x) - bias * F(x)) / scale``, ``A`` the anchor's
  luminance, ``F`` its foreground (non-zero pixels; backgrounds are 0 by convention), ``gain`` and
  ``bias`` the least-squares fit over ``F`` at the current pose (a change of the query's exposure or
  black level costs nothing), ``scale`` the std of the query's foreground (``delta`` is unitless). The
  background stays in the loss (0 on both sides at the right pose): it keeps the object's outline in
  the objective. ``region=foreground``: only the anchor's foreground eroded by ``erode`` px counts
  (whatever the query shows around the object costs nothing; for queries with a background).
  ``region=auto`` (the default): the whole frame, then the foreground alone for a query that shows
  something beside its object at that pose (:meth:`FastRefiner.leak`). ``rho`` is ``l2``, ``huber`` or
  ``cauchy``, minimised by iteratively re-weighted Gauss-Newton (the precomputed Hessian whenever every
  weight is 1). Since ``T = gain * A + bias * F``, the step is ``dp = (sd^T W sd)^-1 sd^T W r / gain``
  (the outline term ``bias * grad F`` is left out of ``sd``).
* **Levenberg-Marquardt safeguard**: a step is kept only if the loss at the level drops; otherwise the
  level goes back to its best pose with the damping raised tenfold (``damping``, relative to the
  Hessian's diagonal), so the loss of each level never increases.
* **Coarse to fine** over ``levels`` pyramid levels (``cv2.pyrDown``), at most ``iterations`` per
  level (``iterations`` is one number, or one per level from the finest), a level ending once an
  accepted step moved no image corner by more than ``tolerance`` px of that level.
* **Where it starts**: ``start=stn`` (default) refines ``s()``'s pose and a refined recognizer skips
  the model's learned alignment stage (``model.align``), whose job this does at a fraction of its cost;
  ``start=align`` refines the stage's pose.
* **What the query shows** (``visibility``): the query's visibility in [0, 1] per pixel (its mask: an RGBA alpha,
  the foreground step's; ones when none), warped into the anchor frame by the same pose, weighs each pixel of the
  anchor's foreground farther than ``visibility_band`` px inside its outline in the gain / bias fit and in the loss
  (the other pixels keep their full weight: a mask's edge is as often off as the pose, and the outline keeps its
  pull); such a pixel the query does not show costs a constant, what a residual of ``delta`` does, so the print an
  occluder or the mask hides does not pull the pose, and no pose gains by hiding the product
  (:func:`~matl.inference.fast_refine_kernels.objective_weighted`). A query with a mask is refined twice from its
  start, with every pixel as it is (far from the answer, the plane over the masked-out background is off, not
  hidden: the silhouette pulls) and weighted by its visibility; the weighted loss picks between them.
* **Small queries** (``upscale``): a query file enlarged to the model's size by more than ``match_upscale`` is
  blurrier than the anchor, and a sharp anchor against a blurred query pulls the pose inwards (a dark fringe
  inside the outline costs less when the anchor shrinks onto the query's interior). Such a query is refined
  against its anchor brought to the query's resolution: resized to the file's scale and back, as the query was
  (computed once per anchor and size, :meth:`FastRefiner.anchor_levels`).
* **Never worse than where it started**: at full resolution the objective of the result is compared with the
  start's and with those of the other unrefined poses given (``alternatives``: the alignment stage's pose,
  ``compare_align``), each on every pixel of the same region; the pose with the lowest loss is kept, the refined
  one only when it is strictly lower and its matrix is finite and well conditioned.

Batch-1 latency is what matters (one camera crop at a time), so a query never touches torch: the warps are
OpenCV's (``cv2.warpPerspective`` of a small grayscale image costs microseconds, a torch op ~10 us of
overhead) and the rest of an iteration is one or two calls of numba-compiled functions
(:mod:`matl.inference.fast_refine_kernels`: the fit, the loss and the normal equations in one, the damped
solve and the update in the other); a batch is a loop over its queries. ``threads`` sets OpenCV's threads
during the refinement (null: OpenCV's own; changing them costs about 0.1 ms a call).

This module holds :class:`FastRefiner` (its settings, the per-query descent and the batch call); what it
precomputes per anchor (:class:`~matl.inference.fast_refine_anchors.AnchorLevel`,
:class:`~matl.inference.fast_refine_anchors.AnchorTemplates`) and the pyramid and luminance it shares with the
queries are in :mod:`matl.inference.fast_refine_anchors`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from matl.geometry import degenerate_matrix, sample_by_pixels
from matl.inference import fast_refine_kernels as kernels
from matl.inference.fast_refine_anchors import (
    CORNERS,
    FOREGROUND,
    LUMA,
    AnchorLevel,
    AnchorTemplates,
    anchor_levels,
    blurred,
    image_pyramid,
    luminance,
    outside_mask,
)
from matl.inference.refine import RefineResult, at_resolution
from matl.utils.errors import MatlError
from matl.utils.threads import thread_map
from matl.utils.timing import opencv_threads

__all__ = ["FAST_LOSSES", "REGIONS", "AnchorLevel", "AnchorTemplates", "FastRefiner"]

FAST_LOSSES = kernels.LOSS_CODES
REGIONS = ("frame", "foreground", "auto")
STARTS = ("stn", "align")


def _folds(H: np.ndarray) -> bool:
    """Whether the normalised pose ``H`` turns the plane over (mirrors it) or sends part of it to or beyond infinity:
    an image corner it maps lies there, or the mapped corners are not a convex quadrilateral of the frame's own
    orientation (no camera sees a plane so)."""
    mapped = CORNERS @ H.T
    if not bool((mapped[:, 2] > 1e-9).all()):
        return True
    xy = mapped[:, :2] / mapped[:, 2:]
    edges = np.roll(xy, -1, axis=0) - xy
    turns = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    return not bool((turns > 0).all())  # the frame's corners, in this order, turn one way: every turn positive


class FastRefiner:
    """Inverse-compositional refinement of ``query_H_anchor`` against precomputed anchors (batch-1 fast).

    Args:
        iterations: most Gauss-Newton steps per pyramid level: one number for every level, or a list
            per level from the finest (e.g. ``[2, 3, 4]``).
        levels: pyramid levels (1: full resolution only); the coarsest keeps at least ``min_size`` px per side.
        region: ``frame`` (the whole anchor frame, background included: the outline counts),
            ``foreground`` (the anchor's foreground eroded by ``erode`` px only: a query's background costs nothing)
            or ``auto`` (``frame``, then ``foreground`` for a query with something beside its object).
        loss: ``l2``, ``huber`` or ``cauchy`` on the residuals.
        delta: robust-loss scale, in units of the query foreground's std.
        damping: initial Levenberg-Marquardt damping, relative to the Hessian's diagonal (raised tenfold
            after a step that did not lower the loss, lowered tenfold after one that did).
        min_size: smallest pyramid level side, pixels.
        min_std: floor of the query foreground's std (a flat image is not amplified into noise).
        erode: ``region=foreground`` only: pixels by which the foreground is eroded at every level.
        max_condition: a refined normalised matrix with a larger condition number is rejected.
        tolerance: a level ends once an accepted step moved no image corner by more than this many
            pixels of that level.
        threads: OpenCV threads during the refinement (None: leave OpenCV's; setting them costs ~0.1 ms a call).
        blur: std in px of a Gaussian applied to query and anchor alike before the pyramid (0: none).
        start: where a refined recognizer (:class:`~matl.inference.refine.RefinedRecognizer`) starts:
            ``stn``, ``s()``'s pose, skipping a model's learned alignment stage (``model.align``: the
            refinement does its job, and it costs more than the refinement at a batch of one), or
            ``align``, the stage's pose.
        auto_band, auto_level, auto_leak: ``region=auto``'s test (:meth:`leak`): query pixels brighter than
            ``auto_level`` more than ``auto_band`` px outside the anchor's foreground, above ``auto_leak`` of its area.
        auto_from: ``region=auto``'s foreground pass starts from the whole-frame result (``refined``) or the start.
        compare_align: a refined recognizer (``start=stn`` on a model with an alignment stage) also runs the stage
            and keeps its pose where its loss is lower than the refined one's and s()'s (costs the stage's time).
        match_upscale: a query whose file was enlarged by more than this factor to the model's size is refined
            against its anchor at the query's resolution (None: never).
        cache: anchors at another resolution kept (least recently used dropped beyond it).
        precompute: a gallery of at most this many anchors has its data computed at enrolment
            (:meth:`anchor_templates`); a larger one's (a warehouse catalogue: about 0.5 MB an anchor) anchor by anchor
            when a query first needs it (about 1.5 ms), at most this many kept, least recently used dropped.
        visibility: weigh the anchor's foreground pixels by the query's visibility (its mask) warped into the anchor
            frame; False: every pixel counts fully, whatever the query's mask.
        visibility_band: px (at full resolution; halved per level, at least 1) along the anchor's outline where the
            visibility does not apply: a mask's edge is as likely off as the pose, and the outline keeps its pull
            (0: the whole foreground).
    """

    def __init__(self, iterations: int | Sequence[int] = (3, 3, 4), levels: int = 3, region: str = "auto",
                 loss: str = "huber", delta: float = 2.0, damping: float = 1e-3, min_size: int = 8,
                 min_std: float = 0.02, erode: int = 1, max_condition: float = 1e4, tolerance: float = 0.25,
                 threads: int | None = None, blur: float = 0.0, start: str = "stn", auto_band: int = 1,
                 auto_level: float = 0.1, auto_leak: float = 0.002, auto_from: str = "refined",
                 compare_align: bool = False, match_upscale: float | None = 1.2, cache: int = 4096,
                 visibility: bool = True, visibility_band: int = 0, precompute: int = 4096) -> None:
        per_level = [int(i) for i in iterations] if isinstance(iterations, Sequence) and not isinstance(
            iterations, str) else [int(iterations)]
        if not per_level or min(per_level) < 0:
            raise MatlError(f"refiner.iterations must be an integer >= 0 or a list of them, got {iterations}")
        if int(levels) < 1:
            raise MatlError(f"refiner.levels must be >= 1, got {levels}")
        if region not in REGIONS:
            raise MatlError(f"refiner.region must be one of {', '.join(REGIONS)}, got {region!r}")
        if loss not in FAST_LOSSES:
            raise MatlError(f"refiner.loss must be one of {', '.join(FAST_LOSSES)}, got {loss!r}")
        if float(delta) <= 0 or float(damping) < 0 or int(min_size) < 4 or float(min_std) <= 0:
            raise MatlError(f"refiner.delta and min_std must be > 0, damping >= 0 and min_size >= 4; got "
                            f"delta={delta}, min_std={min_std}, damping={damping}, min_size={min_size}")
        if int(erode) < 0 or float(tolerance) < 0 or (threads is not None and int(threads) < 1):
            raise MatlError(f"refiner.erode and tolerance must be >= 0 and threads null or >= 1; got erode={erode}, "
                            f"tolerance={tolerance}, threads={threads}")
        self.iterations = per_level[0] if len(per_level) == 1 else per_level
        self.levels, self.region, self.loss, self.delta = int(levels), region, loss, float(delta)
        self.damping, self.min_size, self.min_std = float(damping), int(min_size), float(min_std)
        self.erode, self.max_condition, self.tolerance = int(erode), float(max_condition), float(tolerance)
        self.threads = None if threads is None else int(threads)
        if float(blur) < 0:
            raise MatlError(f"refiner.blur must be >= 0, got {blur}")
        self.blur = float(blur)
        if start not in STARTS:
            raise MatlError(f"refiner.start must be one of {', '.join(STARTS)}, got {start!r}")
        self.start = start
        self._loss_code = FAST_LOSSES.index(loss)
        if int(auto_band) < 0 or not float(auto_leak) >= 0.0 or not float(auto_level) >= 0.0 or auto_from not in (
                "refined", "start"):
            raise MatlError(f"refiner.auto_band, auto_level and auto_leak must be >= 0 and auto_from refined or start; "
                            f"got auto_band={auto_band}, auto_level={auto_level}, auto_leak={auto_leak}, "
                            f"auto_from={auto_from!r}")
        self.auto_band, self.auto_leak, self.auto_from = int(auto_band), float(auto_leak), auto_from
        self.auto_level = float(auto_level)
        if not isinstance(compare_align, bool):
            raise MatlError(f"refiner.compare_align must be true or false, got {compare_align!r}")
        if match_upscale is not None and (isinstance(match_upscale, bool) or not float(match_upscale) >= 1.0):
            raise MatlError(f"refiner.match_upscale must be a factor >= 1 or null (never), got {match_upscale!r}")
        if isinstance(cache, bool) or int(cache) < 0:
            raise MatlError(f"refiner.cache must be an integer >= 0, got {cache!r}")
        if not isinstance(visibility, bool):
            raise MatlError(f"refiner.visibility must be true or false, got {visibility!r}")
        self.compare_align, self.visibility = compare_align, visibility
        if isinstance(visibility_band, bool) or int(visibility_band) < 0:
            raise MatlError(f"refiner.visibility_band must be an integer >= 0 (px), got {visibility_band!r}")
        self.visibility_band = int(visibility_band)
        self.match_upscale = None if match_upscale is None else float(match_upscale)
        self.cache = int(cache)
        if isinstance(precompute, bool) or not isinstance(precompute, int) or precompute < 1:
            raise MatlError(f"refiner.precompute must be an integer >= 1 (anchors), got {precompute!r}")
        self.precompute = precompute
        self._templates: AnchorTemplates | None = None  # set by prepare()
        self._level_ms: list[float] = []

    @property
    def last_level_ms(self) -> list[float]:
        """Milliseconds per pyramid level (finest first) of the last single-query call."""
        return self._level_ms

    def _iterations(self, level: int) -> int:
        if isinstance(self.iterations, list):
            return self.iterations[min(level, len(self.iterations) - 1)]
        return self.iterations

    # ------------------------------------------------------------------------------ anchors
    def _blurred(self, image: np.ndarray) -> np.ndarray:
        """``image`` ``(H, W)`` under a Gaussian of std ``blur`` px (zeros outside), or itself (``blur=0``)."""
        return blurred(image, self.blur)

    def _anchor(self, gray: np.ndarray, fg: np.ndarray
                ) -> tuple[list[AnchorLevel], list[AnchorLevel] | None, np.ndarray | None]:
        """One anchor's ``(levels, region=auto's foreground levels, its outside mask)`` from its luminance and
        foreground ``(H, W)`` (:func:`~matl.inference.fast_refine_anchors.anchor_levels` with this refiner's
        settings; the last two None unless ``region=auto``)."""
        levels = anchor_levels(gray, fg, self._kinds(), self.levels, self.min_size, self.erode,
                               self.visibility_band, self.blur)
        if self.region != "auto":
            return levels[0], None, None
        return levels[0], levels[1], outside_mask(fg, self.auto_band)

    @torch.no_grad()
    def anchor_templates(self, anchors: torch.Tensor) -> AnchorTemplates:
        """Everything the refinement needs of ``anchors`` ``(G, 3, H, W)``, computed once per anchor: all of it now,
        or, for more than ``precompute`` anchors, each anchor's when a query first needs it."""
        if anchors.ndim != 4:
            raise MatlError(f"anchors must be (G, C, H, W), got {tuple(anchors.shape)}")
        start = time.perf_counter()
        kernels.warm_up()  # compiled (or loaded from numba's cache) here, at enrolment, not at the first query
        size = (int(anchors.shape[-2]), int(anchors.shape[-1]))
        if len(anchors) > self.precompute:
            auto = self.region == "auto"
            return AnchorTemplates([None] * len(anchors), size, time.perf_counter() - start,
                                   [None] * len(anchors) if auto else None, [None] * len(anchors) if auto else None,
                                   anchors.detach(), keep=self.precompute)
        gray = [image for image, _ in luminance(anchors)]
        fg = (anchors.detach().float().cpu() > FOREGROUND).any(dim=1).numpy().astype(np.float32)
        # region=auto keeps both: the whole frame first, the foreground for queries with something beside the object
        per_anchor = [self._anchor(gray[i], fg[i]) for i in range(len(gray))]
        auto = self.region == "auto"
        foreground = [a[1] for a in per_anchor] if auto else None
        outside = [a[2] for a in per_anchor] if auto else None
        return AnchorTemplates([a[0] for a in per_anchor], size, time.perf_counter() - start, foreground, outside,
                               anchors.detach())

    def _source_anchor(self, image: torch.Tensor
                       ) -> tuple[list[AnchorLevel], list[AnchorLevel] | None, np.ndarray | None]:
        """:meth:`_anchor` of one anchor image ``(1, 3, H, W)``."""
        gray = luminance(image)[0][0]
        return self._anchor(gray, (image[0] > FOREGROUND).any(dim=0).numpy().astype(np.float32))

    def _at_first_need(self, templates: AnchorTemplates, k: int
                       ) -> tuple[list[AnchorLevel], list[AnchorLevel] | None, np.ndarray | None]:
        """Anchor ``k`` of a large gallery: computed now if it is not held, the least recently used dropped beyond
        ``templates.keep``."""
        with templates.lock:
            if templates.anchors[k] is not None:
                templates.computed.move_to_end(k)
                return templates.held(k)
        found = self._source_anchor(templates.source[k:k + 1].detach().float().cpu())
        with templates.lock:
            templates.anchors[k] = found[0]
            if templates.foreground is not None:
                templates.foreground[k], templates.outside[k] = found[1], found[2]
            templates.computed[k] = None
            templates.computed.move_to_end(k)
            while len(templates.computed) > int(templates.keep or 0):
                old, _ = templates.computed.popitem(last=False)
                templates.anchors[old] = None
                if templates.foreground is not None:
                    templates.foreground[old] = templates.outside[old] = None
        return found

    def _kinds(self) -> tuple[str, ...]:
        return {"frame": ("frame",), "foreground": ("foreground",), "auto": ("frame", "foreground")}[self.region]

    def anchor_levels(self, templates: AnchorTemplates, k: int, upscale: float | None = None
                      ) -> tuple[list[AnchorLevel], list[AnchorLevel] | None, np.ndarray | None]:
        """Anchor ``k``'s ``(levels, region=auto's foreground levels, its outside mask)`` for a query whose file was
        enlarged ``upscale`` times to the model's size: the precomputed ones, or, above ``match_upscale``, those of
        the anchor at the query's resolution (:func:`~matl.inference.refine.at_resolution`: resized to
        ``round(S / upscale)`` px and back), computed once per anchor and side and kept in ``templates``."""
        side = None
        size = min(templates.image_size)
        if (upscale is not None and self.match_upscale is not None and upscale > self.match_upscale
                and templates.source is not None):
            side = max(4, round(size / float(upscale)))
        if side is None or side >= size:
            if templates.keep is not None:
                return self._at_first_need(templates, int(k))
            return templates.held(k)
        key = (int(k), side)
        found = templates.resampled.get(key)
        if found is not None:
            templates.resampled.move_to_end(key)
            return found
        found = self._source_anchor(at_resolution(templates.source[k:k + 1].detach().float().cpu(), side))
        if self.cache > 0:
            templates.resampled[key] = found
            while len(templates.resampled) > self.cache:
                templates.resampled.popitem(last=False)
        return found

    def prepare(self, anchors: torch.Tensor) -> FastRefiner:
        """Precompute the data of a gallery's anchors ``(G, 3, H, W)``; returns self."""
        self._templates = self.anchor_templates(anchors)
        return self

    # ------------------------------------------------------------------------------ objective
    def _evaluate(self, query: np.ndarray, anchor: AnchorLevel, M: np.ndarray, scale: float,
                  visible: np.ndarray | None = None) -> tuple[float, float, np.ndarray, np.ndarray, np.ndarray]:
        """At the pose whose matrix in the level's pixels is ``M`` (anchor px -> query px): the loss (a mean over the
        region, in units of ``scale``; weighted by the query's visibility ``visible`` ``(H, W)`` of this level warped
        by ``M`` when given), the gain, the Gauss-Newton system ``A (8, 8)``, ``b (8,)`` there and the query warped
        into the anchor frame ``(h, w)``."""
        warped = sample_by_pixels(query, M, anchor.size)
        region = anchor.region if anchor.region is not None else anchor.fg
        if visible is not None:
            seen = sample_by_pixels(visible, M, anchor.size)
            total, gain, A, b = kernels.evaluate_weighted(
                warped, seen, anchor.image, anchor.fg, anchor.inner, region, anchor.region is not None, anchor.index,
                anchor.sdT, anchor.hessian, self._loss_code, self.delta * scale)
            return total / (anchor.total * scale * scale), gain, A, b, warped
        total, gain, A, b = kernels.evaluate(warped, anchor.image, anchor.fg, region, anchor.region is not None,
                                             anchor.mean, anchor.inv_var, anchor.inv_count, anchor.index, anchor.sdT,
                                             anchor.hessian, self._loss_code, self.delta * scale)
        return total / (anchor.total * scale * scale), gain, A, b, warped

    def _loss(self, query: np.ndarray, anchor: AnchorLevel, M: np.ndarray, scale: float,
              visible: np.ndarray | None = None) -> float:
        """:meth:`_evaluate`'s loss alone (no normal equations): the objective at the pose whose matrix is ``M``
        (``visible``: the query's visibility ``(H, W)`` of this level, warped by ``M`` here)."""
        warped = sample_by_pixels(query, M, anchor.size)
        region = anchor.region if anchor.region is not None else anchor.fg
        if visible is not None:
            total = kernels.objective_weighted(warped, sample_by_pixels(visible, M, anchor.size), anchor.image,
                                               anchor.fg, anchor.inner, region, anchor.region is not None,
                                               self._loss_code, self.delta * scale)[0]
            return total / (anchor.total * scale * scale)
        total = kernels.objective(warped, anchor.image, anchor.fg, region, anchor.region is not None, anchor.mean,
                                  anchor.inv_var, anchor.inv_count, self._loss_code, self.delta * scale)[0]
        return total / (anchor.total * scale * scale)

    def _level(self, query: np.ndarray, anchor: AnchorLevel, H: np.ndarray, scale: float, iterations: int,
               visible: np.ndarray | None = None) -> tuple[np.ndarray, float, np.ndarray]:
        """Gauss-Newton / Levenberg-Marquardt at one level; the lowest-loss pose, its loss and its warped query."""
        loss, gain, A, b, warped = self._evaluate(query, anchor, anchor.pixel_H_norm @ H @ anchor.norm_H_pixel, scale,
                                                  visible)
        lam = self.damping
        for _ in range(iterations):
            if not math.isfinite(loss) or gain <= 1e-6:
                break
            ok, candidate, M, step = kernels.lm_step(A, b, lam, H, anchor.corner_J, anchor.pixel_H_norm,
                                                     anchor.norm_H_pixel)
            if not ok:
                break
            cand_loss, cand_gain, cand_A, cand_b, cand_warped = self._evaluate(query, anchor, M, scale, visible)
            if cand_loss < loss:
                H, loss, gain, A, b, warped = candidate, cand_loss, cand_gain, cand_A, cand_b, cand_warped
                lam = max(lam * 0.1, 1e-9)
                if step < self.tolerance:
                    break
            else:
                lam = min(lam * 10.0, 1e9)
                if step < self.tolerance:  # a step this small does not lower the loss: converged
                    break
        return H, loss, warped

    def _descend(self, pyramid: list[np.ndarray], anchor: list[AnchorLevel], H: np.ndarray, scale: float,
                 timing: bool, visible: list[np.ndarray] | None = None) -> tuple[np.ndarray, float, np.ndarray]:
        """Coarse to fine from the normalised pose ``H`` (``visible``: the query's visibility per level); the final
        normalised pose, its loss at full size and the full-size query warped by it."""
        loss, warped = math.inf, pyramid[0]
        times = [0.0] * len(pyramid)
        for level in reversed(range(len(pyramid))):  # coarsest first
            t0 = time.perf_counter() if timing else 0.0
            H, loss, warped = self._level(pyramid[level], anchor[level], H, scale, self._iterations(level),
                                          None if visible is None else visible[level])
            if timing:
                times[level] = 1e3 * (time.perf_counter() - t0)
        if timing:
            self._level_ms = times
        return H, loss, warped

    def leak(self, query: np.ndarray, full: AnchorLevel, outside: np.ndarray, H: np.ndarray,
             warped: np.ndarray | None = None) -> float:
        """``region=auto``'s statistic: the query's pixels brighter than ``auto_level`` (luminance in [0, 1]) that the
        normalised pose ``H`` puts in the anchor frame farther than ``auto_band`` px from the anchor's foreground, as a
        fraction of the foreground's area (``warped``: ``query`` already warped into the anchor frame by ``H``)."""
        if warped is None:
            warped = sample_by_pixels(query, full.pixel_H_norm @ H @ full.norm_H_pixel, full.size)
        return kernels.count_above(warped, outside, self.auto_level) / max(full.count, 1.0)

    def refine_one(self, query: np.ndarray, anchor: list[AnchorLevel], query_H_anchor: np.ndarray,
                   timing: bool = False, foreground: list[AnchorLevel] | None = None,
                   outside: np.ndarray | None = None, std: float | None = None, visible: np.ndarray | None = None,
                   alternatives: Sequence[np.ndarray] = ()) -> tuple[np.ndarray, float, float, bool, int]:
        """One query: luminance ``(H, W)`` float32, its anchor's levels, a pixel ``query_H_anchor`` ``(3, 3)``
        (``std``: the std of the query's foreground when known; ``visible``: the query's visibility ``(H, W)``
        float32 in [0, 1], None: all of it; ``alternatives``: other unrefined pixel poses ``(3, 3)`` to keep when
        their loss is lower).

        ``region=auto`` passes the anchor's ``region=foreground`` levels and its ``outside`` mask too: after the
        whole-frame refinement, a query with more than ``auto_leak`` of the anchor's foreground area in non-black
        pixels beyond ``auto_band`` px of its outline (something else is in the crop: other faces of a 3D object,
        background a mask let through, a neighbour) is refined again over the foreground alone, from the
        whole-frame result (``auto_from=refined``) or from the start (``start``), and judged by that objective.

        Returns ``(query_H_anchor (3, 3) float64 pixels, loss_before, loss_after, accepted, source)``: the start's
        loss, the kept pose's, whether that is the refined one, and which it is (0 refined, 1 the start, 2 + i
        ``alternatives[i]``); ``timing=True`` keeps the milliseconds of each level for :attr:`last_level_ms`
        (finest first).
        """
        H0 = np.asarray(query_H_anchor, dtype=np.float64)
        if not math.isfinite(H0.sum()) or abs(H0[2, 2]) < 1e-12:  # a NaN or infinite entry makes the sum one
            return H0, math.inf, math.inf, False, 1
        full = anchor[0]
        H0n = full.norm_H_pixel @ H0 @ full.pixel_H_norm  # normalised (align_corners=True), as PhotometricRefiner
        H0n = H0n / H0n[2, 2]
        if std is None:
            std = kernels.luminance(query[None], LUMA, FOREGROUND)[1]
        scale = max(std, self.min_std)
        raw = query
        query = self._blurred(query)
        pyramid = image_pyramid(query, min(self.levels, len(anchor)), self.min_size)
        seen = None if visible is None else image_pyramid(np.ascontiguousarray(visible, dtype=np.float32),
                                                          len(pyramid), self.min_size)
        # every pixel as it is: the silhouette pulls from afar (a pose that puts the plane over the masked-out
        # background is far off, not hidden)
        H, loss, warped = self._descend(pyramid, anchor, H0n, scale, timing)
        if foreground is not None and outside is not None and self.leak(
                raw, full, outside, H, warped if raw is query else None) > self.auto_leak:
            anchor, full = foreground, foreground[0]
            H, loss, _ = self._descend(pyramid, anchor, H if self.auto_from == "refined" else H0n, scale, False)
        visible_full = None if seen is None else seen[0]
        if seen is not None:  # and weighted by what the query shows, from the start: the hidden print pulls nothing
            refined = [R for R in (H, self._descend(pyramid, anchor, H0n, scale, False, seen)[0]) if not _folds(R)]
            scores = [self._loss(query, full, full.pixel_H_norm @ R @ full.norm_H_pixel, scale, visible_full)
                      for R in refined]
            H, loss = (refined[int(np.argmin(scores))], min(scores)) if refined else (H, math.inf)
        others = [np.asarray(a, dtype=np.float64) for a in alternatives]
        others = [a for a in others if math.isfinite(a.sum()) and abs(a[2, 2]) > 1e-12]
        unrefined = [H0, *others]  # pixel poses, the start first
        # every pose on every pixel of the level's region (a masked query: weighted by what it shows, a pixel it does
        # not show at a fixed cost): the refined one against the unrefined ones
        H_px = full.pixel_H_norm @ H @ full.norm_H_pixel
        losses = [self._loss(query, full, M, scale, visible_full) for M in unrefined]
        best = int(np.argmin(losses))  # the first of equals: the start before an alternative
        accepted = loss < losses[best] and not degenerate_matrix(H, self.max_condition) and not _folds(H)
        if not accepted:
            kept = unrefined[best]
            if best > 0:
                kept = kept / kept[2, 2]
            return kept, losses[0], losses[best], False, 1 + best
        return H_px / H_px[2, 2], losses[0], loss, True, 0

    # ------------------------------------------------------------------------------ main
    @torch.no_grad()
    def __call__(self, queries: torch.Tensor, anchor_index: torch.Tensor, query_H_anchor: torch.Tensor,
                 templates: AnchorTemplates | None = None, visibility: torch.Tensor | None = None,
                 upscale: torch.Tensor | None = None, alternatives: torch.Tensor | None = None) -> RefineResult:
        """Refine a batch against precomputed anchors.

        Args:
            queries: ``(B, 3, H, W)`` query images.
            anchor_index: ``(B,)`` long, each query's anchor in ``templates``.
            query_H_anchor: ``(B, 3, 3)`` pixel homographies (anchor pixel -> query pixel) to start from.
            templates: :meth:`anchor_templates` of the gallery; None: those of :meth:`prepare`.
            visibility: ``(B, 1, H, W)`` each query's visibility in [0, 1] (its mask); None (or the ``visibility``
                option false): every pixel.
            upscale: ``(B,)`` how many times each query's file was enlarged to the model's size (None: not known).
            alternatives: ``(B, K, 3, 3)`` other unrefined pixel poses per query, kept where their loss is lower.
        Returns:
            :class:`~matl.inference.refine.RefineResult` with float64 pixel homographies (on the
            device of ``query_H_anchor``).
        """
        templates = templates if templates is not None else self._templates
        if templates is None:
            raise MatlError("FastRefiner: call prepare(gallery images) or pass templates")
        B = len(queries)
        if queries.ndim != 4 or query_H_anchor.shape != (B, 3, 3) or anchor_index.shape != (B,):
            raise MatlError(f"queries must be (B, C, H, W), anchor_index (B,) and query_H_anchor (B, 3, 3), got "
                            f"{tuple(queries.shape)}, {tuple(anchor_index.shape)}, {tuple(query_H_anchor.shape)}")
        size = (int(queries.shape[-2]), int(queries.shape[-1]))
        if size != templates.image_size:
            raise MatlError(f"queries are {size} but the anchors {templates.image_size}: refine at the gallery's size")
        if visibility is not None and tuple(visibility.shape) != (B, 1, *size):
            raise MatlError(f"visibility must be (B, 1, H, W) = {(B, 1, *size)}, got {tuple(visibility.shape)}")
        gray = luminance(queries)
        starts = query_H_anchor.detach().double().cpu().numpy()
        index = anchor_index.detach().cpu().numpy()
        seen = None if visibility is None or not self.visibility else visibility.detach().float().cpu().numpy()[:, 0]
        factor = None if upscale is None else torch.as_tensor(upscale).detach().double().cpu().numpy()
        others = None if alternatives is None else alternatives.detach().double().cpu().numpy()
        out = np.empty((B, 3, 3))
        before, after, accepted = np.empty(B), np.empty(B), np.zeros(B, dtype=bool)
        source = np.zeros(B, dtype=np.int64)
        # each query's anchor in order (a large gallery's least recently used kept as the queries come), then the
        # queries refined over torch's threads (the kernels release the GIL)
        anchors = [self.anchor_levels(templates, int(index[i]), None if factor is None else float(factor[i]))
                   for i in range(B)]

        def one(i: int) -> tuple[np.ndarray, float, float, bool, int]:
            levels, fg_levels, outside = anchors[i]
            image, std = gray[i]
            visible = None if seen is None or float(seen[i].min()) >= 1.0 else seen[i]
            return self.refine_one(image, levels, starts[i], timing=B == 1, foreground=fg_levels, outside=outside,
                                   std=std, visible=visible, alternatives=() if others is None else list(others[i]))

        with opencv_threads(self.threads):
            for i, found in enumerate(thread_map(one, range(B))):
                out[i], before[i], after[i], accepted[i], source[i] = found
        result = (torch.from_numpy(out), torch.from_numpy(before), torch.from_numpy(after), torch.from_numpy(accepted),
                  torch.from_numpy(source))
        device = query_H_anchor.device
        return RefineResult(*(result if device.type == "cpu" else (t.to(device) for t in result)))

    def refine_images(self, queries: torch.Tensor, anchors: torch.Tensor, query_H_anchor: torch.Tensor) -> RefineResult:
        """The same refinement with each query's anchor image ``(B, 3, H, W)`` given (their data computed here)."""
        return self(queries, torch.arange(len(anchors)), query_H_anchor, self.anchor_templates(anchors))

    def options(self) -> dict[str, Any]:
        """The settings, for result files."""
        return {k: v for k, v in vars(self).items() if not k.startswith("_")}
