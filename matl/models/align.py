"""An anchor-conditioned alignment stage after ``s()`` (beyond the paper; ``model.align``, null = off).

``s()`` regresses ``query_H_anchor`` from the query alone, so on products it never saw its pose is off
by the amount a regressor without a template cannot know. This stage sees the pair: the query warped
by the pose so far and the selected anchor, and predicts a *residual* homography that brings the one
onto the other. It is applied ``iterations`` times with the same weights, each time on the *original*
query warped by the composition so far (never a warp of a warp).

Convention (the STN's own, forward compositional, right-multiplied, in normalised coordinates):

    ``query_H_anchor_norm <- query_H_anchor_norm @ residual_norm``

``residual_norm`` is a sampling homography of the anchor frame: the refined warp at anchor pixel ``x``
samples the previous warp at ``residual_norm @ x``. It is given by 4-point offsets: corner ``i`` of
the normalised square (``(-1, -1)``, ``(1, -1)``, ``(1, 1)``, ``(-1, 1)``: top-left, top-right,
bottom-right, bottom-left) maps to ``corner_i + offset_i``, i.e. ``offset_i`` is where, in the
previous warp, the anchor's corner ``i`` is found. Offsets are ``max_offset * tanh(.)`` of the last
layer, which is zero-initialised: at start every residual is exactly the identity and the stage
leaves the pose as ``s()`` gave it. With ``max_offset <= 0.5`` every corner stays within a box of
half-width 0.5 around its own corner, so the quadrilateral is always strictly convex (no fold).

Training (``MATLModule``): the anchor is the one Eq. 3 selected, the loss is the appearance loss of
the anchor against the query warped by the final composed homography (no pose labels). Inference
(:class:`matl.models.recognizer.TensorRecognizer`): the anchor is the nearest gallery anchor the search
returned; the stage's ``query_H_anchor`` replaces the STN's in the Prediction.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from matl.geometry import (
    guard_homographies,
    normalised_to_pixel,
    pixel_to_normalised,
    sample_by_normalised,
    scale_to_unit,
)
from matl.utils.errors import MatlError

#: the normalised image corners, top-left, top-right, bottom-right, bottom-left
SQUARE = ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))


def square_to_quad(offsets: torch.Tensor) -> torch.Tensor:
    """The homography mapping the normalised square's corners to ``corner_i + offsets[:, i]``.

    Closed form (the square-to-quadrilateral construction through the unit square) rather than
    kornia's ``get_perspective_transform``, which solves an 8x8 linear system: that rounds, so zero
    offsets would not give the identity bit for bit; here they do (every constant is a power of two).
    The two agree to float rounding on any convex quadrilateral (tested).

    Args:
        offsets: ``(B, 4, 2)`` corner displacements ``(dx, dy)`` in normalised coordinates, corners in
            :data:`SQUARE`'s order.
    Returns:
        ``(B, 3, 3)`` normalised homographies, ``H[2, 2] = 1``.
    """
    if offsets.ndim != 3 or tuple(offsets.shape[1:]) != (4, 2):
        raise ValueError(f"offsets must be (B, 4, 2), got {tuple(offsets.shape)}")
    square = torch.tensor(SQUARE, dtype=offsets.dtype, device=offsets.device)
    quad = square + offsets                                        # (B, 4, 2)
    (x0, x1, x2, x3), (y0, y1, y2, y3) = quad[..., 0].unbind(1), quad[..., 1].unbind(1)
    # unit square (0,0), (1,0), (1,1), (0,1) -> p0, p1, p2, p3
    dx1, dx2, dx3 = x1 - x2, x3 - x2, x0 - x1 + x2 - x3
    dy1, dy2, dy3 = y1 - y2, y3 - y2, y0 - y1 + y2 - y3
    det = dx1 * dy2 - dx2 * dy1
    g = (dx3 * dy2 - dx2 * dy3) / det
    h = (dx1 * dy3 - dx3 * dy1) / det
    one = torch.ones_like(g)
    quad_H_unit = torch.stack([
        torch.stack([x1 - x0 + g * x1, x3 - x0 + h * x3, x0], -1),
        torch.stack([y1 - y0 + g * y1, y3 - y0 + h * y3, y0], -1),
        torch.stack([g, h, one], -1),
    ], -2)
    # normalised square [-1, 1]^2 -> unit square: u = (x + 1) / 2
    unit_H_square = torch.tensor([[0.5, 0.0, 0.5], [0.0, 0.5, 0.5], [0.0, 0.0, 1.0]], dtype=offsets.dtype,
                                 device=offsets.device)
    return scale_to_unit(quad_H_unit @ unit_H_square)


@dataclass
class AlignOutput:
    """What the stage returns for a batch of B queries."""

    query_H_anchor: torch.Tensor       # (B, 3, 3) pixel, the final composed homography
    query_H_anchor_norm: torch.Tensor  # (B, 3, 3) the same in normalised coordinates
    residual: torch.Tensor             # (B, 3, 3) normalised, the product of the steps' residuals
    warped: torch.Tensor | None        # (B, 3, S, S) the query warped by the final homography (None if not asked)
    degenerate: torch.Tensor           # (B,) bool, some step's residual was replaced by the identity


class ResidualRegressor(nn.Module):
    """The pair -> 4-point offsets network: ``(warped (B, 3, S, S), anchor (B, 3, S, S)) -> (B, 4, 2)``.

    The 6-channel pair is average-pooled by ``downsample``, then 3x3 conv + ReLU + 2x2 max pool per
    entry of ``channels``, FC ``hidden``, FC 8, ``max_offset * tanh``. The last layer is zero, so
    every offset is exactly 0 until training moves it.
    """

    def __init__(self, image_size: int = 100, downsample: int = 2, channels: tuple[int, ...] = (16, 32, 64),
                 hidden: int = 128, max_offset: float = 0.5) -> None:
        super().__init__()
        if int(downsample) < 1:
            raise MatlError(f"model.align.downsample={downsample} is invalid: use an integer >= 1")
        if not 0.0 < float(max_offset) <= 0.5:
            raise MatlError(f"model.align.max_offset={max_offset} is invalid: use a number in (0, 0.5] "
                            "(normalised units; above 0.5 a corner may fold over its neighbours)")
        if len(channels) < 1 or any(int(c) < 1 for c in channels):
            raise MatlError(f"model.align.channels={list(channels)} is invalid: use one or more positive widths")
        self.downsample, self.max_offset = int(downsample), float(max_offset)
        layers: list[nn.Module] = []
        width = 6
        for c in channels:
            layers += [nn.Conv2d(width, int(c), 3, padding=1), nn.ReLU(), nn.MaxPool2d(2)]
            width = int(c)
        self.features = nn.Sequential(*layers)
        side = -(-int(image_size) // self.downsample)
        try:
            with torch.no_grad():
                flat = self.features(torch.zeros(1, 6, side, side)).numel()
        except RuntimeError:  # a pooling layer got a 1-pixel map
            flat = 0
        if flat == 0:
            raise MatlError(f"model.align: {len(channels)} pooling layers leave nothing of a {side} px input; "
                            "use fewer channels entries or a smaller downsample")
        self.fc1 = nn.Linear(flat, int(hidden))
        self.fc2 = nn.Linear(int(hidden), 8)
        nn.init.zeros_(self.fc2.weight)
        nn.init.zeros_(self.fc2.bias)

    def forward(self, warped: torch.Tensor, anchor: torch.Tensor) -> torch.Tensor:
        x = torch.cat([warped, anchor], dim=1)
        if self.downsample > 1:
            x = F.avg_pool2d(x, self.downsample, ceil_mode=True)
        x = self.features(x).flatten(1)
        raw = self.fc2(F.relu(self.fc1(x)))
        return (self.max_offset * torch.tanh(raw)).view(-1, 4, 2)


class AlignmentStage(nn.Module):
    """Refines ``query_H_anchor`` against a given anchor by a learned, iterated residual (module docstring).

    Args:
        image_size: ``S``, the side of the square model images.
        iterations: residual steps, tied weights (>= 1).
        downsample, channels, hidden, max_offset: the :class:`ResidualRegressor`.
        max_condition: a step whose residual has a larger condition number (or a non-finite entry)
            is replaced by the identity (:func:`matl.geometry.guard_homographies`), so that step keeps
            the pose it was given.
        detach_input: training only: the incoming pose and warp are detached, so the stage's loss
            trains the stage alone and ``s()`` keeps exactly its own training signal (Eq. 4 on its
            warp, which is also what ``c()`` sees for recognition). False lets the stage's loss reach
            ``s()`` as well.
        lr_scale: training only: the stage's parameters are optimised at this multiple of
            ``model.optimizer.lr`` (:meth:`matl.models.module.MATLModule.optimizer_param_groups`).
        optimizer: training only: a partially-instantiated optimiser of the stage's own (e.g. Adam),
            so that the stage need not train under ``s()``'s SGD; None: one optimiser for the whole
            model, the stage in its own group at ``lr_scale``. Given, the model steps both itself
            (:meth:`matl.models.module.MATLModule.configure_optimizers`) and ``lr_scale`` is unused.
    """

    def __init__(self, image_size: int = 100, iterations: int = 3, downsample: int = 2,
                 channels: tuple[int, ...] = (16, 32, 64), hidden: int = 128, max_offset: float = 0.5,
                 max_condition: float = 1e4, detach_input: bool = True, lr_scale: float = 1.0,
                 optimizer: Callable[..., torch.optim.Optimizer] | None = None) -> None:
        super().__init__()
        if optimizer is not None and not callable(optimizer):
            raise MatlError("model.align.optimizer must be an optimiser factory (_target_: torch.optim.Adam with "
                            "_partial_: true) or null")
        self.optimizer_factory = optimizer
        if not isinstance(iterations, int) or isinstance(iterations, bool) or iterations < 1:
            raise MatlError(f"model.align.iterations={iterations} is invalid: use an integer >= 1")
        if not float(max_condition) > 1.0:
            raise MatlError(f"model.align.max_condition={max_condition} is invalid: use a number > 1")
        self.image_size, self.iterations = int(image_size), int(iterations)
        if not float(lr_scale) > 0.0:
            raise MatlError(f"model.align.lr_scale={lr_scale} is invalid: use a number > 0")
        self.max_condition, self.detach_input = float(max_condition), bool(detach_input)
        self.lr_scale = float(lr_scale)
        self.regressor = ResidualRegressor(image_size, downsample, tuple(channels), hidden, max_offset)

    def _check(self, queries: torch.Tensor, anchors: torch.Tensor, query_H_anchor: torch.Tensor,
               warped: torch.Tensor | None) -> None:
        S = self.image_size
        for name, images in (("queries", queries), ("anchors", anchors), ("warped", warped)):
            if images is not None and (images.ndim != 4 or tuple(images.shape[1:]) != (3, S, S)):
                raise ValueError(f"alignment stage: {name} must be (B, 3, {S}, {S}), got {tuple(images.shape)}")
        B = len(queries)
        if len(anchors) != B or (warped is not None and len(warped) != B):
            raise ValueError(f"alignment stage: one anchor (and warp) per query, got {B} queries, {len(anchors)} "
                             f"anchors{'' if warped is None else f', {len(warped)} warps'}")
        if tuple(query_H_anchor.shape) != (B, 3, 3):
            raise ValueError(f"alignment stage: query_H_anchor must be ({B}, 3, 3), got {tuple(query_H_anchor.shape)}")

    def forward(self, queries: torch.Tensor, anchors: torch.Tensor, query_H_anchor: torch.Tensor,
                warped: torch.Tensor | None = None, return_warped: bool = True) -> AlignOutput:
        """Align each query to its anchor, starting from ``query_H_anchor``.

        Args:
            queries: ``(B, 3, S, S)`` the original queries.
            anchors: ``(B, 3, S, S)`` the anchor of each query (Eq. 3's in training, the search's at test time).
            query_H_anchor: ``(B, 3, 3)`` pixel homographies to start from (the STN's), anchor -> query.
            warped: ``(B, 3, S, S)`` the queries already warped by ``query_H_anchor`` (``s(query)``),
                which saves the first warp; None computes it.
            return_warped: also warp the queries by the final homography (the training loss needs it).
        Returns:
            :class:`AlignOutput`. A query whose residuals all are the identity (a zero-initialised stage,
            or every step guarded) gets its ``query_H_anchor`` back bit for bit, not its round trip
            through normalised coordinates.
        """
        self._check(queries, anchors, query_H_anchor, warped)
        if self.training and self.detach_input:
            query_H_anchor = query_H_anchor.detach()
            warped = warped.detach() if warped is not None else None
        size = (self.image_size, self.image_size)
        eye = torch.eye(3, dtype=queries.dtype, device=queries.device)
        H = pixel_to_normalised(query_H_anchor.to(queries.dtype), size)
        current = sample_by_normalised(queries, H) if warped is None else warped
        residual = eye.expand(len(queries), 3, 3)
        degenerate = torch.zeros(len(queries), dtype=torch.bool, device=queries.device)
        for step in range(self.iterations):
            R, bad = guard_homographies(square_to_quad(self.regressor(current, anchors)), self.max_condition, eye)
            H, residual, degenerate = H @ R, residual @ R, degenerate | bad
            if return_warped or step + 1 < self.iterations:
                current = sample_by_normalised(queries, H)
        pixel = normalised_to_pixel(H, size)
        unchanged = (residual == eye).flatten(1).all(dim=1)
        pixel = torch.where(unchanged[:, None, None], query_H_anchor.to(pixel.dtype), pixel)
        return AlignOutput(pixel, H, residual, current if return_warped else None, degenerate)

    @torch.no_grad()
    def infer(self, queries: torch.Tensor, anchors: torch.Tensor, query_H_anchor: torch.Tensor,
              warped: torch.Tensor | None = None) -> AlignOutput:
        """``forward`` without gradient and without the final warp: the recognizer's call."""
        return self.forward(queries, anchors, query_H_anchor, warped, return_warped=False)
