"""The visibility network: which pixels of an RGB crop show the visible print of the crop's target product.

A camera crop (a detector's box) holds one target product, but also background, neighbouring
products behind it that the box's edge cuts, and occluders in front of it (another product, the
gripper). :class:`VisibilityNet` predicts, per pixel, the logit of "this pixel shows the target's
visible print"; everything else is out. It replaces GrabCut as the foreground step of RGB queries
(``foreground=learned``, :class:`matl.inference.foreground.LearnedForeground`), and its soft
probability is what verification and refinement can weigh by.

The crop is resized to a square working size ``S`` (``size``, default 64) and each image
standardised per channel (:class:`~matl.models.feature.ChannelStandardize`: the gain, black level
and white balance of a camera cancel); two constant coordinate channels (x and y in [-1, 1]) tell
the network where the crop's centre is, since the target is the product the box is centred on.
Then a small encoder-decoder:

* encoder: three 3x3 convolutions of stride 2 (``S/2``, ``S/4``, ``S/8``; ``channels``), each with batch
  norm and ReLU;
* context at ``S/8``: 3x3 convolutions with ``dilations`` (a receptive field over the whole crop), plus a
  global-context term (the map's mean through a 1x1 convolution, added everywhere): whether a region
  is the centred product or a neighbour cut by the edge is a question about the whole crop;
* decoder: bilinear upsampling by 2 with the encoder's map of that size concatenated (skip
  connections) and a 3x3 convolution, back to ``S/2``; a 1x1 convolution to one logit, upsampled
  bilinearly to ``S``; or, with ``full_channels`` > 0 (the shipped network: 8), upsampled to ``S`` first,
  the input concatenated and one more 3x3 convolution of that width before the 1x1 logit, so the mask's
  edge is decided at the working size.

Batch norm folds into the convolutions in an exported graph (eval mode), so the ONNX graph is
convolutions, ReLUs, resizes and concatenations only.

:class:`VisibilityModule` trains it (binary cross-entropy plus soft Dice on the logits against the
visible mask; intersection over union on validation scenes), ``python -m matl.train_foreground``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
import torch.nn.functional as F
from torch import nn

from matl.models.feature import ChannelStandardize
from matl.utils.errors import MatlError

__all__ = ["FOREGROUND_WEIGHTS", "VISIBILITY_FORMAT", "VisibilityModule", "VisibilityNet", "dice_loss",
           "load_visibility_net", "mask_iou", "visibility_loss"]

#: the visibility network shipped inside the package (``foreground=learned``'s default weights)
FOREGROUND_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "matl_foreground.ckpt"
#: the format of a published visibility checkpoint (``python -m matl.train_foreground publish=...``)
VISIBILITY_FORMAT = 1


def _block(in_channels: int, out_channels: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    """conv 3x3 (no bias) -> batch norm -> ReLU."""
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 3, stride, padding=dilation, dilation=dilation,
                                   bias=False),
                         nn.BatchNorm2d(out_channels), nn.ReLU(inplace=True))


class VisibilityNet(nn.Module):
    """``(B, 3, S, S)`` RGB in [0, 1] -> ``(B, 1, S, S)`` logits of the target's visible print (module docstring).

    Args:
        size: the working size ``S`` (a multiple of 8): crops are resized to ``S x S`` before the network.
        channels: the encoder's channels at ``S/2``, ``S/4`` and ``S/8``.
        dilations: dilations of the context convolutions at ``S/8`` (each a 3x3 convolution).
        global_context: add the map's mean, through a 1x1 convolution, to the context.
        coordinates: feed the two coordinate channels (x, y in [-1, 1]).
        full_channels: width of a last 3x3 stage at the full working size (0: none, logits at ``S/2`` upsampled).
    """

    def __init__(self, size: int = 64, channels: Sequence[int] = (16, 24, 32), dilations: Sequence[int] = (2, 4),
                 global_context: bool = True, coordinates: bool = True, full_channels: int = 0) -> None:
        super().__init__()
        size, channels, dilations = int(size), [int(c) for c in channels], [int(d) for d in dilations]
        if size < 16 or size % 8:
            raise ValueError(f"visibility net: size={size} must be a multiple of 8, at least 16")
        if len(channels) != 3 or min(channels) < 1 or any(d < 1 for d in dilations):
            raise ValueError(f"visibility net: channels={channels} must be 3 positive widths and "
                             f"dilations={dilations} positive")
        self.size = size
        self.config = {"size": size, "channels": channels, "dilations": dilations,
                       "global_context": bool(global_context), "coordinates": bool(coordinates),
                       "full_channels": int(full_channels)}
        self.standardize = ChannelStandardize()
        inputs = 3
        if coordinates:
            axis = torch.linspace(-1.0, 1.0, size)
            grid = torch.stack([axis[None, :].expand(size, size), axis[:, None].expand(size, size)])
            self.register_buffer("coords", grid[None].contiguous(), persistent=False)  # (1, 2, S, S)
            inputs += 2
        else:
            self.coords = None
        c1, c2, c3 = channels
        self.enc1, self.enc2, self.enc3 = _block(inputs, c1, 2), _block(c1, c2, 2), _block(c2, c3, 2)
        self.context = nn.Sequential(*[_block(c3, c3, dilation=d) for d in dilations])
        self.global_context = nn.Conv2d(c3, c3, 1) if global_context else None
        self.dec2, self.dec1 = _block(c3 + c2, c2), _block(c2 + c1, c1)
        self.full = _block(c1 + inputs, int(full_channels)) if int(full_channels) > 0 else None
        self.head = nn.Conv2d(int(full_channels) if self.full is not None else c1, 1, 1)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """``images`` ``(B, 3, S, S)`` in [0, 1] -> logits ``(B, 1, S, S)``."""
        if images.ndim != 4 or images.shape[1] != 3 or images.shape[2] != self.size or images.shape[3] != self.size:
            raise ValueError(f"visibility net: images must be (B, 3, {self.size}, {self.size}), "
                             f"got {tuple(images.shape)}")
        x = self.standardize(images)
        if self.coords is not None:
            x = torch.cat([x, self.coords.expand(images.shape[0], -1, -1, -1)], 1)
        e1 = self.enc1(x)           # (B, c1, S/2, S/2)
        e2 = self.enc2(e1)          # (B, c2, S/4, S/4)
        e3 = self.enc3(e2)          # (B, c3, S/8, S/8)
        c = self.context(e3)
        if self.global_context is not None:
            c = c + F.relu(self.global_context(c.mean(dim=(2, 3), keepdim=True)))
        d2 = self.dec2(torch.cat([_up(c), e2], 1))    # (B, c2, S/4, S/4)
        d1 = self.dec1(torch.cat([_up(d2), e1], 1))   # (B, c1, S/2, S/2)
        if self.full is None:
            return _up(self.head(d1))                  # (B, 1, S, S)
        return self.head(self.full(torch.cat([_up(d1), x], 1)))  # (B, 1, S, S)


def _up(x: torch.Tensor) -> torch.Tensor:
    """Bilinear upsampling by 2 (half-pixel centres)."""
    return F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)


def load_visibility_net(path: str | Path | None = None, size: int | None = None) -> VisibilityNet:
    """The network of a published visibility checkpoint (``None``: :data:`FOREGROUND_WEIGHTS`), in eval mode, read
    with ``torch.load(weights_only=True)``; ``size`` runs the same weights at another working size (None: its own).

    Raises:
        MatlError: a missing or unreadable file, or one that is not a visibility checkpoint.
    """
    path = FOREGROUND_WEIGHTS if path is None else Path(path).expanduser()
    if not path.is_file():
        raise MatlError(f"foreground learned: weights {path} not found: train them with python -m "
                        "matl.train_foreground publish=shipped (or publish=<file> and foreground.weights=<file>)")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # not a torch file, or one that needs unpickling
        raise MatlError(f"foreground learned: weights {path} cannot be read safely (weights_only=True): "
                        f"{' '.join(str(error).split())[:200]}") from error
    if not isinstance(ckpt, dict) or ckpt.get("format") != VISIBILITY_FORMAT or "matl_visibility" not in ckpt:
        raise MatlError(f"foreground learned: {path} is not a visibility checkpoint of format {VISIBILITY_FORMAT} "
                        "(python -m matl.train_foreground publish=<file> writes one)")
    config = dict(ckpt["matl_visibility"])
    if size is not None:
        config["size"] = int(size)
    try:
        net = VisibilityNet(**config)
        net.load_state_dict(ckpt["state_dict"])
    except (TypeError, ValueError, RuntimeError) as error:
        raise MatlError(f"foreground learned: {path} does not fit the visibility network: "
                        f"{' '.join(str(error).split())[:200]}") from error
    return net.eval()


# ------------------------------------------------------------------------------------------ losses
def dice_loss(logits: torch.Tensor, target: torch.Tensor, eps: float = 1.0) -> torch.Tensor:
    """Soft Dice loss ``1 - 2|p t| / (|p| + |t|)`` per image, averaged: ``(B, 1, S, S)`` logits and targets in
    [0, 1] -> a scalar. ``eps`` (in pixels) keeps an image without target defined."""
    p = torch.sigmoid(logits).flatten(1)
    t = target.flatten(1)
    return (1.0 - (2.0 * (p * t).sum(1) + eps) / (p.sum(1) + t.sum(1) + eps)).mean()


def visibility_loss(logits: torch.Tensor, target: torch.Tensor, dice_weight: float = 1.0,
                    negative_weight: float = 1.0, occluder_weight: float = 1.0,
                    covered: torch.Tensor | None = None) -> torch.Tensor:
    """Binary cross-entropy (soft targets: a pixel's visible coverage) plus ``dice_weight`` x :func:`dice_loss`.

    A pixel's cross-entropy counts ``1 + (negative_weight - 1) (1 - target) + (occluder_weight - 1) hidden`` times
    (the batch's mean weight divides the sum), ``hidden = max(covered - target, 0)`` the target's coverage that an
    occluder hides (``covered`` ``(B, 1, S, S)``: the target's coverage before any occluder; None: nothing hidden).
    Above 1, ``negative_weight`` makes every pixel taken for the product where it is not (the floor, a neighbour,
    an occluder) cost more than a visible one missed; ``occluder_weight`` only the occluder lying over the product.
    """
    weight = None
    if negative_weight != 1.0:
        weight = 1.0 + (float(negative_weight) - 1.0) * (1.0 - target)
    if occluder_weight != 1.0 and covered is not None:
        hidden = (covered - target).clamp(min=0.0)
        weight = (1.0 if weight is None else weight) + (float(occluder_weight) - 1.0) * hidden
    if weight is None:
        bce = F.binary_cross_entropy_with_logits(logits, target)
    else:
        bce = (F.binary_cross_entropy_with_logits(logits, target, reduction="none") * weight).sum() / weight.sum()
    return bce + dice_weight * dice_loss(logits, target) if dice_weight else bce


def mask_iou(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Intersection over union per image of boolean masks ``(B, ...)`` -> ``(B,)`` float (1 when both are empty)."""
    p, t = predicted.flatten(1).bool(), target.flatten(1).bool()
    inter, union = (p & t).sum(1).float(), (p | t).sum(1).float()
    return torch.where(union > 0, inter / union.clamp_min(1.0), torch.ones_like(union))


# ------------------------------------------------------------------------------------------ training
class VisibilityModule(L.LightningModule):
    """Trains a :class:`VisibilityNet` on scenes (``matl.data.scenes``): batches ``{"image": (B, 3, S, S),
    "visible": (B, 1, S, S)}`` at the working size, the visible coverage of the target in [0, 1].

    Args:
        net: the network (or a config mapping of :class:`VisibilityNet`'s arguments).
        lr, weight_decay: AdamW's settings; the rate decays by a cosine over ``epochs`` (stepped per epoch).
        epochs: the cosine's length (the trainer's ``max_epochs``).
        dice_weight: weight of the soft Dice term beside the cross-entropy.
        threshold: probability above which a pixel is foreground for the validation IoU.
        negative_weight: :func:`visibility_loss`'s weight of the pixels that do not show the product.
        occluder_weight: :func:`visibility_loss`'s weight of the pixels where an occluder hides the product (batches
            with ``"covered"``).
    """

    def __init__(self, net: VisibilityNet | dict[str, Any], lr: float = 3e-3, weight_decay: float = 1e-4,
                 epochs: int = 10, dice_weight: float = 1.0, threshold: float = 0.5,
                 negative_weight: float = 1.0, occluder_weight: float = 1.0) -> None:
        super().__init__()
        for name, value in (("negative_weight", negative_weight), ("occluder_weight", occluder_weight)):
            if not float(value) > 0.0:
                raise MatlError(f"model.{name}={value}: use a weight > 0 (1: every pixel alike)")
        self.net = net if isinstance(net, VisibilityNet) else VisibilityNet(**dict(net))
        self.lr, self.weight_decay, self.epochs = float(lr), float(weight_decay), int(epochs)
        self.dice_weight, self.threshold = float(dice_weight), float(threshold)
        self.negative_weight, self.occluder_weight = float(negative_weight), float(occluder_weight)
        self._val: list[torch.Tensor] = []
        self.val_history: list[dict[str, float]] = []

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.net(images)

    def _loss(self, logits: torch.Tensor, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        return visibility_loss(logits, batch["visible"], self.dice_weight, self.negative_weight,
                               self.occluder_weight, batch.get("covered"))

    def training_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        logits = self.net(batch["image"])
        loss = self._loss(logits, batch)
        if not torch.isfinite(loss):
            from matl.utils.errors import NonFiniteLossError

            raise NonFiniteLossError(f"the visibility loss is {float(loss)} at step {self.global_step}: lower lr=")
        self.log("train/loss", loss, prog_bar=True, batch_size=len(logits))
        return loss

    def validation_step(self, batch: dict[str, torch.Tensor], batch_idx: int) -> None:
        logits = self.net(batch["image"])
        self.log("val/loss", self._loss(logits, batch), batch_size=len(logits))
        threshold = math.log(self.threshold / (1.0 - self.threshold))  # the logit of the threshold
        self._val.append(mask_iou(logits > threshold, batch["visible"] > 0.5).cpu())

    def on_validation_epoch_end(self) -> None:
        if not self._val:
            return
        iou = torch.cat(self._val)
        self._val = []
        self.log("val/iou", iou.mean(), prog_bar=True)
        if not self.trainer.sanity_checking:
            self.val_history.append({"epoch": int(self.current_epoch), "iou": float(iou.mean()),
                                     "iou_median": float(iou.median())})

    def configure_optimizers(self) -> Any:
        optimizer = torch.optim.AdamW(self.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(1, self.epochs))
        return {"optimizer": optimizer, "lr_scheduler": scheduler}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["matl_visibility"] = dict(self.net.config)
