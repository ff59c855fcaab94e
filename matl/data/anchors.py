"""Anchor acquisition (paper Sec. 4.1, 5.7): how the N anchors of each canonical plane are made (``anchors=``).

Every acquisition gives, for the ``P`` planes, ``anchor_H_canon`` ``(P, N, 3, 3)``: the pixel
homography from the canonical image to each anchor. It comes in one of two forms:

* a plain call ``acquisition(P, N, size, generator, footprints) -> anchor_H_canon``; the datamodule
  then warps the canonical images by it (:class:`FixedAnchors`, :class:`RandomAnchors`);
* ``build_anchors(dm, N, generator) -> (anchor_H_canon, images)`` for acquisitions that make their
  own anchor images (:class:`RenderedRandomAnchors` renders them, :class:`PhotoAnchors` reads
  photographs); the datamodule calls it when it exists.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from matl.data.canonical import planes_of_objects, require_models
from matl.data.prepared import PreparedPlanes
from matl.data.view_pool import load_view_pool
from matl.data.view_sampler import ViewSampler
from matl.geometry import HomographySampler, anchor_H_canon, warp_image
from matl.utils.errors import MatlError


class FixedAnchors:
    """``anchors=fixed``: in-plane rotations by ``k * 360 / N`` about the image centre (the paper's)."""

    def __call__(self, num_planes: int, num_anchors: int, size: tuple[int, int],
                 generator: torch.Generator, footprints: torch.Tensor) -> torch.Tensor:
        return anchor_H_canon(num_anchors, size, torch.float64).expand(num_planes, -1, -1, -1).clone()


class RandomAnchors:
    """``anchors=random`` (row h): anchors seen from random camera positions.

    Each anchor is the canonical plane under a random view drawn by ``sampler`` (rotation, scale,
    tilt; no translation by default so the object stays centred as a photographer would frame
    it). Its true ``anchor_H_canon`` is known, so poses stay defined.
    """

    def __init__(self, sampler: HomographySampler) -> None:
        self.sampler = sampler

    def __call__(self, num_planes: int, num_anchors: int, size: tuple[int, int],
                 generator: torch.Generator, footprints: torch.Tensor) -> torch.Tensor:
        fp = footprints.repeat_interleave(num_anchors, dim=0)
        H = self.sampler.sample(num_planes * num_anchors, size, generator, fp)
        return H.view(num_planes, num_anchors, 3, 3)


class RenderedRandomAnchors:
    """``anchors=random_rendered``: N anchors per plane *rendered* from random camera positions
    (Sec. 5.7, Table 1 row h, with real views rather than warps).

    Each anchor is a render of the object from a random camera around the plane (``sampler``:
    by default no off-centre framing, as a photographer centres the object), and its
    ``anchor_H_canon`` is the plane-induced homography, exact for planar faces. Needs a mesh-based
    source; the renders are cached per (source, size, N, sampler, split seed).
    """

    def __init__(self, sampler: ViewSampler | dict | None = None) -> None:
        if isinstance(sampler, Mapping):
            sampler = ViewSampler(**{k: v for k, v in sampler.items() if k != "_target_"})
        self.sampler = sampler or ViewSampler(translation=(0.0, 0.0))

    def __call__(self, num_planes: int, num_anchors: int, size: tuple[int, int],
                 generator: torch.Generator, footprints: torch.Tensor) -> torch.Tensor:
        raise MatlError("anchors=random_rendered renders its anchors: the datamodule must call its build_anchors")

    def build_anchors(self, dm: PreparedPlanes, num_anchors: int,
                      generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """Render (or load) the anchors of ``dm``'s planes.

        Returns:
            ``anchor_H_canon`` (P, N, 3, 3) float64 and anchor images (P, N, 3, S, S) float32 in [0, 1].
        """
        source = require_models(dm.source, "anchors=random_rendered")
        seed = int(torch.randint(2**31 - 1, (1,), generator=generator))
        pool = load_view_pool(source, dm.image_size, num_anchors, self.sampler, seed, dm.cache_dir)
        if dm.objects is not None:
            pool = pool.subset_objects(list(dm.objects))
        pool.check_matches(dm.canonical)
        images = torch.from_numpy(pool.images).permute(0, 1, 4, 2, 3).float().div(255.0)
        return torch.from_numpy(pool.query_H_canon).double(), images


class PhotoAnchors:
    """Anchors of the ``images`` dataset (:class:`matl.data.photos.ImageFolderSource`): a plane's
    photographed anchors where it has a plane folder, the ``fallback`` acquisition (default: fixed
    rotations) for the other planes.

    Args:
        fallback: an anchor acquisition (the top-level ``anchors``) for planes without photos.
    """

    def __init__(self, fallback: Any = None) -> None:
        self.fallback = fallback or FixedAnchors()

    def __call__(self, *args: Any, **kwargs: Any) -> torch.Tensor:
        raise MatlError("PhotoAnchors makes anchor images from photos: the datamodule must call its build_anchors")

    def build_anchors(self, dm: PreparedPlanes, num_anchors: int,
                      generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """``anchor_H_canon`` (P, N, 3, 3) float64 and anchor images (P, N, 3, S, S) float32."""
        P, size = dm.canonical.num_planes, (dm.image_size, dm.image_size)
        if hasattr(self.fallback, "build_anchors"):
            H, images = self.fallback.build_anchors(dm, num_anchors, generator)
        else:
            H = self.fallback(P, num_anchors, size, generator, dm.footprints).double()
            src = dm.canon_images.repeat_interleave(num_anchors, dim=0)
            images = warp_image(src, H.reshape(-1, 3, 3)).reshape(P, num_anchors, 3, *size)
        photos_of = getattr(dm.source, "anchor_photos", None)
        if photos_of is None:
            return H, images
        photos = photos_of(dm.image_size)
        # dm.canonical may be a subset of objects (data.objects): map its planes back to the source's.
        keep = planes_of_objects(self._full_plane_object(dm), dm.objects)
        H, images = H.clone(), images.clone()
        for p, full in enumerate(keep):
            photo = photos[int(full)]
            if photo is None:
                continue
            imgs, Hs = photo
            if len(imgs) != num_anchors:
                raise MatlError(f"{dm.canonical.plane_label(p)} has {len(imgs)} photographed anchors but "
                                f"N={num_anchors}: set N={len(imgs)} or give it as many photos")  # fmt: skip
            images[p] = torch.from_numpy(imgs).permute(0, 3, 1, 2).float().div(255.0)
            H[p] = torch.from_numpy(Hs)
        return H, images

    @staticmethod
    def _full_plane_object(dm: PreparedPlanes) -> np.ndarray:
        planes = dm.source.planes()
        objects = list(dict.fromkeys(p.object for p in planes))
        return np.array([objects.index(p.object) for p in planes], dtype=np.int64)
