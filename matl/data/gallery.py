"""The reference gallery (paper Sec. 4.5): all N anchors of every plane of every object."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

#: a coarse cell counts as plane when at least this share of its pixels is (:meth:`Gallery.coarse_images`)
WHOLE_CELL = 0.99


@dataclass
class Gallery:
    """Anchor images with their labels, flattened over (plane, anchor).

    Attributes:
        images: ``(G, 3, H, W)`` anchor images in [0, 1].
        object_index: ``(G,)`` object of each anchor.
        plane_index: ``(G,)`` plane of each anchor.
        anchor_index: ``(G,)`` k in 0..N-1.
        anchor_H_canon: ``(G, 3, 3)`` pixel homography from the plane's canonical image to the anchor.
        object_names: ``(O,)`` names; plane_names: ``(P,)`` names.
    """

    images: torch.Tensor
    object_index: torch.Tensor
    plane_index: torch.Tensor
    anchor_index: torch.Tensor
    anchor_H_canon: torch.Tensor
    object_names: list[str]
    plane_names: list[str]
    #: (anchor_H_canon, its float64 copy): converted once, again only when anchor_H_canon is replaced
    _canon64: tuple[torch.Tensor, torch.Tensor] | None = field(default=None, init=False, repr=False, compare=False)
    #: (images, cell, their coarse copy and whole-plane cells): :meth:`coarse_images`, pooled once per ``images``
    _coarse: tuple[torch.Tensor, int, torch.Tensor, torch.Tensor] | None = field(default=None, init=False, repr=False,
                                                                                compare=False)

    def __len__(self) -> int:
        return len(self.images)

    @property
    def image_size(self) -> int:
        return int(self.images.shape[-1])

    @property
    def num_anchors(self) -> int:
        return int(self.anchor_index.max()) + 1 if len(self) else 0

    def anchor_H_canon64(self) -> torch.Tensor:
        """``anchor_H_canon`` ``(G, 3, 3)`` in float64 (poses are composed in float64), converted once."""
        if self._canon64 is None or self._canon64[0] is not self.anchor_H_canon:
            self._canon64 = (self.anchor_H_canon, self.anchor_H_canon.double())
        return self._canon64[1]

    def coarse_images(self, cell: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The anchors averaged over ``cell`` x ``cell`` pixel cells, ``(G, 3, S / cell, S / cell)`` float32, and which
        cells are plane throughout (any channel non-zero in every pixel) ``(G, 1, S / cell, S / cell)`` bool; pooled
        once per ``images`` (verification's shortlist compares many anchors per query at this scale)."""
        held = self._coarse
        if held is None or held[0] is not self.images or held[1] != cell:
            images = self.images.float()
            plane = (images.amax(1, keepdim=True) > 0).float()
            held = (self.images, cell, torch.nn.functional.avg_pool2d(images, cell),
                    torch.nn.functional.avg_pool2d(plane, cell) > WHOLE_CELL)
            self._coarse = held
        return held[2], held[3]

    def to(self, device: torch.device | str) -> Gallery:
        return Gallery(self.images.to(device), self.object_index.to(device), self.plane_index.to(device),
                       self.anchor_index.to(device), self.anchor_H_canon.to(device), self.object_names,
                       self.plane_names)
