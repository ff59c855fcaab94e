"""Training the visibility network of ``foreground=learned`` from a config (``python -m matl.train_foreground``).

:func:`train_foreground` checks the config (one-line errors, before any scene is made), makes the
scenes (:class:`matl.data.scenes.SceneDataModule`), fits :class:`matl.models.visibility.VisibilityModule`
keeping the checkpoint of the best validation IoU, and writes ``metrics.json``: the best checkpoint's
validation IoU (all scenes, and the scenes with occluders), the milliseconds of one crop in
onnxruntime with one thread, the network's size. ``publish`` also writes the best network as a slim
checkpoint (weights and settings, read with ``torch.load(weights_only=True)``); ``publish=shipped`` writes
the one inside the package, :data:`matl.models.visibility.FOREGROUND_WEIGHTS`, which ``foreground=learned``
loads by default.
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from matl.utils.errors import MatlError
from matl.utils.instantiate import instantiate_list, instantiate_node
from matl.utils.io import write_json

log = logging.getLogger(__name__)



def publish_target(value: Any) -> Path | None:
    """The path ``publish`` names (``shipped``: :data:`FOREGROUND_WEIGHTS`), None for none; a one-line error for
    a folder or a place that cannot be written."""
    if value is None or value is False or value == "":
        return None
    from matl.models.visibility import FOREGROUND_WEIGHTS

    target = FOREGROUND_WEIGHTS if value == "shipped" else Path(str(value)).expanduser()
    if target.is_dir():
        raise MatlError(f"publish={value}: {target} is a folder: name a file, e.g. publish=<dir>/foreground.ckpt")
    parent = target.parent
    while not parent.exists():
        parent = parent.parent
    if not os.access(parent, os.W_OK):
        raise MatlError(f"publish={value}: {parent} is not writable: name another file")
    return target


def check_config(cfg: DictConfig) -> Path | None:
    """The config's mistakes as one line each, before any work; returns the publish target."""
    from matl.data.catalog.drawing import TRAINING_PHOTO_POOL

    for key in ("data.train_source", "data.val_source"):
        photos = OmegaConf.select(cfg, f"{key}.photos", default=TRAINING_PHOTO_POOL)
        if photos != TRAINING_PHOTO_POOL:
            raise MatlError(f"{key}.photos={photos} is the held-out benchmark's photo pool (python -m matl.unseen): "
                            f"train and validate on photos={TRAINING_PHOTO_POOL}")
    size = OmegaConf.select(cfg, "net.size")
    if not isinstance(size, int) or size < 16 or size % 8:
        raise MatlError(f"net.size={size}: use a multiple of 8, at least 16 (e.g. 64)")
    for key in ("data.train_scenes", "data.val_scenes", "data.batch_size", "trainer.max_epochs"):
        value = OmegaConf.select(cfg, key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise MatlError(f"{key}={value}: use an integer >= 1")
    timing = cfg.get("timing_crops", 0)
    if not isinstance(timing, int) or timing < 0:
        raise MatlError(f"timing_crops={timing}: use an integer >= 0 (0: no timing)")
    init = cfg.get("init")
    if init is not None and init != "shipped" and not Path(str(init)).expanduser().is_file():
        raise MatlError(f"init={init}: no such file: name a published visibility network (publish=<file> of an earlier "
                        "run) or shipped")
    return publish_target(cfg.get("publish"))


def slim_checkpoint(ckpt_path: str | Path, target: Path, metrics: dict[str, Any]) -> Path:
    """Write the network of a training checkpoint as ``target``: ``{"format", "state_dict" (the net's),
    "matl_visibility" (its settings), "matl_metrics"}``, atomically."""
    import torch

    from matl.models.visibility import VISIBILITY_FORMAT

    ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=True)
    state = {k[len("net."):]: v.contiguous().clone() for k, v in ckpt["state_dict"].items() if k.startswith("net.")}
    slim = {"format": VISIBILITY_FORMAT, "state_dict": state, "matl_visibility": dict(ckpt["matl_visibility"]),
            "matl_metrics": {k: v for k, v in metrics.items() if isinstance(v, (int, float, str, type(None)))}}
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.tmp")
    torch.save(slim, tmp)
    os.replace(tmp, target)
    return target


def validation_metrics(module: Any, datamodule: Any, threshold: float) -> dict[str, float]:
    """IoU of the thresholded probability against the visible mask (> 0.5) at the working size: the mean over
    the validation scenes, over those with occluders (hidden fraction > 0), and per background kind."""
    import torch

    from matl.models.visibility import mask_iou

    scenes = datamodule.val_set
    module.eval()
    with torch.no_grad():
        images = scenes.images.float().div(255.0)
        prob = torch.cat([torch.sigmoid(module.net(images[i:i + 256])) for i in range(0, len(images), 256)])
    iou = mask_iou(prob > threshold, scenes.visible > 127)
    out = {"val_iou": float(iou.mean())}
    occluded = scenes.hidden > 0
    out["val_iou_occluded"] = float(iou[occluded].mean()) if bool(occluded.any()) else None
    for kind in sorted(set(scenes.background)):
        chosen = torch.tensor([b == kind for b in scenes.background])
        out[f"val_iou_{kind}"] = float(iou[chosen].mean())
    return out


def crop_ms(net: Any, crops: Any, repeats: int) -> dict[str, Any]:
    """Median milliseconds of :class:`matl.inference.foreground.LearnedForeground`'s probability of one 100 px
    crop (resize, the network in onnxruntime with one thread, resize back), over ``repeats`` crops."""
    import numpy as np

    from matl.inference.foreground import LearnedForeground
    from matl.utils.timing import compute_threads

    step = LearnedForeground.from_network(net, threads=1)
    times = []
    with compute_threads(1):
        for i in range(repeats + 5):
            crop = np.ascontiguousarray(crops[i % len(crops)])
            start = time.perf_counter()
            step.probability(crop)
            if i >= 5:
                times.append(time.perf_counter() - start)
    return {"ms_per_crop": round(1000.0 * float(np.median(times)), 4), "runtime": step.runtime_in_use}


def start_from(net: Any, init: Any) -> None:
    """Load a published visibility network's weights (``init``: a file, or ``shipped``) into ``net``, which must have
    its settings (a fine-tune)."""
    from matl.models.visibility import load_visibility_net

    source = load_visibility_net(None if init == "shipped" else str(init))  # a missing or foreign file: one line
    if source.config != net.config:
        raise MatlError(f"init={init}: its network {source.config} differs from net {net.config}: fine-tune with the "
                        "net settings it was trained with")
    net.load_state_dict(source.state_dict())


def train_foreground(cfg: DictConfig) -> dict[str, Any]:
    """Fit, keep the best validation IoU, write ``metrics.json`` (and the published network); returns the metrics."""
    target = check_config(cfg)

    import lightning as L
    import torch

    from matl.training.fit import log_lightning_once

    log_lightning_once()
    L.seed_everything(int(cfg.seed), workers=True)
    output_dir = Path(cfg.paths.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    datamodule = instantiate_node(cfg.data, "data")
    module = instantiate_node(cfg.model, "model")
    if cfg.get("init") is not None:
        start_from(module.net, cfg.init)
    callbacks = instantiate_list(cfg.get("callbacks"))
    loggers = instantiate_list(cfg.get("logger"))
    trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)

    start = time.perf_counter()
    datamodule.setup("fit")
    scene_seconds = time.perf_counter() - start
    start = time.perf_counter()
    trainer.fit(module, datamodule=datamodule)
    train_seconds = time.perf_counter() - start

    best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
    if best:
        state = torch.load(best, map_location="cpu", weights_only=True)["state_dict"]
        module.load_state_dict(state)
    net = module.net.eval()
    results: dict[str, Any] = {"seed": int(cfg.seed), "epochs": int(trainer.current_epoch),
                               "scene_seconds": round(scene_seconds, 2), "train_seconds": round(train_seconds, 2),
                               "train_scenes": len(datamodule.train_set.images),
                               "val_scenes": len(datamodule.val_set.images),
                               "parameters": sum(p.numel() for p in net.parameters()),
                               "working_size": int(net.size),
                               **validation_metrics(module, datamodule, float(module.threshold)),
                               "val_history": module.val_history,
                               "checkpoint": os.path.relpath(best, output_dir) if best else None}
    if int(cfg.get("timing_crops", 0)) > 0:
        crops = datamodule.timing_crops(int(cfg.timing_crops))
        results.update(crop_ms(net, crops, int(cfg.timing_crops)))
    if target is not None and best:
        published = slim_checkpoint(best, target, {k: v for k, v in results.items() if k != "val_history"})
        results["published"] = str(published)
        log.info("published the network as %s (%.1f kB)", published, published.stat().st_size / 1024)
    write_json(output_dir / "metrics.json", results)
    log.info("metrics: %s", json.dumps(results))
    return results
