"""A keypoint matcher behind the recognizer's interface, so baselines run through the same evaluator."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import hydra
import torch
from omegaconf import DictConfig

from matl.data.gallery import Gallery
from matl.geometry import compose_query_H_canon
from matl.models.prediction import Prediction
from matl.utils.errors import MatlError


@dataclass
class BaselinePrediction(Prediction):
    """A :class:`Prediction` of a keypoint baseline, plus its RANSAC inlier counts ``(Q,)``."""

    inliers: torch.Tensor


class BaselineRecognizer:
    """Makes a keypoint matcher answer like :class:`matl.models.recognizer.TensorRecognizer`.

    The matcher indexes the gallery's anchor images once; ``match`` gives the gallery image with
    most RANSAC inliers and ``query_H_anchor``. The pose is ``query_H_anchor @ anchor_H_canon`` of
    that gallery image.

    Convention: the matcher's ``query_H_anchor`` maps pixels of the matched *anchor* image (not of
    the canonical image) to query pixels, the same direction as the STN's, so both compose with
    the gallery's ``anchor_H_canon`` identically.

    Unmatched queries (index -1) get object -1 (never correct) and identity. ``distance`` is NaN:
    a matcher has no feature distance (see ``inliers``).
    """

    def __init__(self, matcher: Any, gallery: Gallery) -> None:
        self.matcher, self.gallery = matcher, gallery.to("cpu")
        matcher.index_gallery(self.gallery.images)

    @torch.no_grad()
    def __call__(self, queries: torch.Tensor) -> BaselinePrediction:
        """``(Q, 3, S, S)`` -> prediction (on the CPU)."""
        g = self.gallery
        result = self.matcher.match(queries.cpu())
        index = result.gallery_index.long()
        found = index >= 0
        safe = index.clamp_min(0)
        none = torch.full_like(index, -1)
        query_H_canon = compose_query_H_canon(result.query_H_anchor.double(), g.anchor_H_canon[safe].double())
        eye = torch.eye(3, dtype=torch.float64).expand_as(query_H_canon)
        return BaselinePrediction(
            gallery_index=torch.where(found, index, none),
            object_index=torch.where(found, g.object_index[safe], none),
            plane_index=torch.where(found, g.plane_index[safe], none),
            anchor_index=torch.where(found, g.anchor_index[safe], none),
            distance=torch.full((len(index),), math.nan, dtype=torch.float64),
            query_H_anchor=result.query_H_anchor.double(),
            query_H_canon=torch.where(found[:, None, None], query_H_canon, eye),
            warped=queries.cpu(),
            degenerate=torch.zeros(len(index), dtype=torch.bool),
            inliers=result.inliers.long(),
        )


def build_baseline(node: DictConfig, name: str) -> Any:
    """Instantiate ``conf/baseline/<name>.yaml``; any failure (missing weights, missing optional
    package) becomes a one-line :class:`MatlError`."""
    try:
        return hydra.utils.instantiate(node)
    except Exception as error:  # InstantiationException wraps the constructor's own error
        cause = error.__cause__ or error
        message = " ".join(str(cause).split()) or type(cause).__name__
        raise MatlError(f"baseline={name} cannot be built: {message}") from error
