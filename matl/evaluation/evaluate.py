"""Evaluating a checkpoint, or a keypoint baseline, on a dataset's test queries: ``eval.json`` and ``per_query.csv``.

The library side of ``python -m matl.eval`` (the command and its options: :mod:`matl.eval`).
"""

from __future__ import annotations

import copy
import json
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf, open_dict
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from matl.baselines.recognizer import BaselineRecognizer, build_baseline
from matl.data.gallery import Gallery
from matl.geometry import corner_error_px, frobenius_pose_error
from matl.inference.options import configure_recognizer
from matl.inference.quantize import apply_quantize_option, datamodule_calibration, quantize_option
from matl.inference.runtime import apply_runtime_option, runtime_option
from matl.metrics import METRIC_NAMES, pose_metrics
from matl.models.checkpoint import build_model, checkpoint_info, load_checkpoint
from matl.models.prediction import Prediction
from matl.utils.config import validate_config
from matl.utils.errors import MatlError
from matl.utils.io import write_csv, write_json
from matl.utils.runs import compose_data_group, hydra_choice, load_run, resolve_checkpoint
from matl.utils.sweep import clear_failed
from matl.utils.timing import median_query_ms

log = logging.getLogger(__name__)

DEFAULT_N, DEFAULT_SEED = 4, 0  # train.yaml's defaults, used by a baseline evaluated without run=
TIMING_WARMUP = 5               # as matl.utils.timing.measure_query_ms (train's query_ms)


# ------------------------------------------------------------------------------ configuration
def _describe_data(data: DictConfig) -> str:
    """A name for a data node whose group choice is unknown, e.g. ``SyntheticCatalog(arc)``."""
    source = data.get("source")
    if not isinstance(source, DictConfig):
        return str(data.get("_target_", "?")).rsplit(".", 1)[-1]
    target = str(source.get("_target_", "?")).rsplit(".", 1)[-1]
    return f"{target}({source.catalog})" if source.get("catalog") else target


def effective_config(cfg: DictConfig) -> tuple[DictConfig, Path | None, str]:
    """The config whose ``data`` (and ``model``) are evaluated, the run folder, and the data's name.

    With ``run=``: the run's saved config, with ``data`` swapped when ``data=<name>`` is given (its
    ``image_size`` set to the run's; ``N``, ``seed``, ``anchors`` and ``paths`` are the run's, which
    the swapped node's interpolations resolve against). Without: a config of ``N``, ``seed``,
    ``anchors``, ``paths`` and ``data`` from the eval config (a baseline's queries).
    """
    data_name = hydra_choice("data")
    if cfg.get("run"):
        run_dir, saved = load_run(cfg.run)
        for key in ("N", "seed"):
            if cfg.get(key) is not None and cfg[key] != saved.get(key):
                raise MatlError(f"{key}={cfg[key]} differs from the run's {key}={saved.get(key)}: eval uses the "
                                f"run's saved config (drop {key}=)")
        if cfg.get("data") is not None and "_target_" in cfg.data:
            data = copy.deepcopy(cfg.data)
            with open_dict(data):
                data.image_size = saved.data.image_size  # the checkpoint's size, whatever the group says
            saved.data = data
        elif cfg.get("data") is not None:  # `+data.test_queries=2000`: edit the run's own data node
            saved.data = OmegaConf.merge(saved.data, cfg.data)
        if data_name is None:
            hydra_file = run_dir / ".hydra" / "hydra.yaml"
            if hydra_file.is_file():  # the run's own choice, for eval.json
                data_name = OmegaConf.select(OmegaConf.load(hydra_file), "hydra.runtime.choices.data")
        return saved, run_dir, str(data_name or _describe_data(saved.data))
    if cfg.get("baseline") is None:
        raise MatlError("run=<run dir> is required (or baseline=<sift|sift_ecc|superpoint|lightglue|xfeat|"
                        "xfeat_lighterglue> to evaluate a baseline)")
    data = cfg.get("data")
    if data is None or "_target_" not in data:  # no data= (possibly `+data.key=value` edits of the default)
        data_name = str(cfg.default_data)
        default = compose_data_group(data_name)
        data = default if data is None else OmegaConf.merge(default, data)
    config = OmegaConf.create({
        "N": DEFAULT_N if cfg.get("N") is None else cfg.N,
        "seed": DEFAULT_SEED if cfg.get("seed") is None else cfg.seed,
        "anchors": cfg.anchors, "paths": cfg.paths, "data": data,
    })
    return config, None, str(data_name or _describe_data(data))


# --------------------------------------------------------------------------------- evaluation
H_COLUMNS = [f"{prefix}_H_{r}{c}" for prefix in ("true", "est") for r in range(3) for c in range(3)]
CSV_COLUMNS = ["query", "true_object", "true_plane", "true_plane_index", "pred_object", "pred_plane",
               "pred_plane_index", "pred_anchor", "gallery_index", "distance", "inliers", "correct",
               "frobenius_err", "corner_err_px", *H_COLUMNS]


def per_query_rows(pred: Prediction, batch: dict[str, torch.Tensor], gallery: Gallery, image_size: int,
                   first: int) -> list[dict[str, Any]]:
    """``per_query.csv`` rows of one batch (errors for *every* query; the metrics keep the correct ones)."""
    size = (image_size, image_size)
    true_H = batch["query_H_canon"].double().cpu()
    est_H = None if pred.query_H_canon is None else pred.query_H_canon.double().cpu()
    frob = corner = None
    if est_H is not None:
        frob, corner = frobenius_pose_error(est_H, true_H, size), corner_error_px(est_H, true_H, size)
    inliers = getattr(pred, "inliers", None)
    rows = []
    for i in range(len(true_H)):
        t_obj, t_plane = int(batch["object"][i]), int(batch["plane"][i])
        p_obj, p_plane = int(pred.object_index[i]), int(pred.plane_index[i])
        row = {
            "query": first + i,
            "true_object": gallery.object_names[t_obj], "true_plane": gallery.plane_names[t_plane],
            "true_plane_index": t_plane,
            "pred_object": gallery.object_names[p_obj] if p_obj >= 0 else "",
            "pred_plane": gallery.plane_names[p_plane] if p_plane >= 0 else "",
            "pred_plane_index": p_plane, "pred_anchor": int(pred.anchor_index[i]),
            "gallery_index": int(pred.gallery_index[i]), "distance": float(pred.distance[i]),
            "inliers": "" if inliers is None else int(inliers[i]),
            "correct": int(p_obj == t_obj),
            "frobenius_err": "" if frob is None else float(frob[i]),
            "corner_err_px": "" if corner is None else float(corner[i]),
        }
        row.update(zip(H_COLUMNS[:9], true_H[i].flatten().tolist(), strict=True))
        row.update(zip(H_COLUMNS[9:], [""] * 9 if est_H is None else est_H[i].flatten().tolist(), strict=True))
        rows.append(row)
    return rows


def run_queries(predict: Callable[[torch.Tensor], Prediction], datamodule: Any, device: torch.device,
                show_progress: bool = True) -> tuple[dict[str, float], list[dict[str, Any]], int]:
    """Evaluate ``predict`` on the datamodule's test split, batched as in ``trainer.test``.

    Returns:
        the accuracy metrics of docs/design.md (NaN where undefined), per-query rows, and the number of queries
        whose STN output was degenerate (replaced by identity).
    """
    metrics = pose_metrics(datamodule.image_size).to(device)
    rows: list[dict[str, Any]] = []
    degenerate = 0
    loader = datamodule.test_dataloader()
    columns = (TextColumn("[bold]eval"), BarColumn(), MofNCompleteColumn(), TextColumn("batches"), TimeElapsedColumn())
    with Progress(*columns, disable=not show_progress) as progress:
        task = progress.add_task("eval", total=len(loader))
        for batch in loader:
            batch = datamodule.materialize({k: v.to(device) for k, v in batch.items()})
            pred = predict(batch["query"])
            true_H = batch["query_H_canon"].double()
            est_H = None if pred.query_H_canon is None else pred.query_H_canon.to(device)
            metrics.update(pred.object_index.to(device), batch["object"], est_H, true_H)
            rows.extend(per_query_rows(pred, batch, datamodule.gallery, datamodule.image_size, len(rows)))
            degenerate += int(pred.degenerate.sum())
            progress.advance(task)
    values = {name: float(value) for name, value in metrics.compute().items()}
    return values, rows, degenerate


def time_queries(predict: Callable[[torch.Tensor], Prediction], datamodule: Any, count: int,
                 device: torch.device) -> float | None:
    """``query_ms`` as train measures it: median over the first ``count`` test queries after
    ``TIMING_WARMUP`` untimed ones, one query per call. A tiny split gives up warm-up calls first;
    None if nothing could be timed."""
    params = {k: v[:count + TIMING_WARMUP] for k, v in datamodule.test_set.params.items()}
    queries = datamodule.materialize({k: v.to(device) for k, v in params.items()})["query"]
    warmup = min(TIMING_WARMUP, len(queries) // 2)
    value = median_query_ms(predict, queries, warmup)
    return None if math.isnan(value) else value


def evaluate(cfg: DictConfig, show_progress: bool = True) -> dict[str, Any]:
    """Evaluate a run's checkpoint or a baseline (see the module docstring); returns ``eval.json``'s content."""
    validate_config(cfg)  # eval's own options (device, timing_queries, ...), before anything is loaded
    quantize_option(cfg)  # quantize=none|int8, checked before anything is loaded
    runtime_option(cfg)  # runtime=torch|onnxruntime
    config, run_dir, data_name = effective_config(cfg)
    validate_config(config)
    out_dir = Path(cfg.paths.output_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    device = torch.device(str(cfg.device) if cfg.device != "auto" else
                          "cuda" if torch.cuda.is_available() else "cpu")

    baseline_name = None
    checkpoint_path = None
    info: dict[str, Any] = {}
    if cfg.get("baseline") is not None:
        baseline_name = hydra_choice("baseline") or str(cfg.baseline._target_).rsplit(".", 1)[-1]
        matcher = build_baseline(cfg.baseline, baseline_name)  # fail fast, before rendering any data
    else:
        checkpoint_path = resolve_checkpoint(run_dir, str(cfg.ckpt))
        ckpt = load_checkpoint(checkpoint_path)
        size, num_anchors = checkpoint_info(ckpt, checkpoint_path)
        data_size, data_n = int(config.data.image_size), int(config.N)
        if size != data_size or num_anchors != data_n:
            raise MatlError(f"checkpoint {checkpoint_path} was trained at {size} px with N={num_anchors}, but the "
                            f"data is {data_size} px with N={data_n}")
        info.update(model=str(config.model._target_).rsplit(".", 1)[-1], checkpoint_epoch=ckpt.get("epoch"),
                    checkpoint_step=ckpt.get("global_step"))

    datamodule = hydra.utils.instantiate(config.data)
    datamodule.setup("test")
    if baseline_name is not None:
        predict: Callable[[torch.Tensor], Prediction] = BaselineRecognizer(matcher, datamodule.gallery)
    else:
        model = build_model(config.model, ckpt, checkpoint_path, datamodule).to(device)
        predict = model.build_recognizer(datamodule.gallery)
    quantize = {"quantize": quantize_option(cfg), "quantize_fallback": None}
    if quantize["quantize"] != "none":  # quantize=int8, calibrated on training positives (matl/inference/quantize.py)
        quantize = apply_quantize_option(predict, cfg, lambda: datamodule_calibration(datamodule))
    runtime = apply_runtime_option(predict, cfg)  # runtime=onnxruntime: MATL's query networks in onnxruntime
    predict, inference = configure_recognizer(predict, cfg)  # search=exact|faiss, refine=true (docs/speed.md)

    metrics, rows, degenerate = run_queries(predict, datamodule, device, show_progress)
    query_ms = time_queries(predict, datamodule, int(cfg.timing_queries), device)

    results: dict[str, Any] = {name: None if math.isnan(metrics[name]) else metrics[name] for name in METRIC_NAMES}
    results.update({
        "query_ms": query_ms,
        "evaluated": "baseline" if baseline_name else "checkpoint",
        "run": None if run_dir is None else str(run_dir),
        "checkpoint": None if checkpoint_path is None else str(checkpoint_path),
        "baseline": baseline_name,
        "data": data_name,
        "split": "test",
        "num_queries": len(rows),
        "gallery_size": len(datamodule.gallery),
        "N": int(config.N),
        "seed": int(config.seed),
        "image_size": int(datamodule.image_size),
        "degenerate_queries": degenerate,
        **inference,
        **quantize,
        **runtime,
        **info,
    })
    write_json(out_dir / "eval.json", results)
    write_csv(out_dir / "per_query.csv", rows, CSV_COLUMNS)
    clear_failed(out_dir)  # an evaluation re-run after it had failed in a sweep
    log.info("eval: %s", json.dumps(results))
    return results
