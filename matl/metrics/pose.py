"""Recognition and pose metrics with the binding names of docs/design.md, as torchmetrics metrics.

Every metric takes the same ``update(pred_object, true_object, est_query_H_canon, true_query_H_canon)``
(``est_query_H_canon=None`` for recognition-only models, whose pose metrics are then NaN) and
keeps per-query records as ``cat`` states, so medians are exact and DDP gathers them.
"""

from __future__ import annotations

import math

import torch
from torchmetrics import Metric, MetricCollection

from matl.geometry import corner_error_px, frobenius_pose_error

REFERENCE_SIZE = 100  # pose_acc_5px's 5 px are at 100 px; the threshold scales with image size


class _PerQueryRecords(Metric):
    """Stores, per query, whether it was recognised and its two pose errors."""

    full_state_update = False
    higher_is_better: bool | None = None

    def __init__(self, image_size: int = 100, **kwargs) -> None:
        super().__init__(**kwargs)
        self.image_size = image_size
        self.add_state("correct", default=[], dist_reduce_fx="cat")
        self.add_state("frobenius", default=[], dist_reduce_fx="cat")
        self.add_state("corner", default=[], dist_reduce_fx="cat")

    def update(self, pred_object: torch.Tensor, true_object: torch.Tensor,
               est_query_H_canon: torch.Tensor | None, true_query_H_canon: torch.Tensor) -> None:
        size = (self.image_size, self.image_size)
        self.correct.append((pred_object == true_object).float())
        if est_query_H_canon is None:
            nan = torch.full((len(true_object),), math.nan, dtype=torch.float64, device=true_object.device)
            self.frobenius.append(nan)
            self.corner.append(nan)
            return
        self.frobenius.append(frobenius_pose_error(est_query_H_canon, true_query_H_canon, size))
        self.corner.append(corner_error_px(est_query_H_canon, true_query_H_canon, size))

    def _records(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        def cat(x: list[torch.Tensor] | torch.Tensor) -> torch.Tensor:
            return torch.cat(x) if isinstance(x, list) else x
        return cat(self.correct).bool(), cat(self.frobenius), cat(self.corner)


class RecognitionAccuracy(_PerQueryRecords):
    """``rec_acc``: fraction of queries whose nearest gallery anchor belongs to the query's object."""

    higher_is_better = True

    def compute(self) -> torch.Tensor:
        correct, _, _ = self._records()
        return correct.double().mean()


class PoseError(_PerQueryRecords):
    """``pose_err``: the paper's Frobenius error in normalised coordinates, correctly recognised queries only."""

    higher_is_better = False

    def compute(self) -> torch.Tensor:
        correct, frob, _ = self._records()
        return frob[correct].mean() if correct.any() else torch.tensor(math.nan, dtype=torch.float64)


class CornerError(_PerQueryRecords):
    """``corner_err_px``: mean (or median) corner distance in pixels, correctly recognised queries only."""

    higher_is_better = False

    def __init__(self, image_size: int = 100, reduction: str = "mean", **kwargs) -> None:
        super().__init__(image_size, **kwargs)
        if reduction not in ("mean", "median"):
            raise ValueError(f"reduction must be 'mean' or 'median', got {reduction!r}")
        self.reduction = reduction

    def compute(self) -> torch.Tensor:
        correct, _, corner = self._records()
        if not correct.any():
            return torch.tensor(math.nan, dtype=torch.float64)
        values = corner[correct]
        return values.mean() if self.reduction == "mean" else values.median()


class PoseAccuracy(_PerQueryRecords):
    """``pose_acc_5px``: fraction of *all* queries recognised with corner error below 5 px at 100 px."""

    higher_is_better = True

    def __init__(self, image_size: int = 100, threshold_px_at_100: float = 5.0, **kwargs) -> None:
        super().__init__(image_size, **kwargs)
        self.threshold = threshold_px_at_100 * image_size / REFERENCE_SIZE

    def compute(self) -> torch.Tensor:
        correct, _, corner = self._records()
        if torch.isnan(corner).all():
            return torch.tensor(math.nan, dtype=torch.float64)
        return (correct & (corner < self.threshold)).double().mean()


# The binding metric names, in report order; pose_metrics() builds exactly these.
METRIC_NAMES = ("rec_acc", "pose_err", "corner_err_px", "corner_err_px_median", "pose_acc_5px")
# The metrics that need an estimated pose (null for recognition-only models).
POSE_METRICS = tuple(name for name in METRIC_NAMES if name != "rec_acc")


def pose_metrics(image_size: int = 100, prefix: str = "") -> MetricCollection:
    """Every accuracy metric of :data:`METRIC_NAMES`, sharing one set of per-query records."""
    metrics = {
        "rec_acc": RecognitionAccuracy(image_size),
        "pose_err": PoseError(image_size),
        "corner_err_px": CornerError(image_size, "mean"),
        "corner_err_px_median": CornerError(image_size, "median"),
        "pose_acc_5px": PoseAccuracy(image_size),
    }
    assert tuple(metrics) == METRIC_NAMES
    return MetricCollection(metrics, prefix=prefix, compute_groups=[list(METRIC_NAMES)])
