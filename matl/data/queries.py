"""Query sources: how positives, negatives and test queries are made (``data.queries``).

A :class:`QuerySource` samples the *parameters* of the datamodule's splits (plane indices and
homographies, drawn once at setup from the split's random stream) and makes their images per
batch on the batch's device. Two are built in:

* :class:`WarpedQueries` (``data.queries=warped``, the default): the canonical image warped by a
  random homography (paper Sec. 5.1), one batched warp per batch.
* :class:`RenderedQueries` (``data.queries=rendered``): views rendered from random 3D camera poses
  around the plane (:mod:`matl.data.view_sampler`), taken from a pool rendered once and cached
  (:mod:`matl.data.view_pool`). Needs a mesh-based source.

Parameter dicts hold ``plane``, ``object`` and ``query_H_canon`` (``(n, 3, 3)`` float32) per query,
plus ``neg_plane``, ``neg_object`` and ``neg_H_canon`` per triplet, and may hold more (the
rendered source adds the flat view indices ``view`` / ``neg_view``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import torch

from matl.data.canonical import require_models
from matl.data.prepared import PreparedPlanes
from matl.data.streams import copy_generator, stream_generator
from matl.data.view_pool import load_view_pool
from matl.data.view_sampler import ViewSampler
from matl.geometry import HomographySampler, warp_image
from matl.utils.errors import MatlError

Batch = dict[str, torch.Tensor]


@runtime_checkable
class QuerySource(Protocol):
    """How positives, negatives and test queries are made.

    The datamodule calls :meth:`setup` once it has its canonical images, then delegates the
    sampling of the parameter datasets and, per batch on its device, the making of images (see
    the module docstring for the parameter dicts).
    """

    def setup(self, dm: PreparedPlanes) -> None:
        """Prepare for ``dm``'s canonical planes (``dm.canonical``, ``dm.image_size``, ``dm.seed``)."""
        ...

    def sample_queries(self, n: int, stream: str, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Parameters of ``n`` labelled queries of split ``stream`` ("val" or "test")."""
        ...

    def sample_triplets(self, n: int, stream: str, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Parameters of ``n`` training triplets (positive and negative) of split ``stream``."""
        ...

    def materialize(self, batch: Batch) -> Batch:
        """Add ``query`` (query batches) or ``positive`` and ``negative`` (triplet batches),
        ``(B, 3, S, S)`` float in [0, 1], on the batch's device."""
        ...

    def foreground(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, 1, S, S)`` float {0, 1} foreground masks of a materialised triplet batch's positives
        and negatives (what :class:`matl.data.augment.CameraAugment` puts a background behind)."""
        ...


class WarpedQueries:
    """``data.queries=warped`` (paper Sec. 5.1): each query, positive and negative is its plane's
    canonical image warped by a random homography of ``homography`` (``data.homography``), drawn
    inside the plane's footprint so the object stays in the frame.

    Args:
        homography: the sampler of the random homographies (default: its defaults).
    """

    def __init__(self, homography: HomographySampler | None = None) -> None:
        self.homography = homography or HomographySampler()

    def setup(self, dm: PreparedPlanes) -> None:
        self.size = dm.size
        self.footprints = dm.footprints
        self.plane_object = dm.plane_object
        self.num_objects = dm.canonical.num_objects
        self.canon_images = dm.canon_images
        self.canon_masks = dm.masks[:, None].float()
        self._device_images: dict[torch.device, torch.Tensor] = {}
        self._device_masks: dict[torch.device, torch.Tensor] = {}

    def sample_queries(self, n: int, stream: str, generator: torch.Generator) -> dict[str, torch.Tensor]:
        plane = torch.randint(len(self.plane_object), (n,), generator=generator)
        H = self.homography.sample(n, self.size, generator, self.footprints[plane])
        return {"plane": plane, "object": self.plane_object[plane], "query_H_canon": H.float()}

    def sample_triplets(self, n: int, stream: str, generator: torch.Generator) -> dict[str, torch.Tensor]:
        # The positives draw from a copy of the stream's generator and the negatives from the stream
        # itself, both from the same starting state (the splits of every earlier version did so).
        params = self.sample_queries(n, stream, copy_generator(generator))
        if self.num_objects < 2:
            raise ValueError("triplets need at least 2 objects (negatives come from other objects)")
        neg_plane = torch.randint(len(self.plane_object), (n,), generator=generator)
        clash = self.plane_object[neg_plane] == params["object"]
        while clash.any():  # resample the negatives that hit the positive's object
            neg_plane[clash] = torch.randint(len(self.plane_object), (int(clash.sum()),), generator=generator)
            clash = self.plane_object[neg_plane] == params["object"]
        neg_H = self.homography.sample(n, self.size, generator, self.footprints[neg_plane])
        params.update(neg_plane=neg_plane, neg_object=self.plane_object[neg_plane], neg_H_canon=neg_H.float())
        return params

    def _on_device(self, device: torch.device) -> torch.Tensor:
        if device not in self._device_images:
            self._device_images[device] = self.canon_images.to(device)
        return self._device_images[device]

    def materialize(self, batch: Batch) -> Batch:
        canon = self._on_device(batch["plane"].device)
        out = dict(batch)
        if "neg_plane" in batch:
            both = torch.cat([canon[batch["plane"]], canon[batch["neg_plane"]]])
            H = torch.cat([batch["query_H_canon"], batch["neg_H_canon"]])
            out["positive"], out["negative"] = warp_image(both, H).chunk(2)
        else:
            out["query"] = warp_image(canon[batch["plane"]], batch["query_H_canon"])
        return out

    def foreground(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        device = batch["plane"].device
        if device not in self._device_masks:
            self._device_masks[device] = self.canon_masks.to(device)
        masks = self._device_masks[device]
        both = torch.cat([masks[batch["plane"]], masks[batch["neg_plane"]]])
        H = torch.cat([batch["query_H_canon"], batch["neg_H_canon"]])
        pos, neg = (warp_image(both, H) > 0.5).float().chunk(2)
        return pos, neg


@dataclass
class RenderedQueries:
    """``data.queries=rendered``: positives, negatives and test queries from a rendered view pool.

    Args:
        views_per_plane: views rendered per plane (pool size; cached).
        val_fraction, test_fraction: share of each plane's views held out for validation and
            test (at least one each); the rest are training views. Which views fall where is
            drawn from the split seed, so test views are never trained on.
        seed: the pool's rendering seed (fixed: the split seed does not re-render the pool).
        sampler: camera and lighting ranges (:class:`ViewSampler`).
    """

    views_per_plane: int = 30
    val_fraction: float = 0.1
    test_fraction: float = 0.3
    seed: int = 0
    sampler: ViewSampler = field(default_factory=ViewSampler)

    def __post_init__(self) -> None:
        if isinstance(self.sampler, Mapping):
            self.sampler = ViewSampler(**{k: v for k, v in self.sampler.items() if k != "_target_"})
        if self.views_per_plane < 3:
            raise MatlError(f"data.views.views_per_plane={self.views_per_plane}: need >= 3 (train, val and test)")
        if not (self.val_fraction > 0 and self.test_fraction > 0 and self.val_fraction + self.test_fraction < 1):
            raise MatlError("data.views.val_fraction and test_fraction must be > 0 with a sum below 1")

    def split_sizes(self) -> tuple[int, int, int]:
        """Views per plane for (train, val, test)."""
        v = self.views_per_plane
        n_val = max(1, round(v * self.val_fraction))
        n_test = max(1, round(v * self.test_fraction))
        return v - n_val - n_test, n_val, n_test

    def setup(self, dm: PreparedPlanes) -> None:
        source = require_models(dm.source, "data.queries=rendered")
        pool = load_view_pool(source, dm.image_size, self.views_per_plane, self.sampler, self.seed, dm.cache_dir)
        if dm.objects is not None:
            pool = pool.subset_objects(list(dm.objects))
        pool.check_matches(dm.canonical)
        P, V = pool.num_planes, pool.views_per_plane
        self.num_views = V
        # uint8 keeps the pool 4x smaller than float; images are converted per batch on its device.
        self.images = torch.from_numpy(pool.images.reshape(P * V, *pool.images.shape[2:])).permute(0, 3, 1, 2)
        self.images = self.images.contiguous()
        self.query_H_canon = torch.from_numpy(pool.query_H_canon.reshape(P * V, 3, 3))
        self.plane_object = torch.from_numpy(pool.plane_object)
        # Per plane, a seeded permutation of its views: the first n_train train, then val, then test.
        n_train, n_val, _ = self.split_sizes()
        g = stream_generator(dm.seed, "views")
        order = torch.argsort(torch.rand(P, V, generator=g), dim=1) + torch.arange(P)[:, None] * V
        self.views = {"train": order[:, :n_train], "val": order[:, n_train : n_train + n_val],
                      "test": order[:, n_train + n_val :]}  # fmt: skip
        self._device_images: dict[torch.device, torch.Tensor] = {}

    def _split(self, stream: str) -> torch.Tensor:
        return self.views.get(stream, self.views["train"])

    def sample_queries(self, n: int, stream: str, generator: torch.Generator) -> dict[str, torch.Tensor]:
        views = self._split(stream).reshape(-1)
        # Without replacement while the split has enough views, so test queries are distinct.
        if n <= len(views):
            view = views[torch.randperm(len(views), generator=generator)[:n]]
        else:
            view = views[torch.randint(len(views), (n,), generator=generator)]
        plane = view // self.num_views
        return {"plane": plane, "object": self.plane_object[plane], "query_H_canon": self.query_H_canon[view].float(),
                "view": view}  # fmt: skip

    def sample_triplets(self, n: int, stream: str, generator: torch.Generator) -> dict[str, torch.Tensor]:
        views = self._split(stream)
        P, per_plane = views.shape
        if len(torch.unique(self.plane_object)) < 2:
            raise MatlError("triplets need at least 2 objects (negatives come from other objects)")
        plane = torch.randint(P, (n,), generator=generator)
        view = views[plane, torch.randint(per_plane, (n,), generator=generator)]
        neg_plane = torch.randint(P, (n,), generator=generator)
        clash = self.plane_object[neg_plane] == self.plane_object[plane]
        while clash.any():  # resample the few negatives that hit the positive's object
            neg_plane[clash] = torch.randint(P, (int(clash.sum()),), generator=generator)
            clash = self.plane_object[neg_plane] == self.plane_object[plane]
        neg_view = views[neg_plane, torch.randint(per_plane, (n,), generator=generator)]
        return {
            "plane": plane, "object": self.plane_object[plane], "query_H_canon": self.query_H_canon[view].float(),
            "view": view, "neg_plane": neg_plane, "neg_object": self.plane_object[neg_plane],
            "neg_H_canon": self.query_H_canon[neg_view].float(), "neg_view": neg_view,
        }  # fmt: skip

    def _on_device(self, device: torch.device) -> torch.Tensor:
        if device not in self._device_images:
            self._device_images[device] = self.images.to(device)
        return self._device_images[device]

    def materialize(self, batch: Batch) -> Batch:
        device = batch["view"].device
        images = self._on_device(device)
        out = dict(batch)
        if "neg_view" in batch:
            out["positive"] = images[batch["view"]].float().div_(255.0)
            out["negative"] = images[batch["neg_view"]].float().div_(255.0)
        else:
            out["query"] = images[batch["view"]].float().div_(255.0)
        return out

    def foreground(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        # rendered views have an exactly-0 background (docs/datasets.md)
        return tuple((batch[k].amax(dim=1, keepdim=True) > 0).float() for k in ("positive", "negative"))


def make_query_source(queries: Any, views: Any = None, homography: HomographySampler | None = None) -> QuerySource:
    """The query source for ``data.queries``.

    Args:
        queries: "warped" (or None): a :class:`WarpedQueries` of ``homography``; "rendered":
            ``views``; a :class:`QuerySource` is returned as it is.
        views: ``data.views``: a :class:`RenderedQueries`, a mapping of its arguments, or None for
            its defaults (used for "rendered" only).
        homography: ``data.homography`` (used for "warped" only).
    """
    if queries is None or queries == "warped":
        return WarpedQueries(homography)
    if isinstance(queries, QuerySource):
        return queries
    if queries == "rendered":
        if isinstance(views, QuerySource):
            return views
        return RenderedQueries(**{k: v for k, v in (views or {}).items() if k != "_target_"})
    raise MatlError(f"data.queries={queries!r} is invalid: use warped (the paper's) or rendered")
