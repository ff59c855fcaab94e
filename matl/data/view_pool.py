"""A pool of rendered views of every canonical plane, rendered once and cached on disk.

Rendering per training step would be far too slow on a CPU, so a *pool* of ``views_per_plane``
views per plane (cameras from :class:`matl.data.view_sampler.ViewSampler`) is rendered once and
cached like the canonical images (``views_<sha1>.npz``, atomic write). Rendered queries
(:class:`matl.data.queries.RenderedQueries`) split each plane's views into train / val / test;
rendered anchors (:class:`matl.data.anchors.RenderedRandomAnchors`) use a pool of N views per plane.

The source must be a :class:`matl.data.canonical.ModelSource` (mesh-based); the pool's planes are
the canonical set's, in the same order, which :meth:`ViewPool.check_matches` verifies.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
import warnings
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from matl.data.canonical import CanonicalSet, CanonicalSource, ModelSource, ProgressFn, planes_of_objects
from matl.data.view_sampler import ViewSampler, bounding_box_corners
from matl.utils.errors import MatlError
from matl.utils.io import atomic_savez

log = logging.getLogger(__name__)

VIEW_CACHE_VERSION = 1


@dataclass(frozen=True, eq=False)
class ViewPool:
    """``V`` rendered views of each of ``P`` planes.

    Attributes:
        images: (P, V, S, S, 3) uint8 RGB, background 0.
        query_H_canon: (P, V, 3, 3) float64, canonical pixels -> view pixels, ``H[2, 2] = 1``.
        plane_object: (P,) int64 object index of each plane; plane_names (P,), object_names (O,):
            as in the source's :class:`CanonicalSet`, so the two can be checked against each other.
    """

    images: np.ndarray
    query_H_canon: np.ndarray
    plane_object: np.ndarray
    plane_names: list[str]
    object_names: list[str]

    def __post_init__(self) -> None:
        if self.images.ndim != 5 or self.images.shape[-1] != 3 or self.images.dtype != np.uint8:
            raise ValueError(f"images must be uint8 (P, V, S, S, 3), got {self.images.dtype} {self.images.shape}")
        if self.query_H_canon.shape != (*self.images.shape[:2], 3, 3):
            raise ValueError(f"query_H_canon must be {(*self.images.shape[:2], 3, 3)}, got {self.query_H_canon.shape}")
        if self.plane_object.shape != self.images.shape[:1] or len(self.plane_names) != self.images.shape[0]:
            raise ValueError("plane_object and plane_names must have one entry per plane")

    @property
    def num_planes(self) -> int:
        return int(self.images.shape[0])

    @property
    def views_per_plane(self) -> int:
        return int(self.images.shape[1])

    def subset_objects(self, object_indices: list[int] | np.ndarray) -> ViewPool:
        """The views of the given objects' planes, re-indexed like :meth:`CanonicalSet.subset_objects`."""
        idx = [int(i) for i in np.asarray(object_indices, dtype=np.int64).reshape(-1)]
        planes = planes_of_objects(self.plane_object, idx)
        remap = np.full(len(self.object_names), -1, dtype=np.int64)
        remap[idx] = np.arange(len(idx))
        return ViewPool(
            images=self.images[planes],
            query_H_canon=self.query_H_canon[planes],
            plane_object=remap[self.plane_object[planes]],
            plane_names=[self.plane_names[i] for i in planes],
            object_names=[self.object_names[i] for i in idx],
        )

    def check_matches(self, canonical: CanonicalSet) -> None:
        """Raise if the pool's planes are not the canonical set's (same order, names, objects)."""
        if (
            self.plane_names != list(canonical.plane_names)
            or self.object_names != list(canonical.object_names)
            or not np.array_equal(self.plane_object, canonical.plane_object)
        ):
            raise MatlError("rendered views do not match the canonical planes; delete the views_*.npz cache")


def render_view_pool(
    source: ModelSource,
    image_size: int,
    views_per_plane: int,
    sampler: ViewSampler,
    seed: int,
    progress: ProgressFn | None = None,
) -> ViewPool:
    """Render ``views_per_plane`` random views of every plane of ``source`` (no cache; see
    :func:`load_view_pool`). Each plane's cameras come from a generator seeded by ``(seed, plane)``,
    so a plane's views do not depend on the other objects."""
    from matl.data.catalog.rendering import ViewRenderer, plane_half_width  # pyrender sets up OpenGL on import

    images, Hs, plane_object, plane_names, object_names = [], [], [], [], []
    total = None
    with ViewRenderer(image_size, source.supersample) as views:
        for o, model in enumerate(source.models()):
            offsets = views.plane_offsets(model, source.fill)  # the plane each view's homography refers to
            box = bounding_box_corners(model)
            for plane, offset in zip(model.planes, offsets, strict=True):
                rng = np.random.default_rng([seed, len(plane_names)])
                half = plane_half_width(plane, source.fill)
                cams, H = sampler.sample(plane, float(offset), half, box, image_size, views_per_plane, rng)
                imgs, _ = views.render(model, cams)
                images.append(imgs)
                Hs.append(H)
                plane_object.append(o)
                plane_names.append(plane.name)
                if progress is not None:
                    total = total or getattr(source, "num_planes", None) or len(plane_names)
                    progress(len(plane_names), max(total, len(plane_names)))
            object_names.append(model.name or f"object_{o}")
    return ViewPool(
        images=np.stack(images),
        query_H_canon=np.stack(Hs),
        plane_object=np.asarray(plane_object, dtype=np.int64),
        plane_names=plane_names,
        object_names=object_names,
    )


def view_pool_path(
    source: CanonicalSource, image_size: int, views_per_plane: int, sampler: ViewSampler, seed: int, cache_dir: Path
) -> tuple[Path, str]:
    """Cache file of a view pool and the JSON key stored inside it."""
    key = {
        "source": source.cache_key(),
        "image_size": int(image_size),
        "views_per_plane": int(views_per_plane),
        "sampler": sampler.key(),
        "seed": int(seed),
        "format": VIEW_CACHE_VERSION,
    }
    key_json = json.dumps(key, sort_keys=True, separators=(",", ":"))
    return Path(cache_dir) / f"views_{hashlib.sha1(key_json.encode()).hexdigest()}.npz", key_json


def load_view_pool(
    source: ModelSource,
    image_size: int,
    views_per_plane: int,
    sampler: ViewSampler,
    seed: int,
    cache_dir: str | Path,
    progress: ProgressFn | None = None,
) -> ViewPool:
    """The cached pool if present (and readable, with the same key), else render and cache it."""
    path, key_json = view_pool_path(source, image_size, views_per_plane, sampler, seed, Path(cache_dir))
    if path.exists():
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["key"]) != key_json:
                    raise ValueError("cache key mismatch")
                pool = ViewPool(
                    images=z["images"],
                    query_H_canon=z["query_H_canon"],
                    plane_object=z["plane_object"].astype(np.int64),
                    plane_names=[str(s) for s in z["plane_names"]],
                    object_names=[str(s) for s in z["object_names"]],
                )
            log.info("loaded %d x %d rendered views from %s", pool.num_planes, pool.views_per_plane, path)
            return pool
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as e:
            warnings.warn(f"view cache {path} is unreadable ({e}); rebuilding it", RuntimeWarning, stacklevel=2)
    start = time.perf_counter()
    pool = render_view_pool(source, image_size, views_per_plane, sampler, seed, progress)
    seconds = time.perf_counter() - start
    atomic_savez(
        path,
        images=pool.images,
        query_H_canon=pool.query_H_canon,
        plane_object=pool.plane_object,
        plane_names=np.array(pool.plane_names, dtype=str),
        object_names=np.array(pool.object_names, dtype=str),
        key=np.array(key_json),
    )
    n = pool.num_planes * pool.views_per_plane
    log.info("rendered %d views in %.1f s (%.1f images/s), cached in %s", n, seconds, n / max(seconds, 1e-9), path)
    return pool
