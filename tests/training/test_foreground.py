"""Training the visibility network (matl/training/foreground.py): a tiny run writes its checkpoints, metrics.json
and the published network; the config's mistakes are found before any work."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from matl.inference.foreground import LearnedForeground
from matl.models.visibility import FOREGROUND_WEIGHTS
from matl.training.foreground import check_config, train_foreground
from matl.utils.errors import MatlError
from tests.conftest import compose_config

TINY = ["data.image_size=32", "net.size=16", "net.channels=[4,6,8]", "data.train_scenes=32", "data.val_scenes=8",
        "data.batch_size=8", "data.scenes.augment.bank=8", "trainer.max_epochs=2", "timing_crops=3"]


def test_tiny_run_writes_checkpoints_metrics_and_the_published_network(tmp_path: Path, cache_dir: Path) -> None:
    published = tmp_path / "published" / "foreground.ckpt"
    cfg = compose_config("train_foreground", [*TINY, f"paths.cache_dir={cache_dir}", f"publish={published}"],
                         tmp_path / "run")
    results = train_foreground(cfg)
    out = tmp_path / "run"
    assert (out / "checkpoints" / "best.ckpt").is_file() and (out / "checkpoints" / "last.ckpt").is_file()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics == json.loads(json.dumps(results))
    assert metrics["epochs"] == 2 and metrics["train_scenes"] == 32 and metrics["val_scenes"] == 8
    assert 0.0 <= metrics["val_iou"] <= 1.0 and len(metrics["val_history"]) == 2 and metrics["ms_per_crop"] > 0
    assert metrics["working_size"] == 16 and metrics["published"] == str(published)
    slim = torch.load(published, weights_only=True)
    assert slim["matl_visibility"]["size"] == 16 and slim["matl_metrics"]["val_iou"] == metrics["val_iou"]
    assert published.stat().st_size < 200_000
    step = LearnedForeground(weights=str(published), threads=1)
    crop = np.random.default_rng(0).random((40, 30, 3)).astype(np.float32)
    assert step.working_size == 16 and step.probability(crop).shape == (40, 30)


def test_config_mistakes_are_found_before_any_work(tmp_path: Path) -> None:
    folder = tmp_path / "a_folder"
    folder.mkdir()
    for override, message in ((f"publish={folder}", "is a folder"), ("net.size=20", "net.size=20"),
                              ("timing_crops=-1", "timing_crops=-1"),
                              ("+data.train_source.photos=skimage", "held-out benchmark's photo pool"),
                              ("data.train_scenes=0", "data.train_scenes=0"),
                              (f"init={tmp_path / 'missing.ckpt'}", "no such file")):
        with pytest.raises(MatlError, match=re.escape(message)):
            check_config(compose_config("train_foreground", [override], tmp_path / "run"))
    assert check_config(compose_config("train_foreground", ["publish=shipped"], tmp_path / "run")) == FOREGROUND_WEIGHTS
    assert check_config(compose_config("train_foreground", [], tmp_path / "run")) is None


def test_a_fine_tune_starts_from_the_published_network(tmp_path: Path, cache_dir: Path) -> None:
    first, second = tmp_path / "first.ckpt", tmp_path / "second.ckpt"
    one_epoch = [*TINY, "trainer.max_epochs=1", "timing_crops=0", f"paths.cache_dir={cache_dir}"]
    train_foreground(compose_config("train_foreground", [*one_epoch, f"publish={first}"], tmp_path / "a"))
    # at a learning rate of 0 the fine-tune's weights are the ones it started from (other scenes: seed 1)
    train_foreground(compose_config("train_foreground", [*one_epoch, f"init={first}", "model.lr=0.0", "seed=1",
                                                         f"publish={second}"], tmp_path / "b"))
    started, tuned = (torch.load(path, weights_only=True)["state_dict"] for path in (first, second))
    weights = [key for key in started if key.endswith(("weight", "bias"))]  # parameters (not running statistics)
    assert weights and all(torch.equal(started[key], tuned[key]) for key in weights)
    with pytest.raises(MatlError, match="differs from net"):
        train_foreground(compose_config("train_foreground", [*one_epoch, "net.channels=[4,6,10]", f"init={first}"],
                                        tmp_path / "c"))
