"""Warping images by homographies: the normalised grid and the grid sampler.

Conventions are those of :mod:`matl.geometry.homography` (pixel centres, normalised coordinates with
``align_corners=True``, ``dst_H_src`` names). Every warp here computes the same function,

    ``out(x) = images(src_H_dst_norm @ x)`` for the normalised pixel centres ``x`` of the output,

bilinear, zeros outside, where a point whose homogeneous ``|z|`` is at most ``HOMOGENEOUS_EPS``
is left undivided (kornia's rule). There are three ways in:

* :func:`sample_by_normalised`: the package's grid sampler. One ``(B, 3, 3) @ (3, h*w)`` product
  with a cached grid (:func:`normalised_grid`), the perspective division, one ``grid_sample``.
  Differentiable and traceable: a traced graph passes its own copy of the grid, which then is a
  constant of the graph. The STN's inference (``SpatialTransformer.infer``, the traced and int8
  query graphs) and the pose refiner use it.
* :func:`sample_by_normalised_kornia`: the same warp through kornia's ``homography_warp``, the
  STN's training forward. kornia builds its grid with another formula, rescales the matrix first
  and multiplies by ``1 / z``: the result differs from :func:`sample_by_normalised` by float
  rounding (a few 1e-6 on images in [0, 1], tested), and the training numbers reproduced in
  docs/results.md are those of kornia's rounding, so training keeps it.
* :func:`warp_image`: a *pixel* homography in the forward direction, ``dst_H_src`` (kornia's
  ``warp_perspective``, which inverts it): the data pipeline's warps (anchors, positives,
  negatives, test queries) and the symmetric appearance loss. Also part of the training path,
  so also kornia's arithmetic.

For one NumPy image at inference, :func:`sample_by_pixels` is the same sampling by a *pixel* matrix
``src_H_dst`` in OpenCV (``cv2.warpPerspective``, sample positions in 1/32 px steps): the onnxruntime query
path's warps and the fast refiner's.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.transform import homography_warp, warp_perspective

from matl.geometry.homography import Size, check_homographies

#: points with ``|z|`` at most this are left undivided (kornia's ``convert_points_from_homogeneous``)
HOMOGENEOUS_EPS = 1e-8


@lru_cache(maxsize=32)
def _normalised_grid(height: int, width: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    with torch.inference_mode(False), torch.no_grad():  # a plain tensor, whatever mode the first caller is in
        v, u = torch.meshgrid(torch.linspace(-1.0, 1.0, height, device=device, dtype=dtype),
                              torch.linspace(-1.0, 1.0, width, device=device, dtype=dtype), indexing="ij")
        return torch.stack([u.reshape(-1), v.reshape(-1), torch.ones_like(u).reshape(-1)])


def normalised_grid(height: int, width: int, device: torch.device | str | None = None,
                    dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``(3, H*W)`` homogeneous normalised pixel centres ``(u, v, 1)`` of an ``H`` x ``W`` image, row-major
    (``u = linspace(-1, 1, W)`` along a row). Cached per size, device and dtype: do not modify it."""
    return _normalised_grid(int(height), int(width), torch.device(device or "cpu"), dtype)


def sample_by_normalised(images: torch.Tensor, src_H_dst_norm: torch.Tensor,
                         grid: torch.Tensor | None = None) -> torch.Tensor:
    """``out(x) = images(src_H_dst_norm @ x)`` over the normalised grid of ``images``; zeros outside.

    A *sampling* homography (output -> input), as an STN predicts it: no matrix inverse, so the
    gradient stays well behaved for any predicted matrix. The matrix is used in the images' dtype.

    Args:
        images: ``(B, C, H, W)``.
        src_H_dst_norm: ``(B, 3, 3)`` sampling homographies in normalised coordinates.
        grid: ``(3, H*W)``, :func:`normalised_grid` of the images' size (a module that is traced passes
            its own copy, so that the grid is a constant of the graph); None looks it up.
    Returns:
        ``(B, C, H, W)``.
    """
    if not torch.jit.is_tracing():  # a trace sees sizes as tensors (and fixes them)
        _check_sampling(images, src_H_dst_norm, grid)
    batch, _, height, width = images.shape
    if grid is None:
        grid = normalised_grid(height, width, images.device, images.dtype)
    points = src_H_dst_norm.to(images.dtype) @ grid                       # (B, 3, H*W)
    z = points[:, 2:]
    z = torch.where(z.abs() > HOMOGENEOUS_EPS, z, 1.0)
    grid_xy = (points[:, :2] / z).transpose(1, 2).reshape(batch, height, width, 2)
    return F.grid_sample(images, grid_xy, mode="bilinear", padding_mode="zeros", align_corners=True)


def _check_sampling(images: torch.Tensor, src_H_dst_norm: torch.Tensor, grid: torch.Tensor | None) -> None:
    if not isinstance(images, torch.Tensor) or images.ndim != 4:
        shape = tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise ValueError(f"images must be a (B, C, H, W) tensor, got {shape}")
    check_homographies(src_H_dst_norm, "src_H_dst_norm")
    batch, _, height, width = images.shape
    if tuple(src_H_dst_norm.shape) != (batch, 3, 3):
        raise ValueError(f"src_H_dst_norm must be ({batch}, 3, 3), one per image, got {tuple(src_H_dst_norm.shape)}")
    if grid is not None and tuple(grid.shape) != (3, height * width):
        raise ValueError(f"grid must be (3, {height * width}) for {height} x {width} images, got {tuple(grid.shape)}")


def sample_by_normalised_kornia(images: torch.Tensor, src_H_dst_norm: torch.Tensor,
                                size: Size | None = None) -> torch.Tensor:
    """:func:`sample_by_normalised` through kornia's ``homography_warp``: the STN's training forward.

    The same function up to float rounding (see the module docstring for why training keeps it).

    Args:
        images: ``(B, C, H, W)``.
        src_H_dst_norm: ``(B, 3, 3)`` sampling homographies in normalised coordinates.
        size: ``(h, w)`` of the output; None: the images' size.
    Returns:
        ``(B, C, h, w)``.
    """
    check_homographies(src_H_dst_norm, "src_H_dst_norm")
    size = tuple(images.shape[-2:]) if size is None else size
    return homography_warp(images, src_H_dst_norm.to(images.dtype), size, align_corners=True,
                           normalized_coordinates=True, normalized_homography=True)


def warp_image(src: torch.Tensor, dst_H_src: torch.Tensor, size: Size | None = None) -> torch.Tensor:
    """Warp images ``(B, C, H, W)`` by pixel homographies ``dst_H_src`` ``(B, 3, 3)``; zeros outside.

    ``out(x) = src(inv(dst_H_src) @ x)`` in pixel coordinates (kornia's ``warp_perspective``).

    Args:
        size: ``(h, w)`` of the output; None: the input's size.
    Returns:
        ``(B, C, h, w)``.
    """
    check_homographies(dst_H_src, "dst_H_src")
    size = tuple(src.shape[-2:]) if size is None else size
    return warp_perspective(src, dst_H_src.to(src.dtype), size, align_corners=True)


def sample_by_pixels(image: np.ndarray, src_H_dst: np.ndarray, size: Size) -> np.ndarray:
    """``out(x) = image(src_H_dst @ x)`` for the pixel centres ``x`` of an output of ``size`` ``(h, w)``: bilinear,
    zeros outside, in OpenCV (``cv2.warpPerspective`` with ``WARP_INVERSE_MAP``). ``image`` is ``(H, W)`` or
    ``(H, W, C)`` NumPy, ``src_H_dst`` ``(3, 3)`` float64."""
    return cv2.warpPerspective(image, src_H_dst, (int(size[1]), int(size[0])),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT,
                               borderValue=0)
