"""Fast photometric pose refinement (``refiner=fast``, the default): inverse-compositional Gauss-Newton.

The query is aligned to the anchor the recognizer selected, as in
:class:`~matl.inference.refine.PhotometricRefiner`, but built so that a query costs a few warps:

* **Inverse compositional** (Baker and Matthews): the linearisation is taken about the *anchor*, so
  its gradients, the steepest-descent images ``sd = grad(T) dW/dp`` and the Gauss-Newton Hessian
  ``sum sd sd^T`` do not depend on the query. They are computed once per gallery anchor
  (:meth:`FastRefiner.prepare`, when the refined recognizer is built over a gallery: at enrolment)
  and gathered per query. The update is ``query_H_anchor <- query_H_anchor @ inv(I + D(dp))`` in
  normalised coordinates (``align_corners=True``, so one matrix serves every pyramid level).
* **Objective over the anchor's foreground only**: the pixels of the anchor that are non-zero
  (backgrounds are 0 by convention), eroded by ``erode`` pixels so that the blurred outline, which
  mixes in whatever lies behind the object in the query, does not count. Whatever the query shows
  outside the object costs nothing.
* **Lighting**: the steepest-descent images are projected orthogonal to the appearance basis
  ``{1, T}`` over the anchor's pixels ("project out", Baker and Matthews), so the Gauss-Newton step
  sees geometry only. The template ``T`` is normalised to zero mean and unit variance over its pixels; the
  warped query ``Iw`` is mapped into the template's photometric frame by the least-squares gain and
  bias over the same pixels (closed form, since ``T`` is normalised): ``r = (Iw - b) / a - T``. A
  gain / bias change of the query costs nothing; a query whose correlation coefficient with the
  anchor is at most ``min_correlation`` has an infinite loss.
* **Robust loss** ``mean rho(r)`` (``l2``, ``huber``, ``cauchy`` or ``geman_mcclure``, scale ``delta``
  in units of the template's std), minimised by iteratively re-weighted Gauss-Newton: the weighted
  Hessian ``sd^T diag(w) sd`` is one small product over the selected pixels (the precomputed
  unweighted one for ``l2``).
* **Pixel selection**: per level at most ``max_pixels`` foreground pixels, those of largest anchor
  gradient (they carry the alignment); all of them on small levels.
* **Coarse to fine** over ``levels`` Gaussian pyramid levels (a wider basin); at most ``iterations``
  per level, a query stops once its update moves no anchor corner by more than ``tolerance`` px of
  that level; the level ends when every query has stopped. Each level keeps, per query, the lowest
  loss pose it evaluated.
* **Never worse than its start**: at full resolution the objective of the final pose is compared
  with the start's; a query whose loss did not decrease, or whose matrix is non-finite or
  ill-conditioned, keeps its start.

Batched over queries (each with its own anchor); every step is a batched tensor operation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d, spatial_gradient
from kornia.geometry.transform import pyrdown

from matl.geometry import degenerate_homographies, normalised_to_pixel, pixel_to_normalised
from matl.inference.refine import RefineResult
from matl.utils.errors import MatlError

__all__ = ["FAST_LOSSES", "AnchorLevel", "AnchorTemplates", "FastRefiner"]

FAST_LOSSES = ("l2", "huber", "cauchy", "geman_mcclure")
_FOREGROUND = 1e-3  # an anchor pixel brighter than this in any channel is foreground (backgrounds are 0)
_LUMA = (0.299, 0.587, 0.114)


@dataclass
class AnchorLevel:
    """Precomputed data of one pyramid level for ``G`` anchors, ``n`` selected pixels each.

    Attributes:
        points: ``(G, n, 3)`` float32 homogeneous normalised coordinates ``(u, v, 1)`` of the pixels.
        template: ``(G, n)`` the normalised template (zero mean, unit variance over the pixels; 0 on padding).
        weight: ``(G, n)`` 1 for a selected foreground pixel, 0 for padding.
        count: ``(G,)`` number of selected pixels (at least 1).
        sd: ``(G, n, 8)`` steepest-descent images ``d T(W(x; p)) / dp`` at ``p = 0`` (0 on padding).
        hessian: ``(G, 8, 8)`` float64 ``sum sd sd^T``.
        size: ``(h, w)`` of the level.
    """

    points: torch.Tensor
    template: torch.Tensor
    weight: torch.Tensor
    count: torch.Tensor
    sd: torch.Tensor
    hessian: torch.Tensor
    size: tuple[int, int]

    def take(self, index: torch.Tensor) -> AnchorLevel:
        """The rows of ``index`` ``(B,)`` (one anchor per query)."""
        return AnchorLevel(self.points[index], self.template[index], self.weight[index], self.count[index],
                           self.sd[index], self.hessian[index], self.size)


@dataclass
class AnchorTemplates:
    """What :class:`FastRefiner` precomputes per anchor: one :class:`AnchorLevel` per pyramid level, finest first.

    Attributes:
        levels: finest first.
        image_size: ``(H, W)`` of the anchors.
    """

    levels: list[AnchorLevel]
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return int(self.levels[0].points.shape[0])

    def take(self, index: torch.Tensor) -> AnchorTemplates:
        return AnchorTemplates([level.take(index) for level in self.levels], self.image_size)


def _corner_jacobian(device: torch.device) -> torch.Tensor:
    """``(8, 8)``: ``dp @ J`` is the first-order motion ``(x0, y0, x1, y1, ...)`` of the 4 normalised
    corners under ``I + D(dp)``."""
    rows = []
    for x, y in ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)):
        rows.append([x, y, 1.0, 0.0, 0.0, 0.0, -x * x, -x * y])
        rows.append([0.0, 0.0, 0.0, x, y, 1.0, -x * y, -y * y])
    return torch.tensor(rows, device=device).T.contiguous()


def _update_matrix(p: torch.Tensor) -> torch.Tensor:
    """``I + D(p)``: ``(B, 8) -> (B, 3, 3)``."""
    full = torch.cat([p, torch.zeros_like(p[:, :1])], dim=1).view(-1, 3, 3)
    return full + torch.eye(3, dtype=p.dtype, device=p.device)


class FastRefiner:
    """Inverse-compositional refinement of ``query_H_anchor`` against precomputed anchors.

    Args:
        iterations: most Gauss-Newton iterations per pyramid level.
        levels: pyramid levels (1: full resolution only); the coarsest keeps at least ``min_size`` px per side.
        loss: ``l2``, ``huber``, ``cauchy`` or ``geman_mcclure`` on the residuals.
        delta: scale of the robust loss, in units of the template's std.
        damping: Levenberg-Marquardt damping added to the Hessian's diagonal (relative to it).
        min_size: smallest pyramid level side, pixels.
        max_pixels: most pixels per level (largest anchor gradient first); null: every foreground pixel.
        erode: pixels by which the anchor's foreground is eroded at every level (0: the whole foreground).
        min_correlation: a warped query whose correlation coefficient with the template is at most
            this has an infinite loss (not the object, or not lit like one).
        max_condition: a refined normalised matrix with a larger condition number is rejected.
        tolerance: a query stops at a level once its update moves no corner by more than this many
            pixels of that level.
        threads: torch threads during the refinement (null: the caller's).
        blur: std in pixels of a Gaussian applied to query and anchor alike before the pyramid (0: none):
            evens out the resampling blur of a warped query against the sharp anchor.
    """

    def __init__(self, iterations: int = 10, levels: int = 3, loss: str = "huber", delta: float = 1.0,
                 damping: float = 1e-4, min_size: int = 8, max_pixels: int | None = None, erode: int = 1,
                 min_correlation: float = 0.05, max_condition: float = 1e4, tolerance: float = 0.01,
                 threads: int | None = None, blur: float = 0.0) -> None:
        if int(iterations) < 0:
            raise MatlError(f"refiner.iterations must be >= 0, got {iterations}")
        if int(levels) < 1:
            raise MatlError(f"refiner.levels must be >= 1, got {levels}")
        if loss not in FAST_LOSSES:
            raise MatlError(f"refiner.loss must be one of {', '.join(FAST_LOSSES)}, got {loss!r}")
        if float(delta) <= 0 or float(damping) < 0 or int(min_size) < 4:
            raise MatlError(f"refiner.delta must be > 0, damping >= 0 and min_size >= 4; got delta={delta}, "
                            f"damping={damping}, min_size={min_size}")
        if max_pixels is not None and int(max_pixels) < 16:
            raise MatlError(f"refiner.max_pixels must be null or >= 16, got {max_pixels}")
        if int(erode) < 0 or float(tolerance) < 0 or (threads is not None and int(threads) < 1):
            raise MatlError(f"refiner.erode and tolerance must be >= 0 and threads null or >= 1; got erode={erode}, "
                            f"tolerance={tolerance}, threads={threads}")
        self.iterations, self.levels, self.loss, self.delta = int(iterations), int(levels), loss, float(delta)
        self.damping, self.min_size, self.erode = float(damping), int(min_size), int(erode)
        self.max_pixels = None if max_pixels is None else int(max_pixels)
        self.min_correlation, self.max_condition = float(min_correlation), float(max_condition)
        self.tolerance = float(tolerance)
        self.threads = None if threads is None else int(threads)
        self.blur = float(blur)
        self._templates: AnchorTemplates | None = None  # set by prepare()

    # ------------------------------------------------------------------------------ anchors
    def _pyramid(self, images: torch.Tensor) -> list[torch.Tensor]:
        """Finest first, ``(B, C, h_l, w_l)``; ``align_corners=True`` keeps normalised coordinates across levels."""
        out = [images]
        while len(out) < self.levels and min(out[-1].shape[-2:]) // 2 >= self.min_size:
            out.append(pyrdown(out[-1], align_corners=True))
        return out

    def _luminance(self, images: torch.Tensor) -> torch.Tensor:
        """``(B, 3, H, W)`` -> ``(B, 1, H, W)`` float32 (ITU-R BT.601), blurred by ``blur``; one channel is kept."""
        images = images.float()
        if images.shape[1] != 1:
            images = (images * images.new_tensor(_LUMA).view(1, 3, 1, 1)).sum(1, keepdim=True)
        if self.blur > 0:
            k = 2 * math.ceil(2 * self.blur) + 1
            images = gaussian_blur2d(images, (k, k), (self.blur, self.blur), border_type="constant")
        return images

    @torch.no_grad()
    def anchor_templates(self, anchors: torch.Tensor, chunk: int = 256) -> AnchorTemplates:
        """Everything the refinement needs of ``anchors`` ``(G, 3, H, W)``, computed once per anchor.

        Anchors are processed independently (chunks of ``chunk``), so the rows of a gallery's
        templates equal those of each anchor computed alone.
        """
        if anchors.ndim != 4:
            raise ValueError(f"anchors must be (G, C, H, W), got {tuple(anchors.shape)}")
        parts = [self._anchor_chunk(anchors[i:i + chunk]) for i in range(0, len(anchors), chunk)] or \
            [self._anchor_chunk(anchors[:0])]
        levels = [AnchorLevel(*(torch.cat([p[k].__dict__[f] for p in parts]) for f in
                                ("points", "template", "weight", "count", "sd", "hessian")), parts[0][k].size)
                  for k in range(len(parts[0]))]
        return AnchorTemplates(levels, (int(anchors.shape[-2]), int(anchors.shape[-1])))

    def _anchor_chunk(self, anchors: torch.Tensor) -> list[AnchorLevel]:
        G = len(anchors)
        gray = self._luminance(anchors)
        mask = (anchors.float() > _FOREGROUND).any(dim=1, keepdim=True).float()    # (G, 1, H, W), before the blur
        out = []
        for level, (image, soft) in enumerate(zip(self._pyramid(gray), self._pyramid(mask), strict=True)):
            h, w = image.shape[-2:]
            fg = soft > 0.5 if level else soft > 0
            if self.erode:  # erosion = not (dilated background)
                k = 2 * self.erode + 1
                fg = ~(F.max_pool2d((~fg).float(), k, stride=1, padding=self.erode) > 0)
            grad = spatial_gradient(image, mode="diff", normalized=True)[:, 0]      # (G, 2, h, w) d/dx, d/dy px
            gx = grad[:, 0].reshape(G, -1) * ((w - 1) / 2.0)                       # per normalised unit
            gy = grad[:, 1].reshape(G, -1) * ((h - 1) / 2.0)
            flat_fg = fg.reshape(G, -1)
            n = h * w if self.max_pixels is None else min(self.max_pixels, h * w)
            score = torch.where(flat_fg, gx * gx + gy * gy, torch.full_like(gx, -1.0))
            chosen = score.topk(n, dim=1, sorted=False).indices.sort(dim=1).values if n < h * w else \
                torch.arange(h * w, device=anchors.device).expand(G, -1)
            weight = flat_fg.gather(1, chosen).float()                              # (G, n)
            count = weight.sum(1).clamp_min(1.0)
            values = image.reshape(G, -1).gather(1, chosen)
            mean = (values * weight).sum(1, keepdim=True) / count[:, None]
            std = (((values - mean) ** 2 * weight).sum(1, keepdim=True) / count[:, None]).sqrt().clamp_min(1e-4)
            template = (values - mean) / std * weight
            u = torch.linspace(-1.0, 1.0, w, device=anchors.device)
            v = torch.linspace(-1.0, 1.0, h, device=anchors.device)
            x, y = u[chosen % w], v[torch.div(chosen, w, rounding_mode="floor")]
            points = torch.stack([x, y, torch.ones_like(x)], dim=-1)                # (G, n, 3)
            gx, gy = gx.gather(1, chosen) / std * weight, gy.gather(1, chosen) / std * weight
            radial = gx * x + gy * y
            sd = torch.stack([gx * x, gx * y, gx, gy * x, gy * y, gy, -radial * x, -radial * y], dim=-1)
            # project out the appearance basis {1, T} (the gain and bias): sd orthogonal to both over the pixels
            w3 = weight[..., None]
            sd = (sd - (sd * w3).sum(1, keepdim=True) / count[:, None, None]) * w3
            sd = sd - template[..., None] * ((template[..., None] * sd).sum(1, keepdim=True) / count[:, None, None])
            sd64 = sd.double()
            out.append(AnchorLevel(points, template, weight, count, sd, sd64.transpose(1, 2) @ sd64,
                                   (int(h), int(w))))
        return out

    def prepare(self, anchors: torch.Tensor) -> FastRefiner:
        """Precompute the templates of a gallery's anchors ``(G, 3, H, W)``; returns self."""
        self._templates = self.anchor_templates(anchors)
        return self

    # ------------------------------------------------------------------------------ objective
    def _rho_and_weight(self, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Robust loss per residual and its IRLS weight ``rho'(r) / r``."""
        d = self.delta
        if self.loss == "l2":
            return 0.5 * r * r, torch.ones_like(r)
        if self.loss == "huber":
            a = r.abs()
            inside = a <= d
            return torch.where(inside, 0.5 * r * r, d * (a - 0.5 * d)), torch.where(inside, 1.0, d / a.clamp_min(1e-12))
        z = (r / d) ** 2
        if self.loss == "cauchy":
            return 0.5 * d * d * torch.log1p(z), 1.0 / (1.0 + z)
        return 0.5 * r * r / (1.0 + z), 1.0 / (1.0 + z) ** 2  # geman_mcclure

    def _evaluate(self, query: torch.Tensor, anchor: AnchorLevel, H: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Residuals ``(B, n)``, IRLS weights ``(B, n)`` (0 off the foreground) and loss ``(B,)`` at ``H``.

        Args:
            query: ``(B, 1, h, w)`` the query's level.
            anchor: the level's anchors, one per query.
            H: ``(B, 3, 3)`` float64 normalised ``query_H_anchor``.
        """
        pts = anchor.points @ H.float().transpose(1, 2)                              # (B, n, 3)
        grid = pts[..., :2] / pts[..., 2:]
        warped = F.grid_sample(query, grid[:, None], mode="bilinear", padding_mode="zeros",
                               align_corners=True)[:, 0, 0]                          # (B, n)
        # pixels the pose maps outside the query are missing (not black)
        wt = anchor.weight * (grid.abs().amax(-1) <= 1.0)
        count = wt.sum(1)
        safe = count.clamp_min(1.0)
        template = anchor.template * wt
        bias = (warped * wt).sum(1) / safe
        t_mean = template.sum(1) / safe
        t_var = (template * anchor.template).sum(1) / safe - t_mean * t_mean
        gain = ((warped * template).sum(1) / safe - bias * t_mean) / t_var.clamp_min(1e-6)
        spread = ((warped * warped * wt).sum(1) / safe - bias * bias).clamp_min(0.0).sqrt()
        # gain * sqrt(t_var) / spread: the correlation coefficient
        valid = (gain * t_var.clamp_min(0.0).sqrt() > self.min_correlation * spread) & (count >= 0.5 * anchor.count)
        scale = (spread / t_var.clamp_min(1e-12).sqrt()).clamp_min(1e-6)  # the query's std in template units
        r = ((warped - bias[:, None]) / scale[:, None] + t_mean[:, None] - anchor.template) * wt
        rho, w = self._rho_and_weight(r)
        loss = (rho * wt).sum(1) / safe
        loss = torch.where(valid & torch.isfinite(loss), loss, torch.full_like(loss, math.inf))
        return r, w * wt, loss

    def _level(self, query: torch.Tensor, anchor: AnchorLevel, H: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """Gauss-Newton at one level; returns the lowest-loss pose ``(B, 3, 3)`` and its loss ``(B,)``."""
        B = len(H)
        h, w = anchor.size
        corner_J = _corner_jacobian(H.device)                                        # (8, 8)
        half = torch.tensor([(w - 1) / 2.0, (h - 1) / 2.0], device=H.device)
        active = torch.ones(B, dtype=torch.bool, device=H.device)
        best_H, best_loss = H, torch.full((B,), math.inf, dtype=torch.float32, device=H.device)
        eye8 = torch.eye(8, dtype=torch.float64, device=H.device)
        for it in range(self.iterations + 1):
            r, wt, loss = self._evaluate(query, anchor, H)
            better = loss < best_loss
            best_H = torch.where(better[:, None, None], H, best_H)
            best_loss = torch.where(better, loss, best_loss)
            active = active & better  # a step that did not lower the loss ends that query's level
            if it == self.iterations or not bool(active.any()):
                break
            g = (anchor.sd.transpose(1, 2) @ (wt * r)[..., None]).double()            # (B, 8, 1)
            if self.loss == "l2":
                A = anchor.hessian
            else:
                A = (anchor.sd.transpose(1, 2) @ (anchor.sd * wt[..., None])).double()
            A = A + self.damping * torch.diag_embed(torch.diagonal(A, dim1=1, dim2=2)) + 1e-9 * eye8
            dp = torch.nan_to_num(torch.linalg.solve(A, g)[..., 0], nan=0.0, posinf=0.0, neginf=0.0)
            # first-order motion of the 4 corners, px of this level: (B, 8) -> (B, 4, 2)
            step_px = (dp.float() @ corner_J).view(B, 4, 2).mul(half).norm(dim=-1).amax(dim=-1)
            # inv(I + D(dp)) to first order: I - D(dp) (exact at convergence, where dp -> 0)
            candidate = H @ _update_matrix(-dp)
            candidate = candidate / candidate[:, 2:3, 2:3]
            H = torch.where(active[:, None, None] & torch.isfinite(candidate).all(2).all(1)[:, None, None],
                            candidate, H)
            active = active & (step_px >= self.tolerance)
            if not bool(active.any()):  # every query converged: evaluate the last step, then stop
                r, wt, loss = self._evaluate(query, anchor, H)
                better = loss < best_loss
                best_H = torch.where(better[:, None, None], H, best_H)
                best_loss = torch.where(better, loss, best_loss)
                break
        return best_H, best_loss

    # ------------------------------------------------------------------------------ main
    @torch.no_grad()
    def __call__(self, queries: torch.Tensor, anchor_index: torch.Tensor, query_H_anchor: torch.Tensor,
                 templates: AnchorTemplates | None = None) -> RefineResult:
        """Refine a batch against precomputed anchors.

        Args:
            queries: ``(B, 3, H, W)`` query images.
            anchor_index: ``(B,)`` long, each query's anchor in ``templates``.
            query_H_anchor: ``(B, 3, 3)`` pixel homographies (anchor pixel -> query pixel) to start from.
            templates: :meth:`anchor_templates` of the gallery; None: those of :meth:`prepare`.
        Returns:
            :class:`~matl.inference.refine.RefineResult` with float64 pixel homographies.
        """
        templates = templates if templates is not None else self._templates
        if templates is None:
            raise RuntimeError("FastRefiner: call prepare(gallery images) or pass templates")
        if queries.ndim != 4 or query_H_anchor.shape != (len(queries), 3, 3) or anchor_index.shape != (len(queries),):
            raise ValueError(f"queries must be (B, C, H, W), anchor_index (B,) and query_H_anchor (B, 3, 3), got "
                             f"{tuple(queries.shape)}, {tuple(anchor_index.shape)}, {tuple(query_H_anchor.shape)}")
        size = (int(queries.shape[-2]), int(queries.shape[-1]))
        if size != templates.image_size:
            raise ValueError(f"queries are {size} but the anchors {templates.image_size}")
        previous = torch.get_num_threads()
        if self.threads is not None:
            torch.set_num_threads(self.threads)
        try:
            return self._refine(queries, templates.take(anchor_index.to(templates.levels[0].points.device)),
                                query_H_anchor, size)
        finally:
            if self.threads is not None:
                torch.set_num_threads(previous)

    def refine_images(self, queries: torch.Tensor, anchors: torch.Tensor, query_H_anchor: torch.Tensor) -> RefineResult:
        """The same refinement with each query's anchor image ``(B, 3, H, W)`` given (templates computed here)."""
        return self(queries, torch.arange(len(anchors), device=anchors.device), query_H_anchor,
                    self.anchor_templates(anchors))

    def _refine(self, queries: torch.Tensor, anchors: AnchorTemplates, query_H_anchor: torch.Tensor,
                size: tuple[int, int]) -> RefineResult:
        H0 = query_H_anchor.double()
        finite0 = torch.isfinite(H0).all(2).all(1)
        H0n = pixel_to_normalised(torch.where(finite0[:, None, None], H0, torch.eye(3, dtype=H0.dtype,
                                                                                    device=H0.device)), size)
        pyramid = self._pyramid(self._luminance(queries))[:len(anchors.levels)]
        H = H0n
        for level in reversed(range(len(pyramid))):  # coarsest first
            H, loss = self._level(pyramid[level], anchors.levels[level], H)
        loss_before = self._evaluate(pyramid[0], anchors.levels[0], H0n)[2]
        loss_before = torch.where(finite0, loss_before, torch.full_like(loss_before, math.inf))
        accepted = finite0 & (loss < loss_before) & ~degenerate_homographies(H, self.max_condition)
        loss_after = torch.where(accepted, loss, loss_before)
        H_px = torch.where(accepted[:, None, None], normalised_to_pixel(H, size), H0)
        return RefineResult(H_px, loss_before, loss_after, accepted)
