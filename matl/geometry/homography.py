"""Homography helpers: frames, normalisation, composition, the degeneracy rule and pose errors.

Convention:
    * Pixel coordinates: x right, y down, ``(0, 0)`` is the *centre* of the top-left pixel (OpenCV).
    * Normalised coordinates map the pixel centres ``0`` and ``W - 1`` to ``-1`` and ``+1``
      (``align_corners=True``), the frame of :func:`torch.nn.functional.grid_sample`.
    * A homography ``dst_H_src`` maps homogeneous *pixel* coordinates of frame ``src`` to frame
      ``dst`` unless its name ends in ``_norm``; all are scaled so that ``H[..., 2, 2] == 1``.
    * Positive angles rotate the image content counter-clockwise *as seen on screen* (y down),
      the convention of OpenCV's ``getRotationMatrix2D`` and kornia.

These functions fix the conventions above so that callers never pass a matrix in the wrong
direction; the warps themselves are in :mod:`matl.geometry.warp`. The pixel <-> normalised changes
are kornia's arithmetic: :func:`pixel_to_normalised` calls it, :func:`normalised_to_pixel` (on every
query, and inside traced graphs) computes the same products with cached matrices, bit for bit.
"""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np
import torch
from kornia.geometry.conversions import normalize_homography
from kornia.geometry.linalg import transform_points

Size = tuple[int, int]  # (height, width)


def check_homographies(H: torch.Tensor, name: str = "H") -> torch.Tensor:
    """Raise a one-line error unless ``H`` has shape ``(..., 3, 3)`` (not checked while tracing, where sizes
    are tensors: the trace fixes them)."""
    if torch.jit.is_tracing():
        return H
    if not isinstance(H, torch.Tensor) or H.ndim < 2 or tuple(H.shape[-2:]) != (3, 3):
        shape = tuple(H.shape) if isinstance(H, torch.Tensor) else type(H).__name__
        raise ValueError(f"{name} must be a (..., 3, 3) tensor of homographies, got {shape}")
    return H


def check_images(images: torch.Tensor, name: str = "images", size: Size | None = None) -> torch.Tensor:
    """Raise a one-line error unless ``images`` is ``(B, 3, H, W)`` (and ``(H, W) == size`` if given)."""
    if not isinstance(images, torch.Tensor) or images.ndim != 4 or images.shape[1] != 3:
        shape = tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise ValueError(f"{name} must be a (B, 3, H, W) RGB float tensor, got {shape}")
    if size is not None and tuple(images.shape[-2:]) != tuple(size):
        raise ValueError(
            f"{name} are {tuple(images.shape[-2:])} pixels but the model expects {tuple(size)}; "
            "resize them (matl.predict does this for image files)"
        )
    return images


def scale_to_unit(H: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Scale homographies ``(..., 3, 3)`` so that ``H[..., 2, 2] == 1``.

    A homography whose ``H[2, 2]`` is (almost) zero maps the image centre to infinity; it is left
    unscaled rather than divided by ~0 so the caller's degeneracy guard can see it.
    """
    check_homographies(H)
    h22 = H[..., 2:3, 2:3]
    safe = torch.where(h22.abs() > eps, h22, torch.ones_like(h22))
    return H / safe


def pixel_to_normalised(dst_H_src: torch.Tensor, size: Size) -> torch.Tensor:
    """Express pixel homographies ``(B, 3, 3)`` between two images of ``size`` in normalised coordinates."""
    check_homographies(dst_H_src, "dst_H_src")
    shape = dst_H_src.shape
    out = normalize_homography(dst_H_src.reshape(-1, 3, 3), size, size, align_corners=True)
    return scale_to_unit(out.reshape(shape))


@lru_cache(maxsize=32)
def _normalisation(height: int, width: int, device: torch.device, dtype: torch.dtype
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    with torch.inference_mode(False), torch.no_grad():  # plain tensors, whatever mode the first caller is in
        # kornia's normal_transform_pixel (a one-pixel axis maps to 0) and the inverse its
        # denormalize_homography takes (LU in the matrix's dtype), so that the products below round as kornia's
        sx, tx = (1.0, 0.0) if width == 1 else (2.0 / (width - 1.0), -1.0)
        sy, ty = (1.0, 0.0) if height == 1 else (2.0 / (height - 1.0), -1.0)
        norm_H_pixel = torch.tensor([[[sx, 0.0, tx], [0.0, sy, ty], [0.0, 0.0, 1.0]]], dtype=dtype, device=device)
        return torch.linalg.inv_ex(norm_H_pixel).inverse, norm_H_pixel


def normalisation_matrices(size: Size, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(pixel_H_norm, norm_H_pixel)``, each ``(1, 3, 3)``, of images of ``size`` (``align_corners=True``).

    Cached per size, device and dtype: do not modify them (a traced module keeps its own copies).
    """
    height, width = size
    return _normalisation(int(height), int(width), torch.device(device or "cpu"), dtype)


def normalised_to_pixel(dst_H_src_norm: torch.Tensor, size: Size,
                        matrices: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Inverse of :func:`pixel_to_normalised`: ``pixel_H_norm @ H @ norm_H_pixel``, scaled so that ``H[2, 2] = 1``.

    The products of kornia's ``denormalize_homography``, in the same order (bit for bit), with cached
    matrices and no Python branch on the values: the one conversion of the training path, the query
    path and the traced query graph.

    Args:
        dst_H_src_norm: ``(..., 3, 3)`` normalised homographies between two images of ``size``.
        size: ``(height, width)``.
        matrices: ``(pixel_H_norm, norm_H_pixel)`` of :func:`normalisation_matrices` (a traced module
            passes its own copies, constants of the graph); None looks them up.
    Returns:
        ``(..., 3, 3)`` pixel homographies.
    """
    check_homographies(dst_H_src_norm, "dst_H_src_norm")
    pixel_H_norm, norm_H_pixel = (normalisation_matrices(size, dst_H_src_norm.device, dst_H_src_norm.dtype)
                                  if matrices is None else matrices)
    shape = dst_H_src_norm.shape
    out = pixel_H_norm @ (dst_H_src_norm.reshape(-1, 3, 3) @ norm_H_pixel)
    return scale_to_unit(out.reshape(shape))


def rescale_homography(dst_H_src: torch.Tensor, src_size: Size, dst_size: Size, src_new: Size,
                       dst_new: Size) -> torch.Tensor:
    """Re-express ``dst_H_src`` when both images are resized (pixel centres stay aligned).

    Used by ``matl.predict`` to report a pose computed at model resolution in the original pixel
    coordinates of the gallery and query files. Sizes are ``(height, width)``.
    """
    def resize_matrix(old: Size, new: Size) -> torch.Tensor:
        # maps old pixel coords to new ones with corner pixel centres fixed (align_corners=True)
        sx = (new[1] - 1) / max(old[1] - 1, 1)
        sy = (new[0] - 1) / max(old[0] - 1, 1)
        return torch.tensor([[sx, 0.0, 0.0], [0.0, sy, 0.0], [0.0, 0.0, 1.0]], dtype=dst_H_src.dtype,
                            device=dst_H_src.device)

    dstnew_H_dst = resize_matrix(dst_size, dst_new)
    src_H_srcnew = torch.linalg.inv(resize_matrix(src_size, src_new))
    return scale_to_unit(dstnew_H_dst @ dst_H_src @ src_H_srcnew)


def centre_rotation(angle_deg: torch.Tensor, size: Size) -> torch.Tensor:
    """Rotation about the image centre, ``(...,) -> (..., 3, 3)``, counter-clockwise on screen."""
    height, width = size
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    theta = torch.deg2rad(angle_deg)
    c, s = torch.cos(theta), torch.sin(theta)
    zeros, ones = torch.zeros_like(c), torch.ones_like(c)
    # y points down, so a counter-clockwise turn on screen is [[c, s], [-s, c]] in (x, y).
    tx = cx - c * cx - s * cy
    ty = cy + s * cx - c * cy
    rows = [torch.stack([c, s, tx], -1), torch.stack([-s, c, ty], -1), torch.stack([zeros, zeros, ones], -1)]
    return torch.stack(rows, -2)


def anchor_H_canon(num_anchors: int, size: Size, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Fixed anchors (docs/design.md): anchor ``k`` is the canonical image rotated by ``k * 360 / N`` degrees.

    Returns:
        ``(N, 3, 3)`` pixel homographies ``anchor_k_H_canon``.
    """
    if num_anchors < 1:
        raise ValueError(f"N (number of anchors) must be >= 1, got {num_anchors}")
    angles = torch.arange(num_anchors, dtype=torch.float64) * (360.0 / num_anchors)
    return centre_rotation(angles, size).to(dtype)


def compose_query_H_canon(query_H_anchor: torch.Tensor, anchor_H_canon: torch.Tensor) -> torch.Tensor:
    """Pose of a query: ``query_H_canon = query_H_anchor @ anchor_k_H_canon``.

    This equals docs/design.md's ``inv(anchor_H_query) @ anchor_k_H_canon``; the STN predicts the sampling
    direction ``query_H_anchor`` directly, so no inverse is needed.
    """
    check_homographies(query_H_anchor, "query_H_anchor")
    check_homographies(anchor_H_canon, "anchor_H_canon")
    if (query_H_anchor.device.type == "cpu" and anchor_H_canon.device.type == "cpu" and query_H_anchor.ndim == 3
            and len(query_H_anchor) <= 8 and query_H_anchor.dtype == anchor_H_canon.dtype == torch.float64
            and not (query_H_anchor.requires_grad or anchor_H_canon.requires_grad) and not torch.jit.is_tracing()):
        # a query's pose at inference: the same products and division in NumPy, without torch's per-op cost
        pose = query_H_anchor.numpy() @ anchor_H_canon.numpy()
        h22 = pose[:, 2:3, 2:3]
        return torch.from_numpy(pose / np.where(np.abs(h22) > 1e-12, h22, 1.0))
    return scale_to_unit(query_H_anchor @ anchor_H_canon)


def degenerate_homographies(H: torch.Tensor, max_condition: float, eye: torch.Tensor | None = None) -> torch.Tensor:
    """``(B,)`` True where a ``(B, 3, 3)`` homography is unusable: a non-finite entry, or a condition
    number (largest / smallest singular value) of at least ``max_condition`` (the zero matrix too).

    The one rule of the STN's guard (:func:`guard_homographies`: training, inference, the traced
    query graph) and of the pose refiner's acceptance. ``eye``: the identity substituted before the
    SVD of non-finite matrices (a traced graph passes its own constant); None makes one.
    """
    check_homographies(H)
    finite = torch.isfinite(H).all(dim=2).all(dim=1)
    if eye is None:
        eye = torch.eye(3, dtype=H.dtype, device=H.device)
    sv = torch.linalg.svdvals(torch.where(finite[:, None, None], H, eye))
    return ~finite | (sv[:, -1] * max_condition <= sv[:, 0])


def degenerate_matrix(H: np.ndarray, max_condition: float) -> bool:
    """:func:`degenerate_homographies`'s rule for one ``(3, 3)`` float64 NumPy matrix: non-finite, or
    ``sv_min * max_condition <= sv_max``. In OpenCV, a few microseconds (a single query's pose is checked
    without a torch op)."""
    if not math.isfinite(H.sum()):  # a NaN or infinite entry makes the sum one
        return True
    sv = cv2.SVDecomp(H, flags=cv2.SVD_NO_UV)[0]  # (3, 1), descending
    return bool(sv[2, 0] * max_condition <= sv[0, 0])


def guard_homographies(H: torch.Tensor, max_condition: float, eye: torch.Tensor | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """Replace the unusable homographies of a batch by the identity, so that a warp by them stays defined.

    Args:
        H: ``(B, 3, 3)``.
        max_condition: the limit of :func:`degenerate_homographies`.
        eye: the ``(3, 3)`` identity to use (a traced graph passes its own constant); None makes one.
    Returns:
        ``(H (B, 3, 3), degenerate (B,) bool)``: ``H`` with the degenerate matrices replaced by the
        identity. The selection is a ``torch.where`` whatever the values (no Python branch, so the same
        code traces); the rule sees ``H`` detached, so the gradient flows to the kept matrices only.
    """
    bad = degenerate_homographies(H.detach(), max_condition, eye)
    if eye is None:
        eye = torch.eye(3, dtype=H.dtype, device=H.device)
    return torch.where(bad[:, None, None], eye, torch.nan_to_num(H)), bad


def transfer_points(dst_H_src: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Map points ``(B, K, 2)`` of ``src`` into ``dst`` with ``dst_H_src`` ``(B, 3, 3)``."""
    return transform_points(dst_H_src, points)


def image_corners(size: Size, dtype: torch.dtype = torch.float32, device: torch.device | None = None) -> torch.Tensor:
    """The 4 corner pixel centres ``(4, 2)``: top-left, top-right, bottom-right, bottom-left."""
    height, width = size
    return torch.tensor([[0.0, 0.0], [width - 1.0, 0.0], [width - 1.0, height - 1.0], [0.0, height - 1.0]],
                        dtype=dtype, device=device)


def corner_error_px(est_query_H_canon: torch.Tensor, true_query_H_canon: torch.Tensor, size: Size) -> torch.Tensor:
    """Mean distance in pixels between the 4 image corners mapped by the estimated and true poses.

    Args:
        est_query_H_canon, true_query_H_canon: ``(B, 3, 3)`` pixel homographies.
    Returns:
        ``(B,)``; ``inf`` where the estimate sends a corner to infinity.
    """
    corners = image_corners(size, torch.float64, est_query_H_canon.device).expand(len(est_query_H_canon), 4, 2)
    est = transfer_points(est_query_H_canon.double(), corners)
    true = transfer_points(true_query_H_canon.double(), corners)
    err = (est - true).norm(dim=-1).mean(dim=-1)
    return torch.nan_to_num(err, nan=math.inf)


def frobenius_pose_error(est_query_H_canon: torch.Tensor, true_query_H_canon: torch.Tensor,
                         size: Size) -> torch.Tensor:
    """The paper's pose error: ``||H_est - H_true||_F`` in normalised coordinates with ``H[2,2] = 1``.

    Returns:
        ``(B,)``.
    """
    est = pixel_to_normalised(est_query_H_canon.double(), size)
    true = pixel_to_normalised(true_query_H_canon.double(), size)
    return torch.linalg.matrix_norm(est - true, ord="fro")
