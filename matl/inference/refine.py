"""Test-time pose refinement (beyond the paper): direct photometric alignment of the query to its anchor.

The STN regresses ``query_H_anchor`` in one or two feed-forward steps; its error is bounded by
what a small regressor can learn. Given the anchor the recognizer selected, the pose can be
polished by minimising the appearance loss itself, the classic Lucas-Kanade way:

* **Parametrisation.** Forward compositional: ``H = H_stn @ (I + D(p))`` in normalised coordinates
  (``align_corners=True``, so one matrix is valid at every pyramid level), ``p`` the 8 entries of a
  homography update about the identity. The STN estimate is the starting point ``p = 0``.
* **Objective.** ``mean rho(r)`` over all pixels of the anchor frame (luminance by default, or the
  3 channels), with ``r = (Iq(H x) - gain * Ia(x) - bias * F(x)) / scale``: ``F`` is the anchor's
  foreground (pixels > 0; backgrounds are 0 by convention), ``gain`` and ``bias`` per channel are
  the least-squares fit over ``F`` at the current pose (variable projection), so a gain / bias
  change of the query's lighting costs nothing, and ``scale`` is the std of the query's
  foreground, so ``delta`` is unitless. Background pixels stay in the loss (0 on both sides at the
  right pose): they keep the object's outline in the objective. ``rho`` is ``l2``, ``huber`` or
  ``cauchy`` (robust to specular spots, occluders, segmentation errors).
* **Solver.** Gauss-Newton with Levenberg-Marquardt damping, re-weighted (IRLS) for the robust
  ``rho``: the Jacobian is the warped query's image gradient times the homography's derivative
  at the identity. A step is accepted per query only if the loss drops, else the damping grows,
  so the loss at each level never increases.
* **Coarse to fine.** A Gaussian pyramid (``levels``), coarsest first: coarse levels widen the
  basin of convergence, the finest level gives sub-pixel accuracy.
* **What the query shows.** A query's visibility in [0, 1] per pixel (its mask; ones when none), warped into
  the anchor frame with the pose, weighs each pixel of the anchor's foreground farther than ``visibility_band``
  px inside its outline in the gain / bias fit and in the loss (the others keep their weight: the outline
  counts, and a mask's edge is as often off as the pose); such a pixel the query does not show costs what a
  residual of ``delta`` does, so what an occluder or the mask hides does not pull the pose and no pose gains by
  hiding the product. A query with a mask is refined twice from its start, every pixel as it is (far from the
  answer the silhouette pulls) and weighted; the weighted loss picks between them.
* **Small queries.** A query file enlarged by more than ``match_upscale`` to the model's size is compared
  with its anchor brought to the query's resolution (:func:`at_resolution`): a sharp anchor against a blurred
  query pulls the pose inwards.
* **Divergence guard.** At full resolution the final loss is compared with the start's (and with those of
  other unrefined poses given, each on every pixel); a query whose loss did not decrease, or whose refined
  matrix is non-finite or ill-conditioned, keeps the unrefined pose of lowest loss. Refinement therefore
  never makes the objective worse.

Everything is batched over queries. ``RefinedRecognizer`` wraps any recognizer (MATL, the STN
classifier, a keypoint baseline) and refines the pose against the anchor it selected.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from kornia.geometry.transform import pyrdown

from matl.geometry import (
    compose_query_H_canon,
    degenerate_homographies,
    normalised_grid,
    normalised_to_pixel,
    pixel_to_normalised,
    sample_by_normalised,
)
from matl.models.prediction import Prediction
from matl.models.recognizer import TensorRecognizer

__all__ = ["LOSSES", "PhotometricRefiner", "RefineResult", "RefinedRecognizer", "at_resolution"]

LOSSES = ("l2", "huber", "cauchy")
_FOREGROUND = 1e-3  # a pixel brighter than this in any channel is foreground (backgrounds are exactly 0)
#: a second judge of refined poses (RefinedRecognizer's ``check``): (queries (T, 3, S, S), query_H_anchor (T, 3, 3),
#: gallery_index (T,), visibility (T, 1, S, S) or None) -> (T,) scores, lower is better
PoseCheck = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, "torch.Tensor | None"], torch.Tensor]


@dataclass
class RefineResult:
    """Refined poses of a batch.

    Attributes:
        query_H_anchor: ``(B, 3, 3)`` float64 pixel homographies (the input where not accepted).
        loss_before: ``(B,)`` objective at the input pose (full resolution).
        loss_after: ``(B,)`` objective at the returned pose (``<= loss_before``).
        accepted: ``(B,)`` bool, the refined pose was kept.
        source: ``(B,)`` int64 the pose returned: 0 the refined one, 1 the start, ``2 + i`` the ``i``-th
            alternative unrefined pose given (None: not reported).
    """

    query_H_anchor: torch.Tensor
    loss_before: torch.Tensor
    loss_after: torch.Tensor
    accepted: torch.Tensor
    source: torch.Tensor | None = None


def at_resolution(images: torch.Tensor, side: int) -> torch.Tensor:
    """``(B, C, H, W)`` images brought to the detail of a file whose longer side is ``side`` px: resized to it and
    back (antialiased bilinear down, bilinear up: the resize of :func:`matl.data.image_files.fit_to_model`), as a
    query from a file that small was enlarged to the model's size."""
    H, W = int(images.shape[-2]), int(images.shape[-1])
    if side >= max(H, W):
        return images
    h, w = max(1, round(H * side / max(H, W))), max(1, round(W * side / max(H, W)))
    small = F.interpolate(images, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
    return F.interpolate(small, size=(H, W), mode="bilinear", align_corners=False).clamp(0.0, 1.0)


def _update_matrix(p: torch.Tensor) -> torch.Tensor:
    """``I + D(p)``: ``(B, 8) -> (B, 3, 3)``."""
    full = torch.cat([p, torch.zeros_like(p[:, :1])], dim=1).view(-1, 3, 3)
    return full + torch.eye(3, dtype=p.dtype, device=p.device)


def _gradients(images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Central differences per pixel ``(B, C, h, w)``, one-sided at the border (same shape)."""
    padded = F.pad(images, (1, 1, 1, 1), mode="replicate")
    gx = (padded[..., 1:-1, 2:] - padded[..., 1:-1, :-2]) * 0.5
    gy = (padded[..., 2:, 1:-1] - padded[..., :-2, 1:-1]) * 0.5
    return gx, gy


class PhotometricRefiner:
    """Refines ``query_H_anchor`` against the selected anchor by direct photometric alignment.

    Args:
        iterations: Gauss-Newton iterations per pyramid level.
        levels: pyramid levels (1: full resolution only); the coarsest level keeps at least
            ``min_size`` pixels per side.
        step: fraction of each Gauss-Newton step taken (1: full step).
        loss: ``l2``, ``huber`` or ``cauchy`` on the residuals.
        delta: scale of the robust loss, in units of the query foreground's std (huber: quadratic below it).
        damping: initial Levenberg-Marquardt damping (relative to the Hessian's diagonal).
        min_size: smallest pyramid level side, pixels.
        min_std: floor of the query foreground's std per channel (a flat image is not amplified into
            noise).
        max_condition: a refined normalised matrix with a larger condition number is rejected.
        grayscale: align luminance (ITU-R BT.601) instead of the 3 colour channels: about 2x cheaper
            per query and as accurate on synthetic_arc; colour only helps where two regions differ in
            hue but not in brightness.
        tolerance: a level stops early once no query's update moves an image corner by more than
            this many pixels (of that level).
        match_upscale: a query whose file was enlarged by more than this factor to the model's size is compared
            with its anchor at the query's resolution (:func:`at_resolution`; None: never).
        visibility: weigh the anchor's foreground pixels by the query's visibility (its mask) warped into the
            anchor frame; False: every pixel counts fully.
        visibility_band: px (at full resolution; halved per level, at least 1) along the anchor's outline where the
            visibility does not apply (a mask's edge is as likely off as the pose; 0: the whole foreground).
    """

    def __init__(self, iterations: int = 8, levels: int = 3, step: float = 1.0, loss: str = "huber",
                 delta: float = 0.5, damping: float = 1e-3, min_size: int = 8, min_std: float = 0.02,
                 max_condition: float = 1e4, tolerance: float = 0.01, grayscale: bool = True,
                 match_upscale: float | None = 1.2, visibility: bool = True, visibility_band: int = 0) -> None:
        if int(iterations) < 0:
            raise ValueError(f"refiner.iterations must be >= 0, got {iterations}")
        if int(levels) < 1:
            raise ValueError(f"refiner.levels must be >= 1, got {levels}")
        if not 0.0 < float(step) <= 2.0:
            raise ValueError(f"refiner.step must be in (0, 2], got {step}")
        if loss not in LOSSES:
            raise ValueError(f"refiner.loss must be one of {', '.join(LOSSES)}, got {loss!r}")
        if float(delta) <= 0 or float(damping) < 0 or float(min_std) <= 0 or int(min_size) < 4:
            raise ValueError(f"refiner.delta, min_std must be > 0, damping >= 0 and min_size >= 4; got delta={delta}, "
                             f"damping={damping}, min_std={min_std}, min_size={min_size}")
        self.iterations, self.levels, self.step = int(iterations), int(levels), float(step)
        self.loss, self.delta, self.damping = loss, float(delta), float(damping)
        self.min_size, self.min_std, self.max_condition = int(min_size), float(min_std), float(max_condition)
        self.tolerance, self.grayscale = float(tolerance), bool(grayscale)
        if match_upscale is not None and (isinstance(match_upscale, bool) or not float(match_upscale) >= 1.0):
            raise ValueError(f"refiner.match_upscale must be a factor >= 1 or null (never), got {match_upscale!r}")
        self.match_upscale = None if match_upscale is None else float(match_upscale)
        if not isinstance(visibility, bool):
            raise ValueError(f"refiner.visibility must be true or false, got {visibility!r}")
        self.visibility = visibility
        if isinstance(visibility_band, bool) or int(visibility_band) < 0:
            raise ValueError(f"refiner.visibility_band must be an integer >= 0 (px), got {visibility_band!r}")
        self.visibility_band = int(visibility_band)

    # ----------------------------------------------------------------------------------- pieces
    def _query_scale(self, queries: torch.Tensor) -> torch.Tensor:
        """Per-channel std ``(B, C, 1, 1)`` of each query's foreground (the residuals' unit), floored."""
        mask = (queries > _FOREGROUND).any(dim=1, keepdim=True).to(queries.dtype)
        count = mask.sum(dim=(-2, -1), keepdim=True).clamp_min(1.0)
        mean = (queries * mask).sum(dim=(-2, -1), keepdim=True) / count
        var = ((queries - mean) ** 2 * mask).sum(dim=(-2, -1), keepdim=True) / count
        return var.sqrt().clamp_min(self.min_std)

    def _rho_and_weight(self, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Robust loss per residual and its IRLS weight ``rho'(r) / r``."""
        d = self.delta
        if self.loss == "l2":
            return 0.5 * r * r, torch.ones_like(r)
        a = r.abs()
        if self.loss == "huber":
            rho = torch.where(a <= d, 0.5 * r * r, d * (a - 0.5 * d))
            return rho, torch.where(a <= d, torch.ones_like(r), d / a.clamp_min(1e-12))
        z = (r / d) ** 2  # cauchy
        return 0.5 * d * d * torch.log1p(z), 1.0 / (1.0 + z)

    def _pyramid(self, images: torch.Tensor) -> list[torch.Tensor]:
        """Finest first; ``align_corners=True`` keeps normalised coordinates identical across levels."""
        out = [images]
        while len(out) < self.levels and min(out[-1].shape[-2:]) // 2 >= self.min_size:
            out.append(pyrdown(out[-1], align_corners=True))
        return out

    def _anchor_level(self, anchor: torch.Tensor, level: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The anchor level, its foreground indicator ``(B, 1, h, w)`` and that foreground less a band of
        ``visibility_band / 2^level`` px (at least 1) along its outline (where the query's visibility applies)."""
        mask = (anchor > _FOREGROUND).any(dim=1, keepdim=True).to(anchor.dtype)
        band = max(1, round(self.visibility_band / 2 ** level)) if self.visibility_band > 0 else 0
        inner = -F.max_pool2d(-mask, 2 * band + 1, stride=1, padding=band) if band else mask
        return anchor, mask, inner

    def _residuals(self, query: torch.Tensor, anchor: torch.Tensor, mask: torch.Tensor, H: torch.Tensor,
                   scale: torch.Tensor, grid: torch.Tensor | None = None, visible: torch.Tensor | None = None,
                   seen: torch.Tensor | None = None, inner: torch.Tensor | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Warped query, residuals ``(B, C, h, w)`` at pose ``H`` (normalised, ``(B, 3, 3)``) and the query's
        visibility in the anchor frame ``(B, 1, h, w)`` (None without one); ``grid``: the level's
        :func:`~matl.geometry.normalised_grid` ``(3, h * w)`` (None looks it up). ``visible`` ``(B, 1, h, w)``: the
        query's visibility at this level, warped here with the query; ``seen``: already in the anchor frame.

        With a visibility ``v`` the query's pixels are its print times ``v`` (a mask applied): on the inner
        foreground ``K`` (``inner``; ``F`` when None) the print is ``warped / v`` (normalised convolution; where ``v``
        is above 1e-3), the fit runs over ``F (1 - K + K v)`` and :meth:`_loss` weighs the residuals by
        ``1 - K + K v``.

        Lighting model: on the anchor's foreground ``F`` the warped query is ``gain * A + bias`` per
        channel, background stays 0, so ``r = (Iw - gain * A - bias * F) / scale`` over the whole frame.
        ``gain`` and ``bias`` are the least-squares fit over ``F`` at this pose (variable projection).
        The whole frame, background included, keeps the silhouette in the loss: restricted to ``F``,
        the loss would reward pushing the query's blurred outline out of the mask (a zoom-in bias of
        about a pixel); and with a model rather than per-image normalisation, background pixels are 0
        on both sides and do not pull the pose towards matching image statistics.
        """
        if visible is not None and seen is None:
            both = sample_by_normalised(torch.cat([query, visible], 1), H, grid)
            warped, seen = both[:, :-1], both[:, -1:]
        else:
            warped = sample_by_normalised(query, H, grid)
        if seen is None:
            count = mask.sum(dim=(-2, -1), keepdim=True).clamp_min(1.0)
            a_mean = (anchor * mask).sum(dim=(-2, -1), keepdim=True) / count
            w_mean = (warped * mask).sum(dim=(-2, -1), keepdim=True) / count
            a_c = (anchor - a_mean) * mask
            cov = (a_c * warped).sum(dim=(-2, -1), keepdim=True)
            var = (a_c * a_c).sum(dim=(-2, -1), keepdim=True).clamp_min(1e-12)
            gain = cov / var
            bias = w_mean - gain * a_mean
            return warped, (warped - gain * anchor - bias * mask) / scale, None
        inner = mask if inner is None else inner
        shown = (inner > 0) & (seen >= 1e-3)
        warped = torch.where(shown, warped / seen.clamp_min(1e-3), warped)
        fit = mask * (1.0 - inner + inner * seen)
        count = fit.sum(dim=(-2, -1), keepdim=True).clamp_min(1e-6)
        a_mean = (anchor * fit).sum(dim=(-2, -1), keepdim=True) / count
        w_mean = (warped * fit).sum(dim=(-2, -1), keepdim=True) / count
        centred = anchor - a_mean
        cov = (centred * fit * warped).sum(dim=(-2, -1), keepdim=True)
        var = (centred * fit * centred).sum(dim=(-2, -1), keepdim=True).clamp_min(1e-12)
        gain = cov / var
        bias = w_mean - gain * a_mean
        return warped, (warped - gain * anchor - bias * mask) / scale, seen

    def _loss(self, r: torch.Tensor, mask: torch.Tensor | None = None, seen: torch.Tensor | None = None
              ) -> torch.Tensor:
        """``(B,)`` mean robust loss; non-finite residuals give +inf (never accepted). With the query's visibility in
        the anchor frame ``seen`` ``(B, 1, h, w)`` (and ``mask``, the inner foreground ``K`` where it applies) each
        residual is weighted by ``1 - K + K v`` and an inner pixel the query does not show costs
        ``K (1 - v) rho(delta)``: every pixel counts, a pose cannot lower its loss by hiding the product."""
        rho = self._rho_and_weight(r)[0]
        if seen is None or mask is None:
            value = rho.mean(dim=(1, 2, 3))
        else:
            hidden = mask * (1.0 - seen)
            cost = self._rho_and_weight(torch.full_like(r[:1, :1, :1, :1], self.delta))[0]
            value = (rho * (1.0 - hidden)).mean(dim=(1, 2, 3)) + (hidden * cost[0, 0]).mean(dim=(1, 2, 3))
        return torch.nan_to_num(value, nan=math.inf, posinf=math.inf)

    def _well_conditioned(self, H: torch.Tensor) -> torch.Tensor:
        return ~degenerate_homographies(H, self.max_condition)

    # ------------------------------------------------------------------------------------- main
    @torch.no_grad()
    def __call__(self, queries: torch.Tensor, anchors: torch.Tensor, query_H_anchor: torch.Tensor,
                 visibility: torch.Tensor | None = None, upscale: torch.Tensor | None = None,
                 alternatives: torch.Tensor | None = None) -> RefineResult:
        """Refine a batch.

        Args:
            queries: ``(B, 3, H, W)`` query images.
            anchors: ``(B, 3, H, W)`` the selected anchor of each query.
            query_H_anchor: ``(B, 3, 3)`` pixel homographies (anchor pixel -> query pixel) to start from.
            visibility: ``(B, 1, H, W)`` each query's visibility in [0, 1] (its mask); None: every pixel.
            upscale: ``(B,)`` how many times each query's file was enlarged to the model's size (None: not known).
            alternatives: ``(B, K, 3, 3)`` other unrefined pixel poses, kept where their loss is lowest.
        Returns:
            :class:`RefineResult` with float64 pixel homographies.
        """
        if queries.shape != anchors.shape or queries.ndim != 4 or query_H_anchor.shape != (len(queries), 3, 3):
            raise ValueError(f"queries and anchors must be (B, C, H, W) of one shape and query_H_anchor (B, 3, 3), got "
                             f"{tuple(queries.shape)}, {tuple(anchors.shape)}, {tuple(query_H_anchor.shape)}")
        size = (int(queries.shape[-2]), int(queries.shape[-1]))
        queries, anchors = queries.float(), anchors.float()
        if upscale is not None and self.match_upscale is not None:
            anchors = self._at_query_resolution(anchors, upscale)
        if self.grayscale and queries.shape[1] == 3:
            luma = queries.new_tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)
            queries, anchors = (queries * luma).sum(1, keepdim=True), (anchors * luma).sum(1, keepdim=True)
        visible = None
        if visibility is not None and self.visibility and float(visibility.min()) < 1.0:
            visible = visibility.to(queries.device, queries.dtype)
        H0 = pixel_to_normalised(query_H_anchor.double(), size)
        scale = self._query_scale(queries)
        q_pyr = self._pyramid(queries)
        v_pyr = None if visible is None else self._pyramid(visible)
        a_pyr = [self._anchor_level(a, level) for level, a in enumerate(self._pyramid(anchors))]

        H = H0.clone()  # every pixel as it is: far from the answer the silhouette pulls
        for level in reversed(range(len(q_pyr))):  # coarsest first
            H = self._refine_level(q_pyr[level], *a_pyr[level], H, scale)
        seen_H = None
        if v_pyr is not None:  # and weighted by what each query shows, from the start
            seen_H = H0.clone()
            for level in reversed(range(len(q_pyr))):
                seen_H = self._refine_level(q_pyr[level], *a_pyr[level], seen_H, scale, v_pyr[level])

        anchor, mask, inner = a_pyr[0]
        starts = [H0]  # the unrefined poses, normalised: the start first
        if alternatives is not None:
            starts += [pixel_to_normalised(alternatives[:, k].double().to(H0.device), size)
                       for k in range(alternatives.shape[1])]

        def loss_at(P: torch.Tensor) -> torch.Tensor:  # every pose on every pixel (a hidden one at a fixed cost)
            _, r, seen = self._residuals(queries, anchor, mask, P, scale, visible=visible, inner=inner)
            return self._loss(r, inner, seen)

        losses = torch.stack([loss_at(P) for P in starts], 1)                      # (B, K + 1)
        loss_after = loss_at(H)
        if seen_H is not None:  # the refined pose of lower weighted loss
            seen_loss = loss_at(seen_H)
            lower = seen_loss < loss_after
            H = torch.where(lower[:, None, None], seen_H, H)
            loss_after = torch.where(lower, seen_loss, loss_after)
        best_loss, best = losses.min(1)  # the first of equals: the start before an alternative
        accepted = (loss_after < best_loss) & self._well_conditioned(H)
        pixel_starts = torch.stack([query_H_anchor.double(), *(normalised_to_pixel(P, size) for P in starts[1:])], 1)
        kept = pixel_starts[torch.arange(len(best)), best]
        H_px = torch.where(accepted[:, None, None], normalised_to_pixel(H, size), kept)
        loss_after = torch.where(accepted, loss_after, best_loss)
        source = torch.where(accepted, torch.zeros_like(best), best + 1)
        return RefineResult(H_px, losses[:, 0], loss_after, accepted, source)

    def _at_query_resolution(self, anchors: torch.Tensor, upscale: torch.Tensor) -> torch.Tensor:
        """``anchors`` of queries enlarged more than ``match_upscale`` times brought to their query's resolution."""
        size = max(int(anchors.shape[-2]), int(anchors.shape[-1]))
        sides = [max(4, round(size / float(u))) if self.match_upscale is not None and float(u) > self.match_upscale
                 else size for u in torch.as_tensor(upscale).tolist()]
        out = anchors.clone()
        for side in set(sides) - {size}:
            rows = [i for i, s in enumerate(sides) if s == side]
            out[rows] = at_resolution(anchors[rows], side)
        return out

    @staticmethod
    def _jacobian(warped: torch.Tensor, scale: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
        """``d r / d p`` ``(B, C * h * w, 8)``: the warped image's gradient times ``d(I + D(p)) x / dp``.

        With ``(gx, gy)`` the gradient in normalised coordinates at ``(x, y)``, the 8 columns are
        ``gx x, gx y, gx, gy x, gy y, gy, -(gx x + gy y) x, -(gx x + gy y) y`` (divided by ``scale``).
        ``gain`` and ``bias`` are held at their fit: by the variable-projection argument (Golub and
        Pereyra) the gradient is then exact; only the Gauss-Newton Hessian is approximate, and the
        Levenberg-Marquardt acceptance test makes up for it.
        """
        B, C, h, w = warped.shape
        gx, gy = _gradients(warped / scale)
        # pixel differences -> derivatives in normalised coordinates (align_corners=True)
        gx = gx.reshape(B, C, h * w) * ((w - 1) / 2.0)
        gy = gy.reshape(B, C, h * w) * ((h - 1) / 2.0)
        x, y = grid[0], grid[1]
        gxx, gyy = gx * x, gy * y
        radial = gxx + gyy
        J = torch.stack([gxx, gx * y, gx, gy * x, gyy, gy, -radial * x, -radial * y], dim=-1)  # (B, C, hw, 8)
        return J.reshape(B, C * h * w, 8)

    def _refine_level(self, query: torch.Tensor, anchor: torch.Tensor, mask: torch.Tensor, inner: torch.Tensor,
                      H: torch.Tensor, scale: torch.Tensor, visible: torch.Tensor | None = None) -> torch.Tensor:
        """Levenberg-Marquardt / IRLS iterations at one level (``visible``: the queries' visibility at this level);
        returns the normalised ``H`` ``(B, 3, 3)``."""
        B, C, h, w = query.shape
        grid = normalised_grid(h, w, query.device, query.dtype)                   # (3, h * w)
        corners = torch.tensor([[-1.0, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=torch.float64,
                               device=query.device)
        half_size = torch.tensor([(w - 1) / 2.0, (h - 1) / 2.0], dtype=torch.float64, device=query.device)
        lam = torch.full((B,), self.damping, dtype=torch.float64, device=query.device)
        eye8 = torch.eye(8, dtype=torch.float64, device=query.device)
        warped, r, seen = self._residuals(query, anchor, mask, H, scale, grid, visible, inner=inner)
        loss = self._loss(r, inner, seen)
        A = g = None
        for _ in range(self.iterations):
            if A is None:  # the normal equations change only when some query moved
                J = self._jacobian(warped, scale, grid)
                weight = self._rho_and_weight(r)[1]
                if seen is not None:
                    weight = weight * (1.0 - inner + inner * seen)
                Jw = J * weight.reshape(B, C * h * w, 1)
                A = (Jw.transpose(1, 2) @ J).double()                              # (B, 8, 8)
                g = (Jw.transpose(1, 2) @ r.reshape(B, C * h * w, 1)).double()     # (B, 8, 1)
            damped = A + lam[:, None, None] * torch.diag_embed(torch.diagonal(A, dim1=1, dim2=2)) + 1e-9 * eye8
            dp = -torch.linalg.solve(damped, g)[..., 0] * self.step
            dp = torch.nan_to_num(dp, nan=0.0, posinf=0.0, neginf=0.0)
            update = _update_matrix(dp)
            candidate = H @ update
            candidate = candidate / candidate[:, 2:3, 2:3]
            cand_warped, cand_r, cand_seen = self._residuals(query, anchor, mask, candidate, scale, grid, visible,
                                                             inner=inner)
            cand_loss = self._loss(cand_r, inner, cand_seen)
            better = cand_loss < loss                                              # per query
            if better.any():
                H = torch.where(better[:, None, None], candidate, H)
                warped = torch.where(better[:, None, None, None], cand_warped, warped)
                r = torch.where(better[:, None, None, None], cand_r, r)
                if seen is not None and cand_seen is not None:
                    seen = torch.where(better[:, None, None, None], cand_seen, seen)
                loss = torch.where(better, cand_loss, loss)
                A = g = None
            lam = torch.where(better, lam * 0.1, lam * 10.0).clamp(1e-9, 1e9)
            # converged: the update moves no image corner by more than `tolerance` pixels of this level
            moved = corners @ update.transpose(1, 2)
            moved = moved[..., :2] / moved[..., 2:]
            step_px = ((moved - corners[:, :2]) * half_size).norm(dim=-1).amax(dim=-1)
            if bool((step_px < self.tolerance).all()):
                break
        return H


class RefinedRecognizer:
    """A recognizer whose poses are refined against the anchor it selected (``refine=true``).

    Wraps anything returning a :class:`Prediction` with ``query_H_anchor`` and ``gallery_index``
    (MATL's :class:`~matl.models.recognizer.TensorRecognizer`, the STN classifier's, a keypoint baseline's);
    recognition is unchanged, ``query_H_anchor`` and ``query_H_canon`` are replaced. Queries without
    a match (``gallery_index == -1``) or without a pose keep their prediction. A refiner whose ``start``
    is ``stn`` refines ``s()``'s pose: the recognizer's alignment stage (``model.align``), whose job the
    refinement does, is skipped during the call, unless the refiner's ``compare_align`` asks for its pose as
    well (then run after the search; the refiner keeps whichever of the three poses has the lowest loss).

    Args:
        recognizer: the wrapped callable; its ``gallery`` attribute is used unless ``gallery`` is given.
        refiner: the refinement: :class:`~matl.inference.fast_refine.FastRefiner` (anything with an
            ``anchor_templates(anchor images)``: its per-anchor data is computed here, once for the gallery,
            and queries pass anchor indices) or :class:`PhotometricRefiner` (queries pass anchor images).
        templates: that per-anchor data when already computed for this gallery (another recognizer's).
        check: a second judge of the refined pose (``refine_check=verify``: the verification distance):
            ``check(queries (T, 3, S, S), query_H_anchor (T, 3, 3), gallery_index (T,), visibility (T, 1, S, S) or
            None) -> (T,)``, lower is better; a query keeps its unrefined pose where that pose scores lower than the
            refined one. None: the refiner's own loss alone decides.
    """

    def __init__(self, recognizer: Callable[[torch.Tensor], Prediction], refiner: Any,
                 gallery: Any = None, templates: Any = None, check: PoseCheck | None = None) -> None:
        self.recognizer, self.refiner, self.check = recognizer, refiner, check
        self.gallery = gallery if gallery is not None else recognizer.gallery
        if templates is None and hasattr(refiner, "anchor_templates"):
            templates = refiner.anchor_templates(self.gallery.images)  # once per gallery
        self.templates = templates  # per-anchor data of the inverse-compositional refiner (None: photometric)
        self.last: RefineResult | None = None  # the last batch's refinement details (for diagnostics)
        # MATL's recognizer can leave its pose out (this call composes the refined one); others answer in full
        self._pose_later = isinstance(recognizer, TensorRecognizer)

    def __getattr__(self, name: str) -> Any:  # search backend, features, ... of the wrapped recognizer
        if name in ("recognizer", "refiner", "gallery", "last", "templates", "_pose_later", "check"):
            raise AttributeError(name)
        return getattr(self.recognizer, name)

    @property
    def skips_align(self) -> bool:
        """The refiner starts from ``s()``'s pose (``refiner.start=stn``): the wrapped recognizer's learned
        alignment stage (``model.align``) is not run."""
        return getattr(self.refiner, "start", "align") == "stn" and getattr(self.recognizer, "align", None) is not None

    def _recognize(self, queries: torch.Tensor) -> Prediction:
        call = (lambda q: self.recognizer(q, pose=False)) if self._pose_later else self.recognizer
        if not self.skips_align:
            return call(queries)
        align = self.recognizer.align
        self.recognizer.align = None  # restored below, whatever happens
        try:
            return call(queries)
        finally:
            self.recognizer.align = align

    @torch.no_grad()
    def __call__(self, queries: torch.Tensor, visibility: torch.Tensor | None = None,
                 upscale: torch.Tensor | None = None) -> Prediction:
        """The refined prediction of ``queries`` ``(B, 3, S, S)``; ``visibility`` ``(B, 1, S, S)``: each query's
        visibility in [0, 1] (its mask; None: every pixel), ``upscale`` ``(B,)``: how many times each query's
        file was enlarged to the model's size (None: not known); both as the refiner takes them."""
        pred = self._recognize(queries)
        if pred.query_H_anchor is None:
            return pred
        g = self.gallery
        device = g.images.device
        index = pred.gallery_index.to(device)
        every = len(index) == 0 or int(index.min()) >= 0  # the usual case: no query is left without an anchor
        safe = index if every else index.clamp_min(0)
        start = pred.query_H_anchor.to(device, torch.float64)
        extra: dict[str, Any] = {}
        if visibility is not None:
            extra["visibility"] = visibility.to(device)
        if upscale is not None:
            extra["upscale"] = upscale
        if self.skips_align and getattr(self.refiner, "compare_align", False) and pred.warped is not None:
            aligned = self.recognizer.align.infer(queries, g.images[safe], pred.query_H_anchor, pred.warped)
            extra["alternatives"] = aligned.query_H_anchor.to(device, torch.float64)[:, None]
        if self.templates is not None:
            result = self.refiner(queries.to(device), safe, start, self.templates, **extra)
        else:
            result = self.refiner(queries.to(device), g.images[safe], start, **extra)
        self.last = result
        refined = result.query_H_anchor
        if self.check is not None and len(index):
            unrefined = [start, *extra["alternatives"].unbind(1)] if "alternatives" in extra else [start]
            refined = self._checked(queries, refined, unrefined, safe, visibility)
        canon = g.anchor_H_canon64()
        if every:
            H = refined
            pose = compose_query_H_canon(H, canon[safe])
        else:  # a query without an anchor keeps the recognizer's answer
            found = (index >= 0)[:, None, None]
            H = torch.where(found, refined, start)
            old = pred.query_H_canon  # None when left out above: the unrefined pose, composed here
            old = compose_query_H_canon(start, canon[safe]) if old is None else old.double().to(device)
            pose = torch.where(found, compose_query_H_canon(H, canon[safe]), old)
        device = pred.query_H_anchor.device
        return dataclasses.replace(pred, query_H_anchor=H.to(device), query_H_canon=pose.to(device))

    def _checked(self, queries: torch.Tensor, refined: torch.Tensor, unrefined: list[torch.Tensor],
                 index: torch.Tensor, visibility: torch.Tensor | None) -> torch.Tensor:
        """Per query, ``refined`` ``(B, 3, 3)`` where :attr:`check` scores it at most as every unrefined pose
        (``unrefined``: the start, then the alternatives, each ``(B, 3, 3)``), else the unrefined pose that scores
        lowest (the first of equals): every pose of every query judged in one call."""
        poses = [refined.to(unrefined[0]), *unrefined]
        n = len(poses)
        seen = None if visibility is None else visibility.repeat(n, 1, 1, 1)
        score = self.check(queries.repeat(n, 1, 1, 1), torch.cat(poses), index.repeat(n), seen).view(n, -1)
        best = score[1:].argmin(0)  # (B,) the lowest-scoring unrefined pose
        keep = (score[1 + best, torch.arange(len(index))] < score[0]).to(refined.device)[:, None, None]
        fallback = torch.stack(unrefined)[best.to(refined.device), torch.arange(len(index), device=refined.device)]
        return torch.where(keep, fallback, poses[0])
