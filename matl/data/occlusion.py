"""Training positives and negatives that are partly hidden (``data.occlude``; beyond the paper, off in its rows).

In a picking bin the product is seldom whole: another product lies across it, the gripper or the bin
wall hides part of it. At inference the foreground step keeps the product's *visible* print and sets
the rest (background, occluders) to 0, so a query is a product with holes. :class:`OccludeQueries`
makes training positives and negatives look like that: with probability ``p`` an occluder of
:class:`matl.data.occluders.Occluders` (another catalog product on top, a gripper finger, a suction cup,
the bin wall) is drawn over the product, hiding a fraction in ``hidden`` of it, and the occluded
pixels are set to 0 as the foreground step would (with probability ``leak_p`` the occluder stays in the
image: a mask that missed it).

The appearance loss must not ask ``s()`` to explain a hole: the datamodule keeps the un-occluded
positive as ``batch["positive_target"]`` and :class:`matl.models.module.MATLModule` takes the appearance
terms (and Eq. 3's anchor selection) on it, warped by the pose ``s()`` regressed from the occluded one.
So ``s()`` learns to pose a product from its visible part, ``c()`` to embed a partly hidden product
near its anchor, and the pose is judged on the whole product.

Randomness: each call takes a generator (the datamodule seeds it per batch from the triplets'
``occ_seed`` column), so a batch looks the same whenever it is made.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from matl.data.occluders import Occluders
from matl.utils.errors import MatlError

#: the kinds' weights of ``occlude=bin`` (conf/occlude/bin.yaml)
DEFAULT_KINDS = {"product": 0.4, "gripper": 0.25, "suction": 0.15, "edge": 0.2}


@dataclass
class OccludeQueries:
    """Occluders over training positives and negatives (see the module docstring).

    Args:
        p: probability that an image gets an occluder.
        occluders: :class:`~matl.data.occluders.Occluders` settings (a mapping or the object): the kinds'
            weights and the hidden-fraction range.
        leak_p: probability that an occluded image keeps the occluder's pixels (a mask that missed it)
            instead of 0 there.
        products: other catalog products offered to the ``product`` occluder per image.
    """

    p: float = 0.5
    occluders: Any = field(default_factory=lambda: Occluders(dict(DEFAULT_KINDS)))
    leak_p: float = 0.25
    products: int = 4

    def __post_init__(self) -> None:
        if isinstance(self.occluders, Mapping):
            self.occluders = Occluders(**{k: v for k, v in self.occluders.items() if k != "_target_"})
        if not 0 <= float(self.p) <= 1 or not 0 <= float(self.leak_p) <= 1 or int(self.products) < 1:
            raise MatlError(f"data.occlude: p={self.p} and leak_p={self.leak_p} must be in [0, 1] and "
                            f"products={self.products} >= 1")
        self._canon: np.ndarray | None = None

    def setup(self, canon_images: torch.Tensor, canon_masks: torch.Tensor, plane_object: torch.Tensor) -> None:
        """Keep the training catalog's ``(P, 3, S, S)`` images, ``(P, 1, S, S)`` masks and ``(P,)`` objects:
        the ``product`` occluders are drawn from them."""
        self._canon = canon_images.permute(0, 2, 3, 1).double().numpy()
        self._masks = canon_masks[:, 0].double().numpy()
        self._plane_object = plane_object.numpy()

    def _others(self, obj: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
        candidates = np.flatnonzero(self._plane_object != obj)
        if len(candidates) == 0:
            candidates = np.arange(len(self._plane_object))
        picks = rng.choice(candidates, size=min(int(self.products), len(candidates)), replace=False)
        return [(self._canon[k], self._masks[k]) for k in picks]

    def __call__(self, images: torch.Tensor, masks: torch.Tensor, objects: torch.Tensor, g: torch.Generator
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """Occlude a batch.

        Args:
            images: ``(B, 3, S, S)`` positives or negatives in [0, 1].
            masks: ``(B, 1, S, S)`` their products' coverage (float in [0, 1]).
            objects: ``(B,)`` their objects (an occluding product is another object's).
            g: the batch's generator.

        Returns:
            The images ``(B, 3, S, S)`` (unchanged where no occluder was drawn) and the products' visible
            coverage ``(B, 1, S, S)``.
        """
        if self._canon is None:
            raise RuntimeError("OccludeQueries.setup() must run before it is called")
        B = images.shape[0]
        if images.ndim != 4 or masks.shape != (B, 1, *images.shape[2:]) or objects.shape != (B,):
            raise ValueError(f"images must be (B, 3, S, S), masks (B, 1, S, S) and objects (B,), got "
                             f"{tuple(images.shape)}, {tuple(masks.shape)} and {tuple(objects.shape)}")
        seeds = torch.randint(2**62, (B,), generator=g).tolist()
        hit = (torch.rand(B, generator=g) < float(self.p)).tolist()
        leak = (torch.rand(B, generator=g) < float(self.leak_p)).tolist()
        out, visible = images.clone(), masks.clone().float()
        for i in (i for i in range(B) if hit[i]):
            rng = np.random.default_rng(seeds[i])
            image = images[i].permute(1, 2, 0).double().cpu().numpy()
            cover = masks[i, 0].double().cpu().numpy()
            if cover.sum() < 1.0:  # nothing of the product in the frame: nothing to hide
                continue
            drawn, seen, _ = self.occluders.apply(image, cover, rng, self._others(int(objects[i]), rng))
            if not leak[i]:  # the foreground step keeps the visible print (in the occluder's shadow) only
                kept = (seen / np.maximum(cover, 1e-6)).clip(0.0, 1.0)[..., None]
                drawn = np.where(cover[..., None] > 1e-6, drawn * kept, image)
            out[i] = torch.from_numpy(drawn).permute(2, 0, 1).to(images)
            visible[i, 0] = torch.from_numpy(seen).to(visible)
        return out, visible
