"""Table 1 row (c): the original STN [15] as a classifier, trained with cross-entropy (paper Sec. 5.4).

"For a fair comparison, the existing STN is constructed to have the same configuration as our
network": the same spatial transformer ``s()`` as MATL, then the same conv trunk as ``c()`` (2 conv,
a max pool and a global max pool: the paper's "two max pooling layers"), then 2 FC layers giving
one logit per *object*. It is trained on the positives of the triplets with their object labels;
anchors, negatives and the appearance loss are not used (the original STN has no such signal).

Recognition is ``argmax`` over objects. The classifier names no gallery entry, but the pose
metrics need one anchor to compose the STN's ``query_H_anchor`` with. Our choice (documented in
``docs/decisions.md``): within the predicted object's planes, the gallery anchor whose appearance
(mean L1, Eq. 1) is closest to ``s(query)``, which is the selection layer (Eq. 3) applied at test
time to the recognised object. The pose is then ``query_H_anchor @ anchor_H_canon`` of that anchor.

The number of classes is the number of objects of the training data, known only once the data is
set up: the last FC layer is created in Lightning's ``setup`` hook (:meth:`attach_data`), before the
optimiser and before any checkpoint is loaded. Checkpoints record the class names
(``matl_class_names``) so a classifier is never evaluated against a gallery of other objects.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from matl.data.gallery import Gallery
from matl.geometry import check_images, compose_query_H_canon
from matl.losses import appearance_distance
from matl.models.evaluation import PoseEvaluationModule
from matl.models.feature import FeatureNet
from matl.models.prediction import Prediction
from matl.models.stn import SpatialTransformer
from matl.utils.errors import NonFiniteLossError

# Elements of the (queries, candidates, 3, S, S) block compared at once when choosing the anchor:
# 8M floats = 32 MB whatever the image size and gallery.
_APPEARANCE_BLOCK = 8_000_000


class ClassifierRecognizer:
    """Answers class and pose for query batches with an :class:`STNClassifierModule`.

    A plain callable, not an ``nn.Module``: a registered submodule would put duplicate weights
    into every checkpoint.

    Args:
        model: the classifier (its ``stn`` and ``logits``).
        gallery: the reference gallery; ``gallery.object_index`` must use the classifier's class
            indices (the same objects in the same order, as in evaluation on the training data).
    """

    def __init__(self, model: STNClassifierModule, gallery: Gallery) -> None:
        self.stn, self.classify = model.stn, model.logits
        self.gallery = gallery
        num_classes = model.num_classes
        counts = torch.bincount(gallery.object_index.cpu(), minlength=num_classes)
        if len(counts) > num_classes or (counts[:num_classes] == 0).any():
            raise ValueError(f"the gallery's objects ({len(counts)}) do not match the classifier's "
                             f"{num_classes} classes")
        # candidates[c] = gallery indices of object c, padded with -1: (C, K_max)
        k_max = int(counts.max())
        candidates = torch.full((num_classes, k_max), -1, dtype=torch.long)
        for c in range(num_classes):
            index = torch.nonzero(gallery.object_index.cpu() == c).flatten()
            candidates[c, :len(index)] = index
        self.candidates = candidates.to(gallery.images.device)

    @torch.no_grad()
    def __call__(self, queries: torch.Tensor) -> Prediction:
        """``(Q, 3, S, S)`` queries -> :class:`Prediction`; ``distance`` is the mean L1 appearance
        distance between ``s(query)`` and the chosen anchor (the classifier has no feature distance)."""
        g = self.gallery
        check_images(queries, "queries", (g.image_size, g.image_size))
        out = self.stn(queries)
        warped = out.warped
        objects = self.classify(warped).argmax(dim=1)                     # (Q,)
        candidates = self.candidates[objects]                                  # (Q, K)
        valid = candidates >= 0
        per_query = candidates.shape[1] * warped[0].numel()
        step = max(1, _APPEARANCE_BLOCK // max(per_query, 1))
        distances = torch.cat([
            appearance_distance(g.images[candidates[i:i + step].clamp_min(0)], warped[i:i + step, None])
            for i in range(0, len(queries), step)
        ]).masked_fill(~valid, math.inf)                                       # (Q, K)
        distance, best = distances.min(dim=1)
        index = candidates.gather(1, best[:, None])[:, 0]
        query_H_canon = compose_query_H_canon(out.query_H_anchor.double(), g.anchor_H_canon[index].double())
        return Prediction(index, g.object_index[index], g.plane_index[index], g.anchor_index[index], distance,
                          out.query_H_anchor, query_H_canon, warped, out.degenerate)


class STNClassifierModule(PoseEvaluationModule):
    """``s()`` + conv trunk + 2 FC, cross-entropy on object labels (Table 1 row c).

    Args:
        stn: the spatial transformer (same config as MATL's).
        trunk: the conv trunk, ``(B, 3, S, S) -> (B, D)`` (a :class:`FeatureNet`, unnormalised).
        hidden: width of the first FC layer.
        num_classes: number of objects; None takes it from the data in ``setup``.
        num_anchors: N anchors per plane of the evaluation gallery (used for the pose only).
        image_size: model image side.
        optimizer / scheduler: partially-instantiated torch optimiser / LR scheduler factories.
        score_weights: weights of the checkpoint-selection ``val/score`` (see PoseEvaluationModule).
    """

    def __init__(self, stn: SpatialTransformer, trunk: FeatureNet, hidden: int = 128,
                 num_classes: int | None = None, num_anchors: int = 4, image_size: int = 100,
                 optimizer: Callable[..., torch.optim.Optimizer] | None = None,
                 scheduler: Callable[..., Any] | None = None,
                 score_weights: dict[str, float] | None = None) -> None:
        if num_anchors < 1:
            raise ValueError(f"N (number of anchors) must be >= 1, got {num_anchors}")
        super().__init__(image_size, num_anchors, optimizer, scheduler, score_weights)
        self.stn, self.trunk = stn, trunk
        self.fc1 = nn.Linear(trunk.embedding_dim, hidden)
        self.fc2: nn.Linear | None = None
        self.class_names: list[str] | None = None
        if num_classes is not None:
            self._build_output(int(num_classes))
        self.degenerate_count = 0

    # ------------------------------------------------------------- classes
    @property
    def num_classes(self) -> int:
        if self.fc2 is None:
            raise RuntimeError("the classifier has no classes yet: call attach_data(datamodule) first")
        return int(self.fc2.out_features)

    def _build_output(self, num_classes: int) -> None:
        if num_classes < 2:
            raise ValueError(f"a classifier needs at least 2 objects, got {num_classes}")
        self.fc2 = nn.Linear(self.fc1.out_features, num_classes).to(self.fc1.weight.device)

    def attach_classes(self, names: list[str]) -> None:
        """Create (or check) the output layer for these object names, in class-index order."""
        if self.fc2 is None:
            self._build_output(len(names))
        elif self.num_classes != len(names):
            raise ValueError(f"the classifier has {self.num_classes} classes but the data has {len(names)} objects")
        self.class_names = list(names)

    def attach_data(self, datamodule: Any) -> None:
        """Classes = the objects of a set-up datamodule (its gallery's ``object_names``)."""
        self.attach_classes(list(datamodule.gallery.object_names))

    def setup(self, stage: str) -> None:
        datamodule = self.trainer.datamodule if self._trainer is not None else None
        if datamodule is not None and hasattr(datamodule, "gallery"):
            self.attach_data(datamodule)

    # -------------------------------------------------------------- forward
    def logits(self, warped: torch.Tensor) -> torch.Tensor:
        """Class logits of already-transformed images: ``(B, 3, S, S) -> (B, C)``."""
        if self.fc2 is None:
            raise RuntimeError("the classifier has no classes yet: call attach_data(datamodule) first")
        return self.fc2(F.relu(self.fc1(self.trunk(warped))))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """``(B, 3, S, S) -> (B, C)`` logits of ``classifier(s(images))``."""
        return self.logits(self.stn(images).warped)

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        out = self.stn(batch["positive"])
        if out.degenerate.any():
            self.degenerate_count += int(out.degenerate.sum())
        logits = self.logits(out.warped)
        loss = F.cross_entropy(logits, batch["object"])
        if not torch.isfinite(loss):
            raise NonFiniteLossError(f"training loss became {loss.item()} at epoch {self.current_epoch}, step "
                                     f"{self.global_step}: lower model.optimizer.lr; checkpoints/last.ckpt holds "
                                     "the last good state")
        B = len(logits)
        accuracy = (logits.argmax(1) == batch["object"]).float().mean()
        self.log_dict({"train/loss": loss, "train/acc": accuracy}, prog_bar=True, batch_size=B)
        return loss

    # ----------------------------------------------------------- evaluation
    def build_recognizer(self, gallery: Gallery) -> ClassifierRecognizer:
        was_training = self.training
        self.eval()
        recognizer = ClassifierRecognizer(self, gallery.to(self.device))
        self.train(was_training)
        return recognizer

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_save_checkpoint(checkpoint)
        if self.class_names is not None:
            checkpoint["matl_class_names"] = list(self.class_names)
