"""The spatial transformer s() (paper Sec. 3.1, 5.2): a homography regressor and a warp.

Convention:
    The regressor predicts the *sampling* homography ``query_H_anchor`` (anchor-frame pixel ->
    query pixel), in normalised coordinates, as identity + 8 learned entries. The STN output is
    ``s(query)(x) = query(query_H_anchor @ x)``: the query brought into the frame of an anchor.
    DESIGN's ``anchor_H_query`` is its inverse; we never need to invert during training.

Inference (``SpatialTransformer.infer``, used by :class:`matl.inference.recognizer.Recognizer`) computes
the same function as ``forward`` up to float rounding, for a batch of one query at a few
milliseconds: the warp is ``grid_sample`` on a cached normalised grid (:func:`warp_by_normalised`)
instead of kornia's general ``homography_warp`` (whose per-call set-up cost more than the sampling),
the pixel conversion uses cached normalisation matrices, and the convolutions run on channels-last
tensors (oneDNN convolutions, vectorised max pools). Training keeps ``forward`` (kornia) unchanged.
See docs/speed.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import torch
import torch.nn.functional as F
from torch import nn

from matl.geometry import normalised_to_pixel, sample_by_normalised
from matl.models.feature import conv_infer

#: points with ``|z|`` at most this are left undivided (kornia's ``convert_points_from_homogeneous``)
HOMOGENEOUS_EPS = 1e-8


@lru_cache(maxsize=32)
def _normalised_grid(height: int, width: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """``(3, H*W)`` homogeneous normalised pixel centres ``(u, v, 1)``, row-major (kornia's
    ``create_meshgrid`` with ``align_corners=True``). Cached: built once per size, device and dtype."""
    with torch.inference_mode(False), torch.no_grad():  # a plain tensor, whatever mode the first caller is in
        v, u = torch.meshgrid(torch.linspace(-1.0, 1.0, height, device=device, dtype=dtype),
                              torch.linspace(-1.0, 1.0, width, device=device, dtype=dtype), indexing="ij")
        return torch.stack([u.reshape(-1), v.reshape(-1), torch.ones_like(u).reshape(-1)])


def normalised_grid(height: int, width: int, device: torch.device | None = None,
                    dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``(3, H*W)`` homogeneous normalised pixel centres ``(u, v, 1)`` of an image, row-major (kornia's
    ``create_meshgrid``, ``align_corners=True``); cached per size, device and dtype (do not modify it)."""
    return _normalised_grid(int(height), int(width), torch.device(device or "cpu"), dtype)


def warp_by_normalised(images: torch.Tensor, src_H_dst_norm: torch.Tensor, grid: torch.Tensor | None = None
                       ) -> torch.Tensor:
    """``out(x) = images(src_H_dst_norm @ x)`` over the normalised grid of ``images``; zeros outside.

    The same warp as :func:`matl.geometry.sample_by_normalised` (kornia's ``homography_warp`` with
    normalised coordinates and ``align_corners=True``) up to float rounding, without its per-call
    overhead: one ``(B, 3, 3) @ (3, H*W)`` product with a cached grid, the perspective division
    (points with ``|z| <= 1e-8`` left undivided, as kornia does), one ``grid_sample``. Differentiable.

    Args:
        images: ``(B, C, H, W)``.
        src_H_dst_norm: ``(B, 3, 3)`` sampling homographies in normalised coordinates.
        grid: :func:`normalised_grid` of the images' size (a module that is traced passes its own copy,
            so that the grid is a constant of the graph); None looks it up.
    """
    batch, _, height, width = images.shape
    if grid is None:
        grid = normalised_grid(height, width, images.device, images.dtype)
    points = src_H_dst_norm.to(images.dtype) @ grid
    z = points[:, 2:]
    z = torch.where(z.abs() > HOMOGENEOUS_EPS, z, 1.0)
    grid_xy = (points[:, :2] / z).transpose(1, 2).reshape(batch, height, width, 2)
    return F.grid_sample(images, grid_xy, mode="bilinear", padding_mode="zeros", align_corners=True)


@lru_cache(maxsize=32)
def pixel_from_normalised(size: int, device: torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """``(pixel_H_norm, norm_H_pixel)`` of a ``size`` x ``size`` image (``align_corners=True``), cached."""
    with torch.inference_mode(False), torch.no_grad():
        norm = torch.tensor([[2.0 / (size - 1), 0.0, -1.0], [0.0, 2.0 / (size - 1), -1.0], [0.0, 0.0, 1.0]],
                            dtype=torch.float64) if size > 1 else torch.eye(3, dtype=torch.float64)
        return torch.linalg.inv(norm).to(device, dtype), norm.to(device, dtype)


def normalised_to_pixel_square(H_norm: torch.Tensor, size: int) -> torch.Tensor:
    """:func:`matl.geometry.normalised_to_pixel` for ``size`` x ``size`` images, with cached matrices:
    ``pixel_H_norm @ H_norm @ norm_H_pixel`` scaled so that ``H[2, 2] = 1``."""
    pixel_H_norm, norm_H_pixel = pixel_from_normalised(int(size), H_norm.device, H_norm.dtype)
    out = pixel_H_norm @ (H_norm @ norm_H_pixel)
    h22 = out[:, 2:3, 2:3]
    return out / torch.where(h22.abs() > 1e-12, h22, torch.ones_like(h22))


def degenerate_homographies(H: torch.Tensor, max_condition: float, eye: torch.Tensor | None = None) -> torch.Tensor:
    """``(B,)`` True where a ``(B, 3, 3)`` homography is unusable: a non-finite entry, or a condition
    number (largest / smallest singular value) of at least ``max_condition`` (also the zero matrix).

    The one rule of the STN's guard (training, inference, the traced query graph) and of the pose
    refiner. ``eye``: the identity substituted before the SVD of non-finite matrices (a traced graph
    passes its own constant); None makes one.
    """
    finite = torch.isfinite(H).all(dim=2).all(dim=1)
    if eye is None:
        eye = torch.eye(3, dtype=H.dtype, device=H.device)
    sv = torch.linalg.svdvals(torch.where(finite[:, None, None], H, eye))
    return ~finite | (sv[:, -1] * max_condition <= sv[:, 0])


@dataclass
class STNOutput:
    warped: torch.Tensor           # (B, 3, H, W) query in the anchor frame
    query_H_anchor: torch.Tensor   # (B, 3, 3) pixel homography
    degenerate: torch.Tensor       # (B,) bool, predictions replaced by identity


class HomographyRegressor(nn.Module):
    """2 conv, 2 max pool, 2 FC (paper Sec. 5.2) -> 8 homography entries, identity-initialised.

    ``batch_norm`` (beyond the paper, which says nothing of normalisation) puts BatchNorm after
    each convolution; it lets plain SGD at the paper's learning rate train the regressor faster.

    ``(B, 3, H, W) -> (B, 3, 3)`` normalised sampling homography.
    """

    def __init__(self, image_size: int = 100, channels: tuple[int, int] = (16, 32),
                 kernel_sizes: tuple[int, int] = (5, 5), strides: tuple[int, int] = (2, 1),
                 pool: int = 2, hidden: int = 128, in_channels: int = 3, batch_norm: bool = False) -> None:
        super().__init__()
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
        x = self.features(images).flatten(1)
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
        x = images.contiguous(memory_format=torch.channels_last)
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
        """Normalised ``query_H_anchor`` ``(B, 3, 3)`` and a ``(B,)`` degeneracy flag."""
        H = self.regressor(images)
        for _ in range(self.iterations - 1):
            H = H @ self.regressor(sample_by_normalised(images, H))
        return self._guard(H)

    def _guard(self, H: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            bad = degenerate_homographies(H, self.max_condition)
        if bad.any():
            eye = torch.eye(3, dtype=H.dtype, device=H.device).expand_as(H)
            H = torch.where(bad[:, None, None], eye, torch.nan_to_num(H))
        return H, bad

    def forward(self, images: torch.Tensor) -> STNOutput:
        H_norm, bad = self.regress(images)
        warped = sample_by_normalised(images, H_norm)
        size = (self.image_size, self.image_size)
        return STNOutput(warped, normalised_to_pixel(H_norm, size), bad)

    @torch.no_grad()
    def infer(self, images: torch.Tensor) -> STNOutput:
        """``forward`` for inference (no gradient), the same outputs up to float rounding, at a
        fraction of the cost for small batches (see the module docstring)."""
        regressor = self.regressor
        predict = regressor.infer if isinstance(regressor, HomographyRegressor) else regressor
        H = predict(images)
        for _ in range(self.iterations - 1):
            H = H @ predict(warp_by_normalised(images, H))
        H, bad = self._guard_infer(H)
        warped = warp_by_normalised(images, H)
        return STNOutput(warped, normalised_to_pixel_square(H, self.image_size), bad)

    def _guard_infer(self, H: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`_guard` with a shortcut on the CPU for the usual case (every matrix finite and well
        conditioned: H is returned as is, the same outcome with a third of the ops)."""
        if H.device.type == "cpu" and bool(torch.isfinite(H).all()):
            bad = degenerate_homographies(H, self.max_condition)
            if not bool(bad.any()):
                return H, bad
        return self._guard(H)
