"""What every trained matl model shares: evaluation against the gallery, metric logging, optimisers.

A subclass provides ``build_recognizer(gallery)`` (a :class:`~matl.models.prediction.QueryRecognizer`: maps a
query batch to a :class:`~matl.models.prediction.Prediction`) and its training step; validation and test then run
the metrics of docs/design.md the same way for every model, so their numbers are comparable.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import lightning as L
import torch

from matl.data.gallery import Gallery
from matl.metrics import pose_metrics
from matl.models.prediction import QueryRecognizer

#: val/score = sum of weight x metric over the metrics a model has (a model without pose has NaN pose
#: metrics; they drop out). Recognition and 5-px pose accuracy count alike: see docs/decisions.md.
DEFAULT_SCORE_WEIGHTS: dict[str, float] = {"rec_acc": 1.0, "pose_acc_5px": 1.0}


def weighted_score(values: Mapping[str, float | None], weights: Mapping[str, float], prefix: str = "") -> float:
    """``sum(weight x values[prefix + name])`` over the metrics that are defined (not None, not NaN).

    A model without pose (TL) has undefined pose metrics: they drop out instead of making the score NaN.
    """
    total = 0.0
    for name, weight in weights.items():
        value = values.get(f"{prefix}{name}")
        if value is not None and not math.isnan(value):
            total += float(weight) * float(value)
    return total


class PoseEvaluationModule(L.LightningModule):
    """Base LightningModule: gallery evaluation, ``val/score`` for checkpointing, optimisers.

    Args:
        image_size: model image side (metrics scale their pixel threshold with it).
        num_anchors: N anchors per plane in the evaluation gallery.
        optimizer / scheduler: partially-instantiated torch optimiser / LR scheduler factories.
        score_weights: ``{metric: weight}`` of ``val/score``, the checkpoint-selection score
            (metric names of docs/design.md without prefix; default: rec_acc + pose_acc_5px).
    """

    def __init__(self, image_size: int, num_anchors: int,
                 optimizer: Callable[..., torch.optim.Optimizer] | None = None,
                 scheduler: Callable[..., Any] | None = None,
                 score_weights: dict[str, float] | None = None) -> None:
        super().__init__()
        self.image_size, self.num_anchors = int(image_size), int(num_anchors)
        self.optimizer_factory, self.scheduler_factory = optimizer, scheduler
        self.val_metrics = pose_metrics(self.image_size, "val/")
        self.test_metrics = pose_metrics(self.image_size, "test/")
        self.score_weights = dict(DEFAULT_SCORE_WEIGHTS if score_weights is None else score_weights)
        known = [name.removeprefix("val/") for name in self.val_metrics]  # the metric names of docs/design.md
        unknown = sorted(set(self.score_weights) - set(known))
        if unknown or not self.score_weights:
            raise ValueError(f"model.score_weights: unknown or no metric {unknown}; use some of {known}")
        # held outside the module tree: its gallery features must not end up in checkpoints
        self._eval_cache: dict[str, QueryRecognizer] = {}
        self.eval_degenerate = 0
        self.run_config: dict | None = None  # the run's resolved Hydra config, saved into checkpoints

    def build_recognizer(self, gallery: Gallery) -> QueryRecognizer:
        raise NotImplementedError

    # -------------------------------------------------------------- evaluation
    def _gallery(self) -> Gallery:
        dm = self.trainer.datamodule if self._trainer is not None else None
        if dm is None or not hasattr(dm, "gallery"):
            raise RuntimeError("evaluation needs a datamodule with a gallery (TripletDataModule)")
        return dm.gallery

    def on_validation_epoch_start(self) -> None:
        self._eval_cache["recognizer"] = self.build_recognizer(self._gallery())
        self.eval_degenerate = 0

    def on_test_epoch_start(self) -> None:
        self._eval_cache["recognizer"] = self.build_recognizer(self._gallery())
        self.eval_degenerate = 0

    def _evaluate(self, batch: dict[str, torch.Tensor], metrics: Any) -> None:
        pred = self._eval_cache["recognizer"](batch["query"])
        self.eval_degenerate += int(pred.degenerate.sum())  # queries whose STN output was replaced by identity
        metrics.update(pred.object_index, batch["object"], pred.query_H_canon, batch["query_H_canon"].double())

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        self._evaluate(batch, self.val_metrics)

    def test_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        self._evaluate(batch, self.test_metrics)

    def _log_metrics(self, metrics: Any, prefix: str) -> dict[str, float]:
        values = {k: float(v) for k, v in metrics.compute().items()}
        metrics.reset()
        # A model without pose (TL) has NaN pose metrics: they are not logged and drop out of the score.
        values[f"{prefix}score"] = weighted_score(values, self.score_weights, prefix)
        self.log_dict({k: v for k, v in values.items() if not math.isnan(v)}, prog_bar=True)
        return values

    def on_validation_epoch_end(self) -> None:
        self._log_metrics(self.val_metrics, "val/")
        self.log("val/degenerate_stn", float(self.eval_degenerate))  # this validation's queries

    def on_test_epoch_end(self) -> None:
        self.test_results = self._log_metrics(self.test_metrics, "test/")

    # -------------------------------------------------------------- plumbing
    def optimizer_param_groups(self) -> Any:
        """What the optimiser is built over: the parameters, or param groups (a group's ``lr_scale``
        multiplies the configured learning rate for it, before the scheduler starts)."""
        return self.parameters()

    def configure_optimizers(self) -> Any:
        if self.optimizer_factory is None:
            raise ValueError("model.optimizer is not set")
        optimizer = self.optimizer_factory(params=self.optimizer_param_groups())
        for group in optimizer.param_groups:  # a group may run at a multiple of the configured rate
            group["lr"] = group["lr"] * float(group.get("lr_scale", 1.0))
        if self.scheduler_factory is None:
            return optimizer
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": self.scheduler_factory(optimizer=optimizer),
                                                          "interval": "epoch"}}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # plain containers only, so the checkpoint loads with torch.load(weights_only=True)
        if self.run_config is not None:
            checkpoint["matl_config"] = self.run_config
        checkpoint["matl_image_size"] = self.image_size
        checkpoint["matl_num_anchors"] = self.num_anchors
