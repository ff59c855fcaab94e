"""The MATL LightningModule (paper Fig. 1(b), Eq. 5 / Eq. 8).

One module covers the paper's trained variants through its switches:
``num_anchors=1`` is the single-anchor method [28] (row a), ``stn=None`` is TL (row b),
``lam=0`` is row (g), ``stn_on_negative=False`` is row (i), ``metric_loss=NCELoss`` is row (j).
Beyond the paper, and off in its rows: ``align`` (an anchor-conditioned alignment stage after ``s()``,
:mod:`matl.models.align`) and ``appearance_mask="foreground"`` (the appearance loss over the anchor's
foreground only).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import nn

from matl.data.gallery import Gallery
from matl.geometry import pixel_to_normalised, sample_by_normalised_kornia, warp_image
from matl.losses import MultiAnchorAppearanceLoss, appearance_distance
from matl.models.align import AlignmentStage
from matl.models.evaluation import PoseEvaluationModule
from matl.models.feature import FeatureNet
from matl.models.recognizer import TensorRecognizer
from matl.models.stn import SpatialTransformer
from matl.utils.errors import MatlError, NonFiniteLossError


class MATLModule(PoseEvaluationModule):
    """Multiple-anchor triplet learning of canonical planes.

    Args:
        feature_net: ``c()``.
        stn: ``s()``, or None for plain triplet learning (TL).
        metric_loss: triplet (Eq. 7) or NCE (Eq. 9) loss with the uniform metric-loss signature.
        lam: weight of the appearance loss (paper: 10).
        num_anchors: N (checked against the data).
        stn_on_negative: pass negatives through ``s()`` (paper: yes; row i: no).
        num_negatives: M negatives per positive. 1 uses the triplet's own negative; M > 1 draws
            M negatives from the batch's negatives and the positives and selected anchors of
            *other* objects (needs ``3 * batch_size - 2 >= M``; our decision, so NCE costs no
            extra images).
        optimizer / scheduler: partially-instantiated torch optimiser / LR scheduler factories.
        image_size: model image side.
        anchor_choice: see :class:`TensorRecognizer`.
        appearance_levels: pyramid levels of the appearance loss (paper: 1; see ``appearance_distance``).
        appearance: ``forward`` is Eq. 4, ``||I^a_* - s(I^p)||_1``. ``symmetric`` (beyond the paper)
            averages it with the backward term ``||I^p - s^-1(I^a_*)||_1`` (the selected anchor
            warped into the positive's frame). With black backgrounds the forward term alone
            rewards shrinking a misaligned object (less non-overlap); the backward term pays for
            it, which removes that attractor. Selection (Eq. 3) always uses the forward term.
        align: the alignment stage (:class:`~matl.models.align.AlignmentStage`), or None (paper, the
            default): after Eq. 3 selects the anchor, the stage refines ``query_H_anchor`` against it and
            the appearance loss of the final homography (``appearance`` and ``appearance_mask`` as for
            ``s()``) is added to ``s()``'s own: ``loss = metric + lam * (L_app(s) + L_app(stage))``.
            Recognition still uses ``c(s(query))``; the stage runs after the search
            (:class:`~matl.models.recognizer.TensorRecognizer`).
        appearance_mask: ``none`` (paper) or ``foreground`` (beyond the paper): every appearance term
            is averaged over the anchor's foreground only, ``batch["anchor_masks"]`` ``(B, N, 1, S, S)``
            (when a batch has none, ``anchors.amax(dim=2, keepdim=True) > 0``: the data's background is
            exactly 0). The forward term and Eq. 3 use each anchor's own mask; the backward term uses the
            selected anchor's mask warped into the positive's frame by the predicted homography (no
            mask of the positive is used), so background behind a query costs nothing. Every term is a
            mean over the image area (no division by a mask, :func:`~matl.losses.appearance_distance`), so
            ``lam`` keeps its scale and no gradient grows as a warped mask shrinks; Eq. 3 compares the
            anchors per unit of their own foreground. Measured (docs/decisions.md): trains finitely, but with
            ``augment=camera`` the pose still drifts towards zooming into the positive (nothing outside the
            anchor's foreground pays for it), so it stays off.
    """

    def __init__(self, feature_net: FeatureNet, stn: SpatialTransformer | None, metric_loss: nn.Module,
                 lam: float = 10.0, num_anchors: int = 4, stn_on_negative: bool = True, num_negatives: int = 1,
                 optimizer: Callable[..., torch.optim.Optimizer] | None = None,
                 scheduler: Callable[..., Any] | None = None, image_size: int = 100,
                 anchor_choice: str = "feature", appearance_levels: int = 1,
                 appearance: str = "forward", score_weights: dict[str, float] | None = None,
                 align: AlignmentStage | None = None, appearance_mask: str = "none") -> None:
        super().__init__(image_size, num_anchors, optimizer, scheduler, score_weights)
        if lam < 0:
            raise ValueError(f"lam must be >= 0, got {lam}")
        if appearance not in ("forward", "symmetric"):
            raise ValueError(f"model.appearance must be 'forward' or 'symmetric', got {appearance!r}")
        if num_negatives < 1:
            raise ValueError(f"M (loss.num_negatives) must be >= 1, got {num_negatives}")
        if appearance_mask not in ("none", "foreground"):
            raise MatlError(f"model.appearance_mask={appearance_mask!r} is invalid: use none (paper) or foreground")
        if align is not None and stn is None:
            raise MatlError("model.align needs an STN to refine (model=tl has none): drop model/align")
        if align is not None and int(getattr(align, "image_size", image_size)) != int(image_size):
            raise MatlError(f"model.align.image_size={align.image_size} differs from the model's {image_size}")
        self.feature_net, self.stn, self.metric_loss = feature_net, stn, metric_loss
        self.appearance_loss = MultiAnchorAppearanceLoss(appearance_levels)
        self.lam = float(lam)
        self.stn_on_negative, self.num_negatives = stn_on_negative, int(num_negatives)
        self.anchor_choice = anchor_choice
        self.appearance, self.appearance_levels = appearance, appearance_levels
        self.align, self.appearance_mask = align, appearance_mask
        # a stage with an optimiser of its own: this module steps the two optimisers itself
        self.automatic_optimization = getattr(align, "optimizer_factory", None) is None
        self.degenerate_count = 0  # training STN outputs replaced by identity, whole run (kept across resumes)

    # ---------------------------------------------------------------- training
    def transform(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``s(images)`` and the pixel ``query_H_anchor`` (identity / None without an STN)."""
        if self.stn is None:
            return images, None
        out = self.stn(images)
        if out.degenerate.any():
            self.degenerate_count += int(out.degenerate.sum())
        return out.warped, out.query_H_anchor

    def _negative_pool(self, emb_anchor: torch.Tensor, emb_pos: torch.Tensor, emb_neg: torch.Tensor,
                       obj: torch.Tensor, neg_obj: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``(B, M, D)`` negatives and their validity mask (see ``num_negatives``).

        The pool is every embedding the step already computed: the B negatives, and the positives
        and selected anchors of the *other* objects in the batch (up to 3B - 2 per row). A row
        with fewer valid candidates than M gets masked slots, which both losses ignore.
        """
        if self.num_negatives == 1:
            return emb_neg[:, None], None
        pool = torch.cat([emb_neg, emb_pos, emb_anchor])           # (3B, D)
        pool_obj = torch.cat([neg_obj, obj, obj])                  # (3B,)
        valid = pool_obj[None, :] != obj[:, None]                  # (B, 3B)
        M = min(self.num_negatives, pool.shape[0])
        # a random valid subset of size M per row: rank random scores, invalid ones last
        scores = torch.rand(valid.shape, device=pool.device).masked_fill(~valid, -1.0)
        idx = scores.topk(M, dim=1).indices                        # (B, M)
        return pool[idx], valid.gather(1, idx)

    @staticmethod
    def anchor_masks(batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """``(B, N, 1, S, S)`` float foreground of every anchor: ``batch["anchor_masks"]``, or where a batch
        has none, the pixels of an anchor that are not exactly 0 in every channel."""
        anchors = batch["anchors"]
        masks = batch.get("anchor_masks")
        if masks is None:
            return (anchors.amax(dim=2, keepdim=True) > 0).to(anchors.dtype)
        expected = (*anchors.shape[:2], 1, *anchors.shape[-2:])
        if tuple(masks.shape) != expected:
            raise ValueError(f"batch['anchor_masks'] must be {expected} for anchors {tuple(anchors.shape)}, "
                             f"got {tuple(masks.shape)}")
        return masks.to(anchors.dtype)

    def backward_appearance(self, anchor: torch.Tensor, positive: torch.Tensor, query_H_anchor: torch.Tensor,
                            mask: torch.Tensor | None) -> torch.Tensor:
        """The backward term ``||I^p - s^-1(I^a_*)||_1`` (a scalar): the anchors ``(B, 3, S, S)`` warped into
        the positives' frame by the pixel ``query_H_anchor`` ``(B, 3, 3)``, against the positives ``(B, 3, S, S)``;
        with ``mask`` ``(B, 1, S, S)`` over the anchors' foreground warped the same way."""
        anchor_in_query = warp_image(anchor, query_H_anchor)
        mask_in_query = warp_image(mask, query_H_anchor) if mask is not None else None
        return appearance_distance(anchor_in_query, positive, self.appearance_levels, mask_in_query).mean()

    def warp_target(self, target: torch.Tensor, query_H_anchor: torch.Tensor | None) -> torch.Tensor:
        """``target`` ``(B, 3, S, S)`` (the un-occluded positives) brought into the anchors' frame by the pixel
        ``query_H_anchor`` ``(B, 3, 3)`` that ``s()`` regressed from the occluded ones, with ``s()``'s own sampler
        (the target itself without an STN)."""
        if query_H_anchor is None:
            return target
        size = target.shape[-2:]
        return sample_by_normalised_kornia(target, pixel_to_normalised(query_H_anchor, (size[0], size[1])))

    def pair_appearance(self, anchor: torch.Tensor, positive: torch.Tensor, warped: torch.Tensor,
                        query_H_anchor: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """The appearance loss of one anchor per positive under a predicted homography (a scalar): the
        forward term (Eq. 4) of ``anchor`` against ``warped`` (the positives warped into the anchors' frame
        by ``query_H_anchor``), with ``appearance=symmetric`` averaged with :meth:`backward_appearance`;
        over ``mask`` (the anchors' foreground) when given. Shapes as in :meth:`backward_appearance`."""
        loss = appearance_distance(anchor, warped, self.appearance_levels, mask).mean()
        if self.appearance == "symmetric":
            loss = 0.5 * (loss + self.backward_appearance(anchor, positive, query_H_anchor, mask))
        return loss

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        loss = self.training_loss(batch)
        if not self.automatic_optimization:  # the model and the alignment stage, each its own optimiser
            optimizers = self.optimizers()
            for optimizer in optimizers:
                optimizer.zero_grad()
            self.manual_backward(loss)
            for optimizer in optimizers:
                optimizer.step()
        return loss

    def on_train_epoch_end(self) -> None:
        if not self.automatic_optimization:  # Lightning steps no scheduler under manual optimisation
            for scheduler in self.lr_schedulers() or []:  # None, or one per optimiser (configure_optimizers)
                scheduler.step()

    def training_loss(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The training loss of a batch (metric loss + ``lam`` x appearance), logged."""
        anchors, positive, negative = batch["anchors"], batch["positive"], batch["negative"]
        if anchors.shape[1] != self.num_anchors:
            raise ValueError(f"batch has {anchors.shape[1]} anchors per plane but the model was built "
                             f"for N={self.num_anchors}")
        degenerate_before = self.degenerate_count
        warped_pos, query_H_anchor = self.transform(positive)
        # an occluded positive (data.occlude) is posed from what is visible, its pose judged on the whole product
        target = batch.get("positive_target")
        warped_target = warped_pos if target is None else self.warp_target(target, query_H_anchor)
        target = positive if target is None else target
        masks = self.anchor_masks(batch) if self.appearance_mask == "foreground" else None
        loss_app, selected = self.appearance_loss(anchors, warped_target, masks)
        rows = torch.arange(len(anchors), device=anchors.device)
        anchor_star = anchors[rows, selected]
        mask_star = masks[rows, selected] if masks is not None else None
        if self.appearance == "symmetric" and query_H_anchor is not None:
            loss_app = 0.5 * (loss_app + self.backward_appearance(anchor_star, target, query_H_anchor, mask_star))
        loss_align = None
        if self.align is not None and query_H_anchor is not None:
            aligned = self.align(positive, anchor_star, query_H_anchor, warped_pos)
            aligned_target = aligned.warped if target is positive else self.warp_target(target, aligned.query_H_anchor)
            loss_align = self.pair_appearance(anchor_star, target, aligned_target, aligned.query_H_anchor,
                                              mask_star)
        warped_neg = self.transform(negative)[0] if self.stn_on_negative else negative
        emb = self.feature_net(torch.cat([anchor_star, warped_pos, warped_neg]))
        emb_a, emb_p, emb_n = emb.chunk(3)
        negatives, mask = self._negative_pool(emb_a, emb_p, emb_n, batch["object"], batch["neg_object"])
        loss_metric = self.metric_loss(emb_a, emb_p, negatives, mask)
        appearance = loss_app if loss_align is None else loss_app + loss_align
        loss = loss_metric + self.lam * appearance if self.stn is not None else loss_metric
        if not torch.isfinite(loss):  # stop instead of training on (and checkpointing) NaN weights
            raise NonFiniteLossError(
                f"training loss became {loss.item()} at epoch {self.current_epoch}, step {self.global_step} "
                f"(metric {loss_metric.item():.4g}, appearance {appearance.item():.4g}): lower model.optimizer.lr "
                "or lam; checkpoints/last.ckpt holds the last good state")
        B = len(anchors)
        # STN outputs replaced by identity (matl.geometry.guard_homographies), summed over the epoch
        self.log("train/degenerate_stn", float(self.degenerate_count - degenerate_before), on_step=False,
                 on_epoch=True, reduce_fx="sum", batch_size=B)
        self.log_dict({"train/loss": loss, "train/appearance": loss_app, "train/metric": loss_metric},
                      prog_bar=True, batch_size=B)
        self.log("train/selected_anchor_mean", selected.float().mean(), batch_size=B)
        if loss_align is not None:
            self.log("train/appearance_align", loss_align, batch_size=B)
        return loss

    def optimizer_param_groups(self) -> Any:
        """All parameters in one group; with an alignment stage its parameters form a second group at
        ``align.lr_scale`` times the learning rate (a fresh network refining a pose that ``s()`` already
        brought close gets small gradients), or, when the stage has an optimiser of its own, are left
        to it."""
        if self.align is None:
            return self.parameters()
        stage = {id(p) for p in self.align.parameters()}
        rest = [p for p in self.parameters() if id(p) not in stage]
        if not self.automatic_optimization:
            return rest
        return [{"params": rest}, {"params": list(self.align.parameters()),
                                   "lr_scale": float(getattr(self.align, "lr_scale", 1.0))}]

    def configure_optimizers(self) -> Any:
        """The model's optimiser (and scheduler); with a stage that has its own optimiser, both, the
        scheduler applied to each."""
        config = super().configure_optimizers()
        if self.automatic_optimization:
            return config
        stage = self.align.optimizer_factory(params=self.align.parameters())
        if not isinstance(config, dict):
            return [config, stage]
        main = config["optimizer"]
        return ([main, stage], [{"scheduler": config["lr_scheduler"]["scheduler"], "interval": "epoch"},
                                {"scheduler": self.scheduler_factory(optimizer=stage), "interval": "epoch"}])

    # -------------------------------------------------------------- evaluation
    def build_recognizer(self, gallery: Gallery) -> TensorRecognizer:
        was_training = self.training
        self.eval()
        rec = TensorRecognizer(self.feature_net, self.stn, gallery.to(self.device), self.anchor_choice,
                               align=self.align)
        self.train(was_training)
        return rec

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_save_checkpoint(checkpoint)
        checkpoint["matl_degenerate_count"] = self.degenerate_count

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        self.degenerate_count = int(checkpoint.get("matl_degenerate_count", 0))  # a resumed run keeps counting
