"""What the datamodule's parts read of it once its canonical planes are loaded.

Anchor acquisitions (:mod:`matl.data.anchors`) and query sources (:mod:`matl.data.queries`) are set up
by :class:`matl.data.datamodule.TripletDataModule`, which they must not import (it imports them): they
take it as a :class:`PreparedPlanes`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import torch

from matl.data.canonical import CanonicalSet, CanonicalSource

__all__ = ["PreparedPlanes"]


class PreparedPlanes(Protocol):
    """The canonical planes of a set-up datamodule and where they came from."""

    source: CanonicalSource
    image_size: int
    cache_dir: Path
    seed: int
    objects: list[int] | None           # the source's objects kept (data.objects), None: all
    canonical: CanonicalSet
    canon_images: torch.Tensor          # (P, 3, S, S) float in [0, 1]
    masks: torch.Tensor                 # (P, S, S) bool, the planes' foreground
    footprints: torch.Tensor            # (P, 4, 2) bounding-box corners of each plane's object
    plane_object: torch.Tensor          # (P,) int64 object index of each plane

    @property
    def size(self) -> tuple[int, int]:
        """``(S, S)``."""
        ...
