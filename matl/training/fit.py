"""Training a model from a config: fit, test the best checkpoint, write ``metrics.json``.

:func:`train` is what ``python -m matl.train`` runs. It validates the config (one-line errors,
before any data or model is built), instantiates data, model, trainer, callbacks and loggers from
their ``_target_`` nodes, fits, tests the best checkpoint and returns the test metrics;
:func:`sweep_value` turns them into the number a Hydra sweeper optimises.

Resuming: ``ckpt_path=<run>/checkpoints/last.ckpt`` continues a run killed at any point, also
mid-epoch (``last.ckpt`` is rewritten atomically every ``callbacks.model_checkpoint.
last_every_n_train_steps`` steps; see :class:`matl.models.checkpoint.AtomicModelCheckpoint`), and
ends with the metrics of an uninterrupted run of the same seed. ``resume=auto`` does the same for
the run's own folder (``last.ckpt`` when present; a run whose ``metrics.json`` exists is not
trained again), which is what a re-launched or requeued sweep job needs
(:mod:`matl.utils.sweep`, docs/experiments.md).

Heavy imports (torch, Lightning) happen inside :func:`train`, after the config is validated, so a
mistyped option is reported in about a second.
"""

from __future__ import annotations

import json
import logging
import math
import time
import warnings
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from matl.metrics import METRIC_NAMES, POSE_METRICS
from matl.utils.config import validate_config
from matl.utils.distributed import is_global_zero
from matl.utils.errors import MatlError
from matl.utils.instantiate import build, instantiate_list
from matl.utils.io import write_json
from matl.utils.sweep import auto_resume, check_distributed_launch, clear_failed

log = logging.getLogger(__name__)


def _relative(path: Path, root: Path) -> str:
    try:
        return str(path.relative_to(root))
    except ValueError:  # a checkpoint dirpath outside the run folder
        return str(path)


def null_reasons(results: dict[str, Any], model: Any) -> dict[str, str]:
    """Why each ``null`` of ``metrics.json`` is null, so a missing number is never silent."""
    reasons: dict[str, str] = {}
    has_pose = getattr(model, "stn", True) is not None
    for name in (*METRIC_NAMES, "query_ms"):
        if name not in results or results[name] is not None:
            continue
        if name in POSE_METRICS and not has_pose:
            reasons[name] = "the model has no STN (model=tl): it estimates no pose"
        elif name in POSE_METRICS and results.get("rec_acc") == 0:
            reasons[name] = "no test query was recognised correctly; pose errors average over recognised queries"
        elif name == "query_ms":
            reasons[name] = "too few test queries to time"
        else:
            reasons[name] = "not finite (NaN or inf): the model or the data produced an undefined value"
    return reasons


def _check_fits(key: str, path: str | Path, ckpt: dict[str, Any], cfg: DictConfig, model: Any) -> None:
    """``ckpt`` (read from ``path``, given as ``key=``) holds weights of this config's size, N and model."""
    from matl.models.checkpoint import checkpoint_info

    size, num_anchors = checkpoint_info(ckpt, path)
    if size != int(cfg.data.image_size) or num_anchors != int(cfg.N):
        raise MatlError(f"{key}={path} was trained at {size} px with N={num_anchors}, but this config has "
                        f"data.image_size={cfg.data.image_size} and N={cfg.N}: use the checkpoint's own settings")
    expected = {k: tuple(v.shape) for k, v in model.state_dict().items() if not k.startswith("recognizer.")}
    found = {k: tuple(v.shape) for k, v in ckpt["state_dict"].items() if not k.startswith("recognizer.")}
    if expected != found:
        missing = sorted(set(expected) - set(found))[:3]
        extra = sorted(set(found) - set(expected))[:3]
        shapes = sorted(k for k in set(expected) & set(found) if expected[k] != found[k])[:3]
        raise MatlError(f"{key}={path} does not fit this model (model=... or its options differ): "
                        f"missing {missing}, unexpected {extra}, other shapes {shapes}")


def check_resume_checkpoint(path: str | Path, cfg: DictConfig, model: Any) -> None:
    """Before Lightning touches ``ckpt_path``: it must be a matl checkpoint of this config's size, N and model.

    Read with ``weights_only=True``; every mismatch is a one-line :class:`MatlError` naming the file.
    """
    from matl.models.checkpoint import load_checkpoint

    ckpt = load_checkpoint(path)
    _check_fits("ckpt_path", path, ckpt, cfg, model)
    if "loops" not in ckpt or "optimizer_states" not in ckpt:
        raise MatlError(f"ckpt_path={path} holds weights only (no optimizer / loop state): it cannot resume training; "
                        f"init_from={path} starts a new run from its weights")


def init_weights(value: Any, cfg: DictConfig, model: Any) -> str:
    """``init_from``: load the weights of a checkpoint (a path, ``pretrained`` or ``pretrained_fast``) into ``model``
    before training: a new run (optimiser, schedule and epochs from this config) from those weights. Returns the
    checkpoint's path."""
    from matl.models.checkpoint import load_checkpoint, resolve_checkpoint_keyword

    path = str(resolve_checkpoint_keyword(str(value)))
    ckpt = load_checkpoint(path)
    _check_fits("init_from", path, ckpt, cfg, model)
    state = {k: v for k, v in ckpt["state_dict"].items() if not k.startswith("recognizer.")}
    model.load_state_dict(state, strict=False)
    return path


def check_training_photos(cfg: DictConfig) -> None:
    """Refuse a training source that prints the unseen benchmark's held-out photos (docs/datasets.md)."""
    from matl.data.catalog.drawing import TRAINING_PHOTO_POOL

    photos = OmegaConf.select(cfg, "data.source.photos", default=TRAINING_PHOTO_POOL)
    if photos != TRAINING_PHOTO_POOL:
        raise MatlError(f"data.source.photos={photos} is the held-out benchmark's photo pool (python -m matl.unseen): "
                        f"training uses photos={TRAINING_PHOTO_POOL}")


def log_lightning_once() -> None:
    """Print each Lightning log line once.

    ``import lightning`` gives its package logger a console handler of its own, yet the logger also
    propagates to the root logger that Hydra configured (console and ``<run>/<task>.log``), so every
    Lightning line was printed twice. When the root has handlers, Lightning's own are dropped.
    """
    if logging.getLogger().hasHandlers():
        lightning_logger = logging.getLogger("lightning")
        for handler in list(lightning_logger.handlers):
            lightning_logger.removeHandler(handler)


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit, test the best checkpoint, write ``metrics.json``; returns the test metrics."""
    validate_config(cfg)  # before any heavy import, data or model: a config mistake costs a second
    check_training_photos(cfg)  # the benchmark's held-out photos are never trained on
    check_distributed_launch(cfg)  # local DDP inside -m would re-run the whole sweep in every process
    auto_ckpt, finished = auto_resume(cfg)  # resume=auto: continue this run folder (matl/utils/sweep.py)
    if finished is not None:
        return finished

    import lightning as L
    import torch

    accelerator = str(OmegaConf.select(cfg, "trainer.accelerator", default="cpu"))
    if accelerator in ("gpu", "cuda") and not torch.cuda.is_available():
        raise MatlError(f"trainer.accelerator={accelerator} but this machine has no CUDA GPU that torch can use: "
                        "train on the CPU with trainer=default (or install a CUDA build of torch)")
    log_lightning_once()

    from matl.utils.timing import measure_query_ms

    torch.set_float32_matmul_precision("high")
    L.seed_everything(cfg.seed, workers=True)
    output_dir = Path(cfg.paths.output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)

    datamodule, model = build(cfg)
    model.run_config = OmegaConf.to_container(cfg, resolve=True)
    resume = cfg.get("ckpt_path") or auto_ckpt
    if resume:
        check_resume_checkpoint(resume, cfg, model)
    elif cfg.get("init_from"):  # a resumed run keeps its own weights; a new one may start from a checkpoint's
        log.info("starting from the weights of %s", init_weights(cfg.init_from, cfg, model))
    callbacks = instantiate_list(cfg.get("callbacks"))
    loggers = instantiate_list(cfg.get("logger"))
    trainer = hydra.utils.instantiate(cfg.trainer, callbacks=callbacks, logger=loggers or False)

    # Our training sampler *is* resumable (matl.data.resumable places it from the restored step), but
    # Lightning only recognises stateful DataLoaders and would warn that a mid-epoch resume is unreliable.
    warnings.filterwarnings("ignore", message="You're resuming from a checkpoint that ended before the epoch ended")
    start = time.perf_counter()
    # weights_only=True: resuming never unpickles code from the checkpoint (our checkpoints hold
    # tensors and plain containers only; see matl.models.checkpoint)
    trainer.fit(model, datamodule=datamodule, ckpt_path=resume or None, weights_only=True)
    train_seconds = time.perf_counter() - start

    results: dict[str, Any] = {"train_seconds": round(train_seconds, 2), "seed": cfg.seed, "N": cfg.N,
                               "lam": cfg.lam, "epochs": trainer.current_epoch}
    if cfg.get("test", True):
        ckpt = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
        trainer.test(model, datamodule=datamodule, ckpt_path=ckpt or None, weights_only=True)
        tested = model.test_results
        for name in METRIC_NAMES:
            value = float(tested.get(f"test/{name}", math.nan))
            results[name] = value if math.isfinite(value) else None
        results["query_ms"] = measure_query_ms(model, datamodule)
        results["checkpoint"] = _relative(Path(ckpt), output_dir) if ckpt else None
        results["degenerate_stn"] = model.degenerate_count  # training STN outputs replaced by identity
        results["test_degenerate_stn"] = getattr(model, "eval_degenerate", 0)  # test queries, likewise
        reasons = null_reasons(results, model)
        if reasons:
            results["null_reasons"] = reasons
        if is_global_zero():  # under DDP every process gets here with the same (gathered) metrics
            if cfg.get("publish") and ckpt:
                from matl.models.checkpoint import publish_checkpoint

                target = cfg.publish
                if target == "shipped":  # the model inside the package: Recognizer.pretrained(), predict without ckpt=
                    from matl.models.checkpoint import PRETRAINED as target
                elif target == "shipped_fast":  # the fast one: Recognizer.pretrained("fast"), ckpt=pretrained_fast
                    from matl.models.checkpoint import PRETRAINED_FAST as target
                published = publish_checkpoint(ckpt, target, results)
                results["published"] = str(published)
                log.info("published the tested checkpoint as %s (%.1f MB)", published,
                         published.stat().st_size / 2**20)
            write_json(output_dir / "metrics.json", results)
            clear_failed(output_dir)  # a resumed job that had failed before
        log.info("test metrics: %s", json.dumps(results))
    return results


def sweep_value(results: dict[str, Any], cfg: DictConfig) -> float | None:
    """The number a Hydra sweeper optimises: the test value of ``optimized_metric``.

    ``val/score`` (checkpoint selection) becomes the same weighted sum of the *test* metrics
    (``model.score_weights``), so an Optuna sweep ranks runs by what selected their checkpoints.
    """
    from matl.models.evaluation import DEFAULT_SCORE_WEIGHTS, weighted_score

    metric = str(cfg.get("optimized_metric", "")).split("/")[-1]
    if metric == "score":
        weights = OmegaConf.select(cfg, "model.score_weights", default=None)
        weights = DEFAULT_SCORE_WEIGHTS if weights is None else OmegaConf.to_container(weights)
        return weighted_score(results, weights)
    value = results.get(metric)
    return None if value is None else float(value)
