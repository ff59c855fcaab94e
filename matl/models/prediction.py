"""What every recognizer answers for a batch of query tensors, and the call they all share.

The tensor-level recognizers (MATL's :class:`~matl.models.recognizer.TensorRecognizer`, the STN
classifier's :class:`~matl.models.stn_classifier.ClassifierRecognizer`, a keypoint baseline's
:class:`~matl.baselines.recognizer.BaselineRecognizer`, and :class:`~matl.inference.refine.RefinedRecognizer`
around any of them) are :class:`QueryRecognizer`: ``recognizer(queries (Q, 3, S, S)) -> Prediction``
against their ``gallery``. Evaluation, timing and refinement take any of them through this call.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import torch

from matl.data.gallery import Gallery

__all__ = ["Prediction", "QueryRecognizer"]


@dataclass
class Prediction:
    """Per-query results; ``query_H_canon`` is None for models without an STN."""

    gallery_index: torch.Tensor          # (Q,) nearest gallery anchor
    object_index: torch.Tensor           # (Q,)
    plane_index: torch.Tensor            # (Q,)
    anchor_index: torch.Tensor           # (Q,)
    distance: torch.Tensor               # (Q,) L2 feature distance to it
    query_H_anchor: torch.Tensor | None  # (Q, 3, 3) pixel, STN output
    query_H_canon: torch.Tensor | None   # (Q, 3, 3) pixel pose
    warped: torch.Tensor                 # (Q, 3, H, W) s(query)
    degenerate: torch.Tensor             # (Q,) bool, STN output replaced by identity
    #: (Q, D) c(s(query)), the embeddings the search used; None from recognizers without a feature gallery
    features: torch.Tensor | None = field(default=None, kw_only=True)


@runtime_checkable
class QueryRecognizer(Protocol):
    """Recognises query batches against a gallery: object, plane, anchor and pose of each query."""

    #: the anchors answers are drawn from (``gallery_index`` indexes it)
    gallery: Gallery

    def __call__(self, queries: torch.Tensor) -> Prediction:
        """``(Q, 3, S, S)`` queries in ``[0, 1]``, ``S = gallery.image_size`` -> one :class:`Prediction`."""
        ...
