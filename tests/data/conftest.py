"""Sources for the data tests: in-memory patterns (no rendering) and a tiny mesh-based catalog."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
import torch

from matl.data.canonical import CanonicalSet
from matl.data.catalog import SyntheticCatalog
from matl.data.catalog.models import product_model
from matl.data.catalog.shapes import ProductModel
from matl.data.datamodule import TripletDataModule


def masked_prints(B: int, S: int, rows: tuple[int, int], cols: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """``B`` random RGB prints in [0.1, 0.9] (seed 0) on the rectangle ``rows`` x ``cols`` of an ``S`` x ``S`` frame,
    black elsewhere, and their masks ``(B, 1, S, S)``."""
    masks = torch.zeros(B, 1, S, S)
    masks[:, :, rows[0]:rows[1], cols[0]:cols[1]] = 1.0
    images = torch.rand(B, 3, S, S, generator=torch.Generator().manual_seed(0)) * 0.8 + 0.1
    return images * masks, masks


class PatternSource:
    """A fast in-memory source: 6 objects x 2 planes of random blocks (no rendering)."""

    def __init__(self, size_hint: int = 0) -> None:
        self.size_hint = size_hint

    def cache_key(self) -> dict:
        return {"kind": "pattern-test"}

    def build(self, image_size: int, progress=None) -> CanonicalSet:
        rng = np.random.default_rng(0)
        S, P = image_size, 12
        images = np.zeros((P, S, S, 3), np.uint8)
        masks = np.zeros((P, S, S), bool)
        lo, hi = S // 4, 3 * S // 4
        for p in range(P):
            images[p, lo:hi, lo:hi] = rng.integers(20, 255, (hi - lo, hi - lo, 3))
            masks[p, lo:hi, lo:hi] = True
        return CanonicalSet(images, masks, np.repeat(np.arange(6), 2).astype(np.int64),
                            [f"p{i % 2}" for i in range(P)], [f"o{i}" for i in range(6)], ["planar"] * 6)


def pattern_datamodule(cache_dir, **options: Any) -> TripletDataModule:
    """A set-up :class:`TripletDataModule` of :class:`PatternSource` at 32 px: 2 anchors, 16 training triplets in
    batches of 8, 4 validation and 4 test queries, seed 0; ``options`` its others (``augment``, ``occlude``)."""
    dm = TripletDataModule(PatternSource(), image_size=32, num_anchors=2, train_triplets=16, val_queries=4,
                           test_queries=4, batch_size=8, eval_batch_size=4, seed=0, cache_dir=cache_dir, **options)
    dm.setup()
    return dm


class TinyCatalog:
    """Three products of the APC catalog (planar, rectangular, cylindrical): 18 planes, fast."""

    fill = 0.6
    supersample = 2

    def __init__(self, texture_px: int = 96) -> None:
        specs = SyntheticCatalog("apc", texture_px=texture_px).products()
        self.specs = [next(s for s in specs if s.shape == shape) for shape in ("planar", "rectangular", "cylindrical")]
        self.texture_px = texture_px
        self.num_planes = 18

    def cache_key(self) -> dict[str, Any]:
        return {"type": "tiny-test-catalog", "texture_px": self.texture_px}

    def models(self) -> Iterator[ProductModel]:
        for spec in self.specs:
            yield product_model(spec, self.texture_px)

    def build(self, image_size: int) -> CanonicalSet:
        from matl.data.catalog.rendering import CanonicalRenderer

        images, masks, plane_object, names = [], [], [], []
        with CanonicalRenderer(image_size, self.supersample, self.fill) as r:
            for o, model in enumerate(self.models()):
                im, m = r.render(model)
                images.append(im)
                masks.append(m)
                plane_object += [o] * len(model.planes)
                names += [p.name for p in model.planes]
        return CanonicalSet(np.concatenate(images), np.concatenate(masks), np.asarray(plane_object, np.int64), names,
                            [s.name for s in self.specs], [s.shape for s in self.specs])  # fmt: skip


@pytest.fixture(scope="session")
def tiny() -> TinyCatalog:
    return TinyCatalog()
