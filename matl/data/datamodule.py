"""The datamodule: multiple-anchor training triplets, labelled queries and the gallery of anchors.

Design: the datasets hold only *parameters* (plane indices and homographies), sampled once in
``setup`` from seeded generators; images are made per batch in ``materialize``, after the batch
reaches its device (``on_after_batch_transfer``). So data making is a few tensor ops per step,
never a per-image Python loop, and runs on the GPU when there is one.

What the parameters are and how their images are made is the query source's
(:mod:`matl.data.queries`: canonical images warped by random homographies, the paper's Sec. 5.1, or
rendered views); how the anchors are made is the anchor acquisition's (:mod:`matl.data.anchors`).

Splits: the ``seed`` selects the training triplets, validation queries and test queries, each
from its own random stream (:func:`matl.data.streams.stream_generator`); test queries are disjoint
from training by construction.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

from matl.data.anchors import FixedAnchors
from matl.data.augment import CameraAugment
from matl.data.canonical import CanonicalSet, CanonicalSource, load_canonical
from matl.data.gallery import Gallery
from matl.data.occlusion import OccludeQueries
from matl.data.queries import QuerySource, make_query_source
from matl.data.resumable import ResumableShuffleSampler, resume_position
from matl.data.streams import stream_generator
from matl.geometry import HomographySampler, warp_image
from matl.utils.distributed import eval_sampler

Batch = dict[str, torch.Tensor]


class ParamsDataset(Dataset):
    """A dict of equal-length tensors, one item = one row of each."""

    def __init__(self, params: dict[str, torch.Tensor]) -> None:
        lengths = {len(v) for v in params.values()}
        if len(lengths) != 1:
            raise ValueError(f"parameter tensors differ in length: {lengths}")
        self.params = params
        self.length = lengths.pop()

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return {k: v[index] for k, v in self.params.items()}


def footprints_from_masks(masks: torch.Tensor) -> torch.Tensor:
    """Bounding-box corners ``(P, 4, 2)`` (x, y pixels) of each mask ``(P, H, W)``."""
    _, H, W = masks.shape
    rows, cols = masks.any(dim=2), masks.any(dim=1)
    ar_h, ar_w = torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64)
    big = 1e9
    y0 = torch.where(rows, ar_h, big).amin(1)
    y1 = torch.where(rows, ar_h, -big).amax(1)
    x0 = torch.where(cols, ar_w, big).amin(1)
    x1 = torch.where(cols, ar_w, -big).amax(1)
    empty = ~rows.any(1)
    x0, y0 = torch.where(empty, 0.0, x0), torch.where(empty, 0.0, y0)
    x1, y1 = torch.where(empty, W - 1.0, x1), torch.where(empty, H - 1.0, y1)
    return torch.stack([torch.stack([x0, y0], -1), torch.stack([x1, y0], -1),
                        torch.stack([x1, y1], -1), torch.stack([x0, y1], -1)], 1)


class TripletDataModule(L.LightningDataModule):
    """Multiple-anchor triplets for training, labelled queries and a gallery for evaluation.

    Args:
        source: what provides the canonical images (a :class:`CanonicalSource`).
        image_size: model image side in pixels (paper: 100).
        num_anchors: N anchors per plane.
        homography: sampler of the random homographies of warped positives, negatives and queries.
        anchors: anchor acquisition (:mod:`matl.data.anchors`; fixed rotations by default).
        train_triplets / val_queries / test_queries: sizes of the splits.
        batch_size / eval_batch_size: loader batch sizes.
        seed: selects the split.
        cache_dir: where canonical images are cached.
        objects: optional list of object indices to keep (e.g. a planar / non-planar split).
        queries: "warped" (default, the paper's), "rendered", or a
            :class:`matl.data.queries.QuerySource`: what this module delegates query sampling and
            image making to (:func:`matl.data.queries.make_query_source`, ``docs/datasets.md``).
        views: options of the rendered view pool (``data.views``), used when ``queries="rendered"``.
        augment: camera-like positives and negatives (:class:`matl.data.augment.CameraAugment`,
            ``data.augment``), or None for the paper's clean warps. Anchors and the validation and
            test queries are never augmented.
        occlude: partly hidden positives and negatives (:class:`matl.data.occlusion.OccludeQueries`,
            ``data.occlude``), or None (the paper). The un-occluded positive is kept as
            ``positive_target`` for the appearance loss.
    """

    def __init__(self, source: CanonicalSource, image_size: int = 100, num_anchors: int = 4,
                 homography: HomographySampler | None = None, anchors: Any = None,
                 train_triplets: int = 4000, val_queries: int = 300, test_queries: int = 1000,
                 batch_size: int = 32, eval_batch_size: int = 250, seed: int = 0,
                 cache_dir: str | Path = ".cache", objects: list[int] | None = None,
                 queries: Any = "warped", views: Any = None, augment: CameraAugment | None = None,
                 occlude: OccludeQueries | None = None) -> None:
        super().__init__()
        if num_anchors < 1:
            raise ValueError(f"N (number of anchors) must be >= 1, got {num_anchors}")
        self.source = source
        self.image_size = int(image_size)
        self.num_anchors = int(num_anchors)
        self.homography = homography or HomographySampler()
        self.anchors = anchors or FixedAnchors()
        self.train_triplets, self.val_queries, self.test_queries = train_triplets, val_queries, test_queries
        self.batch_size, self.eval_batch_size = batch_size, eval_batch_size
        self.seed = seed
        self.cache_dir = Path(cache_dir)
        self.objects = objects
        self.queries, self.views = queries, views
        self.augment = augment
        self.occlude = occlude
        self._ready = False

    # ------------------------------------------------------------------ setup
    @property
    def size(self) -> tuple[int, int]:
        return (self.image_size, self.image_size)

    def setup(self, stage: str | None = None) -> None:
        if self._ready:
            return
        canonical = load_canonical(self.source, self.image_size, self.cache_dir)
        if self.objects is not None:
            canonical = canonical.subset_objects(list(self.objects))
        self.canonical: CanonicalSet = canonical
        self.canon_images = torch.from_numpy(canonical.images).permute(0, 3, 1, 2).float().div(255.0)
        self.masks = torch.from_numpy(canonical.masks)
        self.footprints = footprints_from_masks(self.masks)
        self.plane_object = torch.from_numpy(canonical.plane_object).long()
        P, N = canonical.num_planes, self.num_anchors

        # anchors: (P, N, 3, S, S) and their poses (P, N, 3, 3)
        if hasattr(self.anchors, "build_anchors"):  # acquisitions that make their own images (rendered, photos)
            H, images = self.anchors.build_anchors(self, N, stream_generator(self.seed, "anchors"))
            self.anchor_H_canon, self.anchor_images = H.double(), images.float()
            flat_H = self.anchor_H_canon.reshape(-1, 3, 3)
        else:
            self.anchor_H_canon = self.anchors(P, N, self.size, stream_generator(self.seed, "anchors"),
                                               self.footprints).double()
            flat_H = self.anchor_H_canon.reshape(-1, 3, 3)
            src = self.canon_images.repeat_interleave(N, dim=0)
            self.anchor_images = warp_image(src, flat_H).reshape(P, N, 3, *self.size)
        # (P, N, 1, S, S) bool: each anchor's foreground, its non-zero pixels (backgrounds are exactly 0
        # and print never is); bool keeps a large catalog's masks small
        self.anchor_masks = (self.anchor_images.amax(dim=2, keepdim=True) > 0).contiguous()
        self.gallery = Gallery(
            images=self.anchor_images.reshape(P * N, 3, *self.size),
            object_index=self.plane_object.repeat_interleave(N),
            plane_index=torch.arange(P).repeat_interleave(N),
            anchor_index=torch.arange(N).repeat(P),
            anchor_H_canon=flat_H.clone(),
            object_names=list(canonical.object_names),
            plane_names=list(canonical.plane_names),
        )
        self.query_source: QuerySource = make_query_source(self.queries, self.views, self.homography)
        self.query_source.setup(self)
        sample, stream = self.query_source, functools.partial(stream_generator, self.seed)
        triplets = sample.sample_triplets(self.train_triplets, "train", stream("train"))
        if self.augment is not None:  # one seed per triplet: a batch is augmented alike whenever it is made
            self.augment.setup(self.canon_images, self.masks[:, None].float())
            triplets["aug_seed"] = torch.randint(2**62, (self.train_triplets,), generator=stream("augment"))
        if self.occlude is not None:  # likewise one seed per triplet for the occluders
            self.occlude.setup(self.canon_images, self.masks[:, None].float(), self.plane_object)
            triplets["occ_seed"] = torch.randint(2**62, (self.train_triplets,), generator=stream("occlude"))
        self.train_set = ParamsDataset(triplets)
        self.val_set = ParamsDataset(sample.sample_queries(self.val_queries, "val", stream("val")))
        self.test_set = ParamsDataset(sample.sample_queries(self.test_queries, "test", stream("test")))
        self._device_anchors: dict[torch.device, tuple[torch.Tensor, torch.Tensor]] = {}
        self._ready = True

    # -------------------------------------------------------------- loaders
    def train_dataloader(self) -> DataLoader:
        # The shuffle of DataLoader(shuffle=True, generator=stream "shuffle"), but resumable: a run
        # restarted from a mid-epoch checkpoint continues with the batches it had not trained on.
        make_generator = functools.partial(stream_generator, self.seed, "shuffle")
        sampler = ResumableShuffleSampler(len(self.train_set), make_generator)
        epoch, batches = resume_position(getattr(self, "trainer", None), len(self.train_set) // self.batch_size)
        sampler.resume_at(epoch, batches * self.batch_size)
        return DataLoader(self.train_set, batch_size=self.batch_size, sampler=sampler, drop_last=True,
                          generator=stream_generator(self.seed, "loader"))

    # Under DDP, eval_sampler shards the queries without the DistributedSampler's padding, so every
    # query counts exactly once (matl/utils/distributed.py); one process: None, the sequential order.
    # Evaluation loaders get their own generator: creating a loader's iterator otherwise draws from
    # the global RNG, which would shift the training's random negatives (NCE) after every validation.
    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=self.eval_batch_size, sampler=eval_sampler(self.val_set),
                          generator=stream_generator(self.seed, "loader"))

    def test_dataloader(self) -> DataLoader:
        return DataLoader(self.test_set, batch_size=self.eval_batch_size, sampler=eval_sampler(self.test_set),
                          generator=stream_generator(self.seed, "loader"))

    # ------------------------------------------------------------ materialise
    def _anchors_on(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        if device not in self._device_anchors:
            self._device_anchors[device] = (self.anchor_images.to(device), self.anchor_masks.to(device))
        return self._device_anchors[device]

    def materialize(self, batch: Batch) -> Batch:
        """Turn a batch of parameters into images (on the batch's device), by the query source.

        Adds ``query`` ``(B, 3, S, S)`` to query batches; ``positive``, ``negative``, ``anchors``
        ``(B, N, 3, S, S)`` and ``anchor_masks`` ``(B, N, 1, S, S)`` (float {0, 1}, each anchor's
        foreground) to triplet batches. With ``augment``, positives and negatives are camera-like.
        """
        if "query" in batch or "positive" in batch:
            return batch
        out = self.query_source.materialize(batch)
        if "neg_plane" in batch:
            anchors, masks = self._anchors_on(batch["plane"].device)
            out["anchors"], out["anchor_masks"] = anchors[batch["plane"]], masks[batch["plane"]].float()
            if self.augment is not None and "aug_seed" in batch:
                g = torch.Generator().manual_seed(int(batch["aug_seed"][0]))
                pos_mask, neg_mask = self.query_source.foreground(out)
                both = self.augment(torch.cat([out["positive"], out["negative"]]), torch.cat([pos_mask, neg_mask]), g)
                out["positive"], out["negative"] = both.chunk(2)
            if self.occlude is not None and "occ_seed" in batch:
                g = torch.Generator().manual_seed(int(batch["occ_seed"][0]))
                pos_mask, neg_mask = self.query_source.foreground(out)
                objects = torch.cat([batch["object"], batch["neg_object"]]).cpu()
                both, _ = self.occlude(torch.cat([out["positive"], out["negative"]]),
                                       torch.cat([pos_mask, neg_mask]), objects, g)
                out["positive_target"] = out["positive"]
                out["positive"], out["negative"] = both.chunk(2)
        return out

    def on_after_batch_transfer(self, batch: Batch, dataloader_idx: int) -> Batch:
        return self.materialize(batch)
