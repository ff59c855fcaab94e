"""A tiny end-to-end run: train -> test the best checkpoint -> metrics.json with the metric names of docs/design.md."""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from matl.metrics import METRIC_NAMES
from matl.training.fit import train


def test_tiny_train_writes_metrics(tiny_train_cfg) -> None:
    cfg = tiny_train_cfg()
    results = train(cfg)
    out = Path(cfg.paths.output_dir)
    assert (out / "checkpoints" / "best.ckpt").is_file() and (out / "checkpoints" / "last.ckpt").is_file()
    metrics = json.loads((out / "metrics.json").read_text())
    for name in (*METRIC_NAMES, "query_ms"):
        assert name in metrics, name
    assert 0.0 <= metrics["rec_acc"] <= 1.0 and 0.0 <= metrics["pose_acc_5px"] <= 1.0
    assert metrics["pose_err"] is not None and math.isfinite(metrics["pose_err"])
    assert metrics["corner_err_px_median"] <= metrics["corner_err_px"] * 10
    assert metrics["query_ms"] > 0
    assert metrics == json.loads(json.dumps(results, default=str))
    # checkpoints hold plain data: they load without unpickling arbitrary objects
    ckpt = torch.load(out / "checkpoints" / "best.ckpt", weights_only=True)
    assert ckpt["matl_image_size"] == 32 and ckpt["matl_config"]["N"] == 4
    assert (out / "csv" / "metrics.csv").is_file()


def test_tiny_tl_and_nce_run(tiny_train_cfg) -> None:
    tl = train(tiny_train_cfg(["model=tl", "N=1"], run="tl"))
    assert tl["pose_err"] is None and tl["pose_acc_5px"] is None and 0 <= tl["rec_acc"] <= 1
    nce = train(tiny_train_cfg(["loss=nce", "N=6", "loss.num_negatives=8"], run="nce"))
    assert math.isfinite(nce["pose_err"])
