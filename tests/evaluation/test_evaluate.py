"""``matl.eval``: a checkpoint or a baseline on a run's test queries reproduces the run's own numbers."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from matl.evaluation.evaluate import DEFAULT_N, DEFAULT_SEED, evaluate
from matl.inference.files import predict
from matl.metrics import METRIC_NAMES
from matl.utils.errors import MatlError
from tests.conftest import compose_config
from tests.predict_helpers import (
    eval_cfg,
    make_files,
    predict_cfg,
    read_csv,
    save_run_config,
    tiny_eval,  # noqa: F401 - a module fixture
    tiny_run,  # noqa: F401 - a module fixture
    train_run,
)


# ----------------------------------------------------------------------------------------- eval
def test_eval_reproduces_train_test_metrics(tiny_run: Path, tiny_eval: Path) -> None:
    trained = json.loads((tiny_run / "metrics.json").read_text())
    evaluated = json.loads((tiny_eval / "eval.json").read_text())
    for name in METRIC_NAMES:
        assert evaluated[name] == pytest.approx(trained[name], abs=1e-6), name
    assert evaluated["query_ms"] > 0
    assert evaluated["evaluated"] == "checkpoint" and evaluated["checkpoint"].endswith("best.ckpt")
    assert evaluated["num_queries"] == 48 and evaluated["N"] == 4 and evaluated["image_size"] == 32
    rows = read_csv(tiny_eval / "per_query.csv")
    assert len(rows) == 48
    assert np.mean([int(r["correct"]) for r in rows]) == pytest.approx(evaluated["rec_acc"])
    correct = [float(r["frobenius_err"]) for r in rows if r["correct"] == "1"]
    assert np.mean(correct) == pytest.approx(evaluated["pose_err"], rel=1e-9)
    est = np.array([[float(r[f"est_H_{i}{j}"]) for i in range(3) for j in range(3)] for r in rows])
    assert np.allclose(est[:, 8], 1.0)


def test_eval_last_checkpoint_and_other_data(tiny_run: Path, tmp_path: Path, cache_dir: Path) -> None:
    out = evaluate(eval_cfg(tmp_path / "a", [f"run={tiny_run}", "ckpt=last", "+data.test_queries=8"]),
                   show_progress=False)
    assert out["checkpoint"].endswith("last.ckpt") and out["num_queries"] == 8
    # data=<name>: composed and swapped in, the run's image size / N / seed stay
    other = evaluate(eval_cfg(tmp_path / "b", [f"run={tiny_run}", "data=synthetic_apc", "data.test_queries=8"]),
                     show_progress=False)
    assert other["image_size"] == 32 and other["N"] == 4 and other["seed"] == 0
    assert other["gallery_size"] == 90 * 4 and other["num_queries"] == 8


def test_eval_user_errors(tiny_run: Path, tmp_path: Path) -> None:
    with pytest.raises(MatlError, match="no such folder"):
        evaluate(eval_cfg(tmp_path / "e", [f"run={tmp_path / 'missing'}"]))
    (tmp_path / "bare").mkdir()
    with pytest.raises(MatlError, match=r"no \.hydra/config\.yaml"):
        evaluate(eval_cfg(tmp_path / "e", [f"run={tmp_path / 'bare'}"]))
    with pytest.raises(MatlError, match="not found"):
        evaluate(eval_cfg(tmp_path / "e", [f"run={tiny_run}", f"ckpt={tmp_path / 'nope.ckpt'}"]))
    with pytest.raises(MatlError, match="seed=3 differs"):
        evaluate(eval_cfg(tmp_path / "e", [f"run={tiny_run}", "seed=3"]))
    with pytest.raises(MatlError, match="run=<run dir> is required"):
        evaluate(eval_cfg(tmp_path / "e", []))
    # a 32 px checkpoint against a run config of another size / N
    for key, value, message in (("data.image_size", 48, "trained at 32 px"), ("N", 2, "with N=4")):
        other = tmp_path / f"other_{value}"
        saved = OmegaConf.load(tiny_run / ".hydra" / "config.yaml")
        OmegaConf.update(saved, key, value)
        save_run_config(saved, other)
        ckpt = tiny_run / "checkpoints" / "best.ckpt"
        with pytest.raises(MatlError, match=message):
            evaluate(eval_cfg(tmp_path / "e", [f"run={other}", f"ckpt={ckpt}"]))


def test_eval_defaults_match_train() -> None:
    train_cfg = compose_config("train", [])
    assert (train_cfg.N, train_cfg.seed) == (DEFAULT_N, DEFAULT_SEED)


def test_baseline_sift_same_queries(tiny_run: Path, tiny_eval: Path, tmp_path: Path) -> None:
    pytest.importorskip("matl.baselines.sift")
    cfg = eval_cfg(tmp_path, [f"run={tiny_run}", "baseline=sift", "timing_queries=3"])
    out = evaluate(cfg, show_progress=False)
    assert out["evaluated"] == "baseline" and out["checkpoint"] is None
    assert 0.0 <= out["rec_acc"] <= 1.0 and out["query_ms"] > 0
    rows, model_rows = read_csv(tmp_path / "per_query.csv"), read_csv(tiny_eval / "per_query.csv")
    true_cols = [f"true_H_{i}{j}" for i in range(3) for j in range(3)]
    assert [[r[c] for c in true_cols] for r in rows] == [[r[c] for c in true_cols] for r in model_rows]
    assert all(r["inliers"] != "" for r in rows)


def test_baseline_without_run(tmp_path: Path, cache_dir: Path) -> None:
    pytest.importorskip("matl.baselines.sift")
    cfg = eval_cfg(tmp_path, ["baseline=sift", "data=synthetic_arc", "data.image_size=32", "data.test_queries=6",
                              "seed=1", "N=2", "timing_queries=2", f"paths.cache_dir={cache_dir}"])
    out = evaluate(cfg, show_progress=False)
    assert out["run"] is None and out["seed"] == 1 and out["N"] == 2 and out["num_queries"] == 6
    assert out["gallery_size"] == 152 * 2


# --------------------------------------------------------------------------------- classifier
def test_stn_classifier_trains_evaluates_and_cannot_enrol(tmp_path: Path, cache_dir: Path) -> None:
    matl_stn = compose_config("train", ["model=matl"]).model.stn
    assert compose_config("train", ["model=stn_classifier"]).model.stn == matl_stn, "row (c) must use MATL's STN"
    run_dir = tmp_path / "cls"
    results = train_run(run_dir, cache_dir, ["model=stn_classifier"])
    for name in METRIC_NAMES:
        assert results[name] is not None and math.isfinite(results[name]), name
    ckpt = torch.load(run_dir / "checkpoints" / "best.ckpt", weights_only=True)
    assert len(ckpt["matl_class_names"]) == 34 and not any(k.startswith("recognizer.") for k in ckpt["state_dict"])
    evaluated = evaluate(eval_cfg(tmp_path / "eval", [f"run={run_dir}"]), show_progress=False)
    for name in METRIC_NAMES:
        assert evaluated[name] == pytest.approx(results[name], abs=1e-6), name
    with pytest.raises(MatlError, match="trained on"):
        evaluate(eval_cfg(tmp_path / "eval2", [f"run={run_dir}", "data=synthetic_apc", "data.test_queries=4"]))
    gallery, queries, _ = make_files(tmp_path / "files")
    with pytest.raises(MatlError, match="cannot enrol"):
        predict(predict_cfg(tmp_path, run_dir / "checkpoints" / "best.ckpt", gallery, queries))


