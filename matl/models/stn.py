"""The spatial transformer s() (paper Sec. 3.1, 5.2): a homography regressor and a warp.

Convention:
    The regressor predicts the *sampling* homography ``query_H_anchor`` (anchor-frame pixel ->
    query pixel), in normalised coordinates, as identity + 8 learned entries. The STN output is
    ``s(query)(x) = query(query_H_anchor @ x)``: the query brought into the frame of an anchor.
    docs/design.md's ``anchor_H_query`` is its inverse; we never need to invert during training.

The pose is :func:`regress_homography`: ``iterations`` regressions, each on the query warped by the
composition so far, then the degeneracy guard (:func:`matl.geometry.guard_homographies`). Every path
calls it with its own regressor and warp:

* ``SpatialTransformer.forward`` (training): the regressor module and kornia's warp
  (:func:`matl.geometry.sample_by_normalised_kornia`, whose rounding the training numbers are).
* ``SpatialTransformer.infer`` (inference, used by :class:`matl.models.recognizer.TensorRecognizer`):
  ``HomographyRegressor.infer`` (channels-last tensors, oneDNN convolutions, vectorised max pools)
  and :func:`matl.geometry.sample_by_normalised` on a cached grid, for a batch of one query at a few
  milliseconds; the same outputs as ``forward`` up to float rounding. See docs/speed.md.
* :class:`matl.models.recognizer.QueryGraph` (traced, exported, and with int8 layers in
  :mod:`matl.inference.quantize`): its own regressor callable and a grid held as a buffer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import torch
import torch.nn.functional as F
from torch import nn

from matl.geometry import guard_homographies, normalised_to_pixel, sample_by_normalised, sample_by_normalised_kornia
from matl.models.feature import conv_infer, input_normalization

#: ``(B, 3, S, S) -> (B, 3, 3)`` normalised sampling homographies
Regressor = Callable[[torch.Tensor], torch.Tensor]
#: ``(images (B, 3, S, S), src_H_dst_norm (B, 3, 3)) -> (B, 3, S, S)``
Warp = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def regress_homography(regressor: Regressor, images: torch.Tensor, iterations: int, max_condition: float,
                       warp: Warp = sample_by_normalised, eye: torch.Tensor | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """s()'s pose: regress, re-regress on the warped query and compose, then guard.

    ``H = regressor(images)``, then ``iterations - 1`` times ``H = H @ regressor(warp(images, H))``
    (each step refines the warp so far), then the unusable matrices are replaced by the identity.
    No Python branch on the values: the same code runs eagerly, under autograd and traced.

    Args:
        regressor: ``(B, 3, S, S) -> (B, 3, 3)`` normalised sampling homographies.
        images: ``(B, 3, S, S)`` queries.
        iterations: regressions composed (>= 1).
        max_condition: the degeneracy limit (:func:`matl.geometry.degenerate_homographies`).
        warp: ``warp(images, H)``, the sampler of the intermediate steps.
        eye: the identity for the guard (a traced graph passes its own constant); None makes one.
    Returns:
        ``(query_H_anchor (B, 3, 3) normalised, degenerate (B,) bool)``.
    """
    H = regressor(images)
    for _ in range(iterations - 1):
        H = H @ regressor(warp(images, H))
    return guard_homographies(H, max_condition, eye)


@dataclass
class STNOutput:
    warped: torch.Tensor           # (B, 3, H, W) query in the anchor frame
    query_H_anchor: torch.Tensor   # (B, 3, 3) pixel homography
    degenerate: torch.Tensor       # (B,) bool, predictions replaced by identity


class HomographyRegressor(nn.Module):
    """2 conv, 2 max pool, 2 FC (paper Sec. 5.2) -> 8 homography entries, identity-initialised.

    ``batch_norm`` (beyond the paper, which says nothing of normalisation) puts BatchNorm after
    each convolution; it lets plain SGD at the paper's learning rate train the regressor faster.
    ``input_norm`` (beyond the paper): ``channel`` standardises each image per channel first
    (:class:`matl.models.feature.ChannelStandardize`), so the pose does not move with exposure.

    ``(B, 3, H, W) -> (B, 3, 3)`` normalised sampling homography.
    """

    def __init__(self, image_size: int = 100, channels: tuple[int, int] = (16, 32),
                 kernel_sizes: tuple[int, int] = (5, 5), strides: tuple[int, int] = (2, 1),
                 pool: int = 2, hidden: int = 128, in_channels: int = 3, batch_norm: bool = False,
                 input_norm: str = "none") -> None:
        super().__init__()
        self.input_norm = input_normalization(input_norm)
        c1, c2 = channels
        k1, k2 = kernel_sizes
        s1, s2 = strides

        def norm(c: int) -> nn.Module:
            return nn.BatchNorm2d(c) if batch_norm else nn.Identity()

        self.features = nn.Sequential(
            nn.Conv2d(in_channels, c1, k1, stride=s1, padding=k1 // 2), norm(c1), nn.ReLU(), nn.MaxPool2d(pool),
            nn.Conv2d(c1, c2, k2, stride=s2, padding=k2 // 2), norm(c2), nn.ReLU(), nn.MaxPool2d(pool),
        )
        with torch.no_grad():
            flat = self.features(torch.zeros(1, in_channels, image_size, image_size)).numel()
        self.fc1 = nn.Linear(flat, hidden)
        self.fc2 = nn.Linear(hidden, 8)
        # Identity at start: the first steps then compare the untouched query with the anchors.
        nn.init.zeros_(self.fc2.weight)
        nn.init.zeros_(self.fc2.bias)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = self.features(self.input_norm(images)).flatten(1)
        delta = self.fc2(F.relu(self.fc1(x)))
        eye = torch.eye(3, dtype=delta.dtype, device=delta.device).flatten()[:8]
        entries = torch.cat([eye + delta, torch.ones_like(delta[:, :1])], dim=1)
        return entries.view(-1, 3, 3)

    @torch.no_grad()
    def infer(self, images: torch.Tensor) -> torch.Tensor:
        """``forward`` for inference (no gradient), the same matrices up to float rounding.

        On the CPU the feature maps are channels-last (the flatten below still reads them in NCHW
        order), convolutions go straight to oneDNN (:func:`matl.models.feature.conv_infer`), ReLUs are
        in place, and the identity is added in one op.
        """
        if images.device.type != "cpu" or images.dtype != torch.float32 or not torch.backends.mkldnn.is_available():
            return self.forward(images)
        x = self.input_norm(images).contiguous(memory_format=torch.channels_last)
        for layer in self.features:
            if isinstance(layer, nn.Conv2d):
                x = conv_infer(layer, x)
            elif isinstance(layer, nn.ReLU):
                x = x.relu_()
            else:
                x = layer(x)
        delta = self.fc2(self.fc1(x.flatten(1)).relu_())
        # [1 + d0, d1, d2, d3, 1 + d4, d5, d6, d7, 1]: the same sums as forward's eye + delta
        return F.pad(delta, (0, 1)).add_(_identity_entries(delta.device, delta.dtype)).view(-1, 3, 3)


@lru_cache(maxsize=8)
def _identity_entries(device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    with torch.inference_mode(False), torch.no_grad():
        return torch.eye(3, device=device, dtype=dtype).flatten()


class SpatialTransformer(nn.Module):
    """``s()``: regress ``query_H_anchor`` and warp the query into the anchor frame.

    Args:
        regressor: the homography regressor.
        image_size: side of the square model images, pixels.
        iterations: >1 refines by re-regressing on the warped image and composing (beyond the
            paper, which uses 1).
        max_condition: predictions whose normalised matrix has a larger condition number, or
            any non-finite entry, are replaced by identity and counted (the warp stays defined).
    """

    def __init__(self, regressor: HomographyRegressor, image_size: int = 100, iterations: int = 1,
                 max_condition: float = 1e4) -> None:
        super().__init__()
        if iterations < 1:
            raise ValueError(f"model.stn.iterations must be >= 1, got {iterations}")
        self.regressor = regressor
        self.image_size = image_size
        self.iterations = iterations
        self.max_condition = max_condition

    def regress(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised ``query_H_anchor`` ``(B, 3, 3)`` and a ``(B,)`` degeneracy flag (the training path)."""
        return regress_homography(self.regressor, images, self.iterations, self.max_condition,
                                  sample_by_normalised_kornia)

    def forward(self, images: torch.Tensor) -> STNOutput:
        H_norm, bad = self.regress(images)
        warped = sample_by_normalised_kornia(images, H_norm)
        return STNOutput(warped, normalised_to_pixel(H_norm, (self.image_size, self.image_size)), bad)

    @torch.no_grad()
    def infer(self, images: torch.Tensor) -> STNOutput:
        """``forward`` for inference (no gradient), the same outputs up to float rounding, at a
        fraction of the cost for small batches (see the module docstring)."""
        regressor = self.regressor
        predict = regressor.infer if isinstance(regressor, HomographyRegressor) else regressor
        H, bad = regress_homography(predict, images, self.iterations, self.max_condition, sample_by_normalised)
        warped = sample_by_normalised(images, H)
        return STNOutput(warped, normalised_to_pixel(H, (self.image_size, self.image_size)), bad)
