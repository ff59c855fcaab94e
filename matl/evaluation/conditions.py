"""The query conditions of the unseen-products benchmark: what a camera does to a product crop.

Every condition starts from the same held-out products and, where it can, the same query planes and
poses (:func:`sample_poses`, drawn once from ``query_seed``); a condition's own randomness comes from
``(query_seed, condition, query index)``, so a query looks the same whatever the number of queries.
Images are ``(H, W, 3)`` float64 RGB in [0, 1] (background exactly 0 in the canonical images) and
homographies are ``query_H_canon`` in pixels (docs/design.md).

* ``clean``: the canonical image warped by the pose (the paper's test queries).
* ``photometric``: the clean warp through a camera model: defocus blur, exposure gain, white-balance
  tint, black-level bias, sensor noise, a tone curve (gamma), 8 bits and JPEG compression.
* ``mask``: the product composited on a real textured background; RGBA, alpha an imperfect
  segmentation (the true warped mask grown or shrunk by a few px, with a ragged edge).
* ``clutter``: the product on a real background, a neighbouring product partly in the frame, cut by
  the crop's edge; RGB, no mask.
* ``occluded``: the product on a picking bin's floor (:class:`DarkFloor`, or a real background), partly
  hidden by another product lying on it, a gripper, a suction cup or the bin's wall
  (:class:`matl.data.occluders.Occluders`); mostly RGB, a share RGBA with alpha the visible part.
* ``view``: the products rendered from 3D camera poses; ``sizes``: the clean poses, with the gallery and
  the query files at other sizes than the model's.

This module holds the conditions' models; :mod:`matl.evaluation.condition_writers` writes every
condition's files and their ground truth.
"""

from __future__ import annotations

import io
import math
import zlib
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch
from PIL import Image

from matl.data.canonical import CanonicalSet
from matl.data.datamodule import footprints_from_masks
from matl.geometry import HomographySampler, warp_image

CONDITIONS = ("clean", "photometric", "mask", "clutter", "occluded", "view", "sizes")


def condition_rng(seed: int, condition: str, index: int) -> np.random.Generator:
    """The generator of one query's condition-specific randomness."""
    return np.random.default_rng([int(seed), zlib.crc32(condition.encode()), int(index)])


def _uniform(rng: np.random.Generator, bounds: Any) -> float:
    low, high = (float(v) for v in bounds)
    return float(rng.uniform(low, high)) if high > low else low


def sample_poses(cs: CanonicalSet, sampler: HomographySampler, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The queries' planes ``(n,)`` int64 (uniform) and poses ``query_H_canon`` ``(n, 3, 3)`` float64.

    The object stays in the frame (its mask's bounding box), as for the training queries.
    """
    size = (cs.image_size, cs.image_size)
    g = torch.Generator().manual_seed(int(seed))
    plane = torch.randint(cs.num_planes, (n,), generator=g)
    footprints = footprints_from_masks(torch.from_numpy(cs.masks))
    return plane, sampler.sample(n, size, g, footprints[plane])


def warp_planes(cs: CanonicalSet, plane: torch.Tensor, query_H_canon: torch.Tensor,
                size: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Canonical images and masks of ``plane`` warped by ``query_H_canon``.

    Returns:
        ``(n, S, S, 3)`` float64 RGB in [0, 1] and ``(n, S, S)`` float64 masks in [0, 1] (bilinear,
        so a product's edge is partly covered), ``S`` = ``size`` or the set's image size.
    """
    out = (size, size) if size is not None else None
    canon = torch.from_numpy(cs.images[plane.numpy()]).permute(0, 3, 1, 2).double().div(255.0)
    masks = torch.from_numpy(cs.masks[plane.numpy()]).double()[:, None]
    images = warp_image(canon, query_H_canon.double(), out).clamp(0.0, 1.0)
    warped_masks = warp_image(masks, query_H_canon.double(), out).clamp(0.0, 1.0)
    return images.permute(0, 2, 3, 1).numpy(), warped_masks[:, 0].numpy()


def to_uint8(image: np.ndarray) -> np.ndarray:
    """``(H, W, C)`` float in [0, 1] -> uint8."""
    return (np.clip(image, 0.0, 1.0) * 255.0).round().astype(np.uint8)


# ------------------------------------------------------------------------------------ photometric
@dataclass
class Photometric:
    """Random camera effects, uniform in ``[low, high]`` per query (``photometric.*`` of conf/unseen.yaml).

    Args:
        gain: exposure gain (1: unchanged).
        bias: black-level offset added to every channel.
        gamma: tone-curve exponent on [0, 1] values (``> 1`` darkens mid-tones).
        tint: per-channel white-balance gain (each channel its own draw).
        blur_sigma: Gaussian defocus blur, px at the file's size (0: none).
        noise_sigma: standard deviation of additive Gaussian sensor noise.
        jpeg_quality: the JPEG quality the file is saved with (integer, PIL's 1-95 scale).
    """

    gain: tuple[float, float] = (0.7, 1.4)
    bias: tuple[float, float] = (-0.04, 0.04)
    gamma: tuple[float, float] = (0.8, 1.25)
    tint: tuple[float, float] = (0.9, 1.1)
    blur_sigma: tuple[float, float] = (0.0, 1.0)
    noise_sigma: tuple[float, float] = (0.0, 0.03)
    jpeg_quality: tuple[int, int] = (40, 95)

    def apply(self, image: np.ndarray, rng: np.random.Generator) -> tuple[bytes, dict[str, float]]:
        """``(H, W, 3)`` float RGB in [0, 1] -> the JPEG file's bytes and the drawn parameters.

        Order of a camera: optics (blur), exposure and white balance, black level, sensor noise,
        tone curve, 8-bit quantisation, compression.
        """
        p = {"gain": _uniform(rng, self.gain), "bias": _uniform(rng, self.bias), "gamma": _uniform(rng, self.gamma),
             "blur_sigma": _uniform(rng, self.blur_sigma), "noise_sigma": _uniform(rng, self.noise_sigma)}
        tint = np.array([_uniform(rng, self.tint) for _ in range(3)])
        quality = round(_uniform(rng, self.jpeg_quality))
        x = image.astype(np.float64)
        if p["blur_sigma"] > 0.05:
            x = cv2.GaussianBlur(x, (0, 0), p["blur_sigma"], borderType=cv2.BORDER_REPLICATE)
        x = x * p["gain"] * tint + p["bias"]
        x = x + rng.standard_normal(x.shape) * p["noise_sigma"]
        x = np.clip(x, 0.0, 1.0) ** p["gamma"]
        buffer = io.BytesIO()
        Image.fromarray(to_uint8(x)).save(buffer, format="JPEG", quality=quality)
        return buffer.getvalue(), {**p, "tint": tint.tolist(), "jpeg_quality": quality}


# ------------------------------------------------------------------------------------ backgrounds
class Backgrounds:
    """Random crops of real photos (``(H, W, 3)`` float RGB in [0, 1]), the backgrounds of ``mask`` and ``clutter``.

    Args:
        photos: the photos (the held-out background pool, :data:`matl.data.catalog.drawing.HELDOUT_BACKGROUND_FILES`).
        crop: side of the square crop as a fraction of the photo's shorter side, ``[low, high]``.
    """

    def __init__(self, photos: list[np.ndarray], crop: tuple[float, float] = (0.25, 0.8)) -> None:
        if not photos:
            raise ValueError("no background photos")
        self.photos, self.crop = photos, crop

    def sample(self, size: int, rng: np.random.Generator) -> np.ndarray:
        """One ``(size, size, 3)`` crop, resized with area averaging."""
        photo = self.photos[int(rng.integers(len(self.photos)))]
        h, w = photo.shape[:2]
        side = max(8, round(_uniform(rng, self.crop) * min(h, w)))
        y0, x0 = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
        patch = np.ascontiguousarray(photo[y0:y0 + side, x0:x0 + side])
        return cv2.resize(patch, (size, size), interpolation=cv2.INTER_AREA)


def heldout_backgrounds(crop: tuple[float, float] = (0.25, 0.8)) -> Backgrounds:
    """:class:`Backgrounds` over the held-out background photos (scikit-image's bundled images)."""
    from matl.data.catalog.drawing import HELDOUT_BACKGROUND_FILES, heldout_image

    return Backgrounds([np.asarray(heldout_image(k), dtype=np.float64) / 255.0
                        for k in sorted(HELDOUT_BACKGROUND_FILES)], crop)


@dataclass
class DarkFloor:
    """A dark bin floor (``occluded.dark_floor.*`` of conf/unseen.yaml): near-black, lit from above, with noise.

    Args:
        level: its brightness at the centre (of 1), uniform in ``[low, high]``.
        noise: standard deviation of per-pixel sensor noise.
        vignetting: the corners are darker by this share (a radial falloff, quadratic in the distance).
    """

    level: tuple[float, float] = (0.02, 0.08)
    noise: tuple[float, float] = (0.005, 0.02)
    vignetting: tuple[float, float] = (0.1, 0.4)

    def sample(self, size: int, rng: np.random.Generator) -> np.ndarray:
        """One ``(size, size, 3)`` float64 floor in [0, 1]."""
        level, noise, vignetting = (_uniform(rng, r) for r in (self.level, self.noise, self.vignetting))
        tint = 1.0 + rng.uniform(-0.05, 0.05, 3)
        centre = (size - 1) / 2.0
        ys, xs = np.mgrid[0:size, 0:size]
        radius2 = ((xs - centre) ** 2 + (ys - centre) ** 2) / (2.0 * max(centre, 1.0) ** 2)  # 1 at the corners
        floor = level * (1.0 - vignetting * radius2)[..., None] * tint
        return np.clip(floor + rng.standard_normal((size, size, 3)) * noise, 0.0, 1.0)


def composite(background: np.ndarray, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` (premultiplied: 0 outside its object) over ``background`` with coverage ``mask`` ``(H, W)``."""
    return image + (1.0 - mask[..., None]) * background


# ------------------------------------------------------------------------------------------- mask
@dataclass
class ImperfectMask:
    """An imperfect segmentation of a true mask (``mask.*`` of conf/unseen.yaml).

    Args:
        offset_px: the boundary moves out (dilation, > 0) or in (erosion, < 0) by this many px,
            uniform in ``[low, high]``.
        ragged_px: amplitude (standard deviation, px) of a smooth random displacement of the boundary.
        ragged_scale_px: correlation length (Gaussian sigma, px) of that displacement.
    """

    offset_px: tuple[float, float] = (-3.0, 3.0)
    ragged_px: tuple[float, float] = (0.5, 2.0)
    ragged_scale_px: float = 2.5

    def apply(self, mask: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict[str, float]]:
        """``(H, W)`` bool true mask -> ``(H, W)`` bool segmentation and its parameters."""
        inside = mask.astype(np.uint8)
        # signed distance to the boundary, > 0 outside the object
        outside_d = cv2.distanceTransform(1 - inside, cv2.DIST_L2, 5)
        inside_d = cv2.distanceTransform(inside, cv2.DIST_L2, 5)
        signed = np.where(inside > 0, -inside_d + 0.5, outside_d - 0.5)
        offset, ragged = _uniform(rng, self.offset_px), _uniform(rng, self.ragged_px)
        field = cv2.GaussianBlur(rng.standard_normal(mask.shape), (0, 0), self.ragged_scale_px)
        field = field / max(float(field.std()), 1e-9) * ragged
        return signed < offset + field, {"offset_px": offset, "ragged_px": ragged}


# ---------------------------------------------------------------------------------------- clutter
@dataclass
class Clutter:
    """A neighbouring product cut by the crop's edge (``clutter.*`` of conf/unseen.yaml).

    The neighbour is another product's plane under its own random pose (the queries' sampler), moved
    by ``distance`` x the image size in a uniformly random direction, so that part of it stays in the
    frame and the crop's edge cuts it; it lies behind the query's product.
    """

    distance: tuple[float, float] = (0.55, 0.75)

    def neighbour_H(self, H: torch.Tensor, size: int, rng: np.random.Generator) -> torch.Tensor:
        """``(3, 3)`` the neighbour's ``query_H_canon``: its own pose ``H`` moved off-centre."""
        angle, d = rng.uniform(0.0, 2.0 * math.pi), _uniform(rng, self.distance) * size
        move = torch.tensor([[1.0, 0.0, d * math.cos(angle)], [0.0, 1.0, d * math.sin(angle)], [0.0, 0.0, 1.0]],
                            dtype=torch.float64)
        return move @ H.double()


def other_plane(cs: CanonicalSet, plane: int, rng: np.random.Generator) -> int:
    """A random plane of another object than ``plane``'s (the same object's when there is no other)."""
    own = int(cs.plane_object[plane])
    candidates = np.flatnonzero(cs.plane_object != own)
    if len(candidates) == 0:
        candidates = np.arange(cs.num_planes)
    return int(candidates[int(rng.integers(len(candidates)))])


def scale_pixels(factor: float) -> torch.Tensor:
    """``(3, 3)`` float64: pixel coordinates of an image resized by ``factor`` (pixel centres kept:
    ``x' = (x + 0.5) * factor - 0.5``)."""
    return torch.tensor([[factor, 0.0, 0.5 * factor - 0.5], [0.0, factor, 0.5 * factor - 0.5], [0.0, 0.0, 1.0]],
                        dtype=torch.float64)
