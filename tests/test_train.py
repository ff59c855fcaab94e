"""A tiny end-to-end run: train -> test the best checkpoint -> metrics.json with the metric names of docs/design.md."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from matl.metrics import METRIC_NAMES
from matl.training.fit import init_weights, train
from matl.utils.errors import MatlError
from matl.utils.instantiate import build


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


def test_tiny_occluded_run_from_another_runs_weights(tiny_train_cfg) -> None:
    """``occlude=bin`` trains end to end; ``init_from`` starts a new run from a checkpoint's weights, and a
    checkpoint of another N is a one-line error."""
    first = tiny_train_cfg(run="first")
    train(first)
    best = Path(first.paths.output_dir) / "checkpoints" / "best.ckpt"
    cfg = tiny_train_cfg(["occlude=bin", f"init_from={best}"], run="occluded")
    _, model = build(cfg)
    init_weights(cfg.init_from, cfg, model)
    saved = torch.load(best, weights_only=True)["state_dict"]
    assert all(torch.equal(v, saved[k]) for k, v in model.state_dict().items() if not k.startswith("recognizer."))
    results = train(cfg)
    assert math.isfinite(results["pose_err"]) and 0.0 <= results["rec_acc"] <= 1.0
    other = tiny_train_cfg(["N=2", f"init_from={best}"], run="other")
    with pytest.raises(MatlError, match=r"init_from=.* with N=4"):
        init_weights(other.init_from, other, build(other)[1])


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA GPU")
def test_trainer_gpu_on_a_machine_without_one_is_one_line(tiny_train_cfg) -> None:
    cfg = tiny_train_cfg(["trainer=gpu"], run="gpu")
    with pytest.raises(MatlError, match=r"trainer.accelerator=gpu but this machine has no CUDA GPU.*trainer=default"):
        train(cfg)
    assert not (Path(cfg.paths.output_dir) / "metrics.json").exists()


def test_the_shipped_default_recipe_fine_tunes_the_whole_product_model(tmp_path: Path) -> None:
    """experiment=pretrained_occluded: experiment=pretrained's settings, occluders on, started from the model the
    first command publishes, 2000 steps of a schedule laid out over 8 epochs, published into the package."""
    from tests.conftest import compose_config

    whole = compose_config("train", ["experiment=pretrained"], tmp_path / "whole")
    occluded = compose_config("train", ["experiment=pretrained_occluded"], tmp_path / "occluded")
    assert occluded.data.occlude is not None and whole.data.occlude is None
    assert occluded.init_from == "runs/pretrained_whole.ckpt" and occluded.publish == "shipped"
    assert occluded.trainer.accelerator == "gpu" and occluded.model.scheduler.T_max == 8
    steps = occluded.trainer.max_epochs * occluded.data.train_triplets // occluded.data.batch_size
    assert steps == 2000
    assert occluded.model.stn == whole.model.stn and occluded.model.feature_net == whole.model.feature_net
    assert occluded.model.align.optimizer.lr == 0.0003 and occluded.model.optimizer.lr == 0.003
    assert {k: v for k, v in occluded.model.align.items() if k != "optimizer"} == {
        k: v for k, v in whole.model.align.items() if k != "optimizer"}


def test_the_shipped_fast_recipe_fine_tunes_the_whole_product_fast_model(tmp_path: Path) -> None:
    """experiment=pretrained_fast_occluded: experiment=pretrained_fast's settings, occluders on, started from the
    model the first command publishes, 1500 steps of a schedule laid out over 12 epochs, published into the package."""
    from tests.conftest import compose_config

    whole = compose_config("train", ["experiment=pretrained_fast"], tmp_path / "whole")
    occluded = compose_config("train", ["experiment=pretrained_fast_occluded"], tmp_path / "occluded")
    assert occluded.data.occlude is not None and whole.data.occlude is None
    assert whole.publish == occluded.init_from == "runs/pretrained_fast_whole.ckpt"
    assert occluded.publish == "shipped_fast" and occluded.model.scheduler.T_max == 12
    assert occluded.trainer.max_epochs * occluded.data.train_triplets // occluded.data.batch_size == 1500
    assert occluded.model.stn == whole.model.stn and occluded.model.feature_net == whole.model.feature_net
    assert occluded.model.optimizer.lr == 0.003 and occluded.model.get("align") is None
