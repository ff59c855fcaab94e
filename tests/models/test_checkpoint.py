"""matl.models.checkpoint: the one resolver of ``ckpt=`` (pretrained, pretrained_fast, a path) in every command,
and one-line errors for files that are not matl checkpoints."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from matl.models import checkpoint
from matl.models.checkpoint import (
    PRETRAINED,
    PRETRAINED_FAST,
    load_checkpoint,
    load_embedding_model,
    resolve_checkpoint_keyword,
    resolve_ckpt_option,
)
from matl.utils.errors import MatlError
from tests.conftest import TINY, compose_config

REPO = Path(__file__).resolve().parents[2]
needs_models = pytest.mark.skipif(not (PRETRAINED.is_file() and PRETRAINED_FAST.is_file()),
                                  reason="the shipped models are not in this checkout")


def test_keywords_name_the_shipped_models_and_anything_else_is_a_path(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    assert resolve_checkpoint_keyword("runs/x/best.ckpt") == "runs/x/best.ckpt"
    assert resolve_checkpoint_keyword(None) is None
    cfg = OmegaConf.create({"ckpt": "best"})
    assert resolve_ckpt_option(cfg) == "best" and cfg.ckpt == "best"  # eval's own keywords are left alone
    monkeypatch.setattr(checkpoint, "PRETRAINED_FAST", tmp_path / "missing.ckpt")
    with pytest.raises(MatlError, match="no pretrained model ships with this version of matl"):
        resolve_checkpoint_keyword("pretrained_fast")
    import matl.inference.api as api

    assert api.resolve_checkpoint_keyword is resolve_checkpoint_keyword  # one resolver, importable from the API too


@needs_models
def test_resolved_in_place() -> None:
    cfg = OmegaConf.create({"ckpt": "pretrained"})
    assert resolve_ckpt_option(cfg) == str(PRETRAINED) == cfg.ckpt
    cfg = OmegaConf.create({"ckpt": "pretrained_fast"})
    assert resolve_ckpt_option(cfg) == str(PRETRAINED_FAST) == cfg.ckpt


# ------------------------------------------------------------------------------ every command
@needs_models
def test_predict_takes_the_keywords(tmp_path: Path) -> None:
    from matl.inference.files import predict
    from tests.predict_helpers import make_files

    gallery, queries, _ = make_files(tmp_path)
    for name in ("pretrained", "pretrained_fast"):
        out = tmp_path / f"{name}.jsonl"
        cfg = compose_config("predict", [f"ckpt={name}", f"gallery={gallery}", f"images={queries}", f"out={out}",
                                         "cache=false", "threshold=null"], tmp_path / name)
        predict(cfg)
        assert cfg.ckpt == str(PRETRAINED if name == "pretrained" else PRETRAINED_FAST)
        assert len(out.read_text().splitlines()) == 3


@needs_models
def test_export_takes_the_keywords(tmp_path: Path) -> None:
    from matl.inference.export import export

    info = export(compose_config("export", ["ckpt=pretrained_fast", f"out={tmp_path / 'out'}"], tmp_path / "run"))
    assert info["checkpoint"] == str(PRETRAINED_FAST) and info["image_size"] == 100
    assert (tmp_path / "out" / "query_net.pt").is_file()


@needs_models
def test_score_takes_the_keywords(tmp_path: Path) -> None:
    from matl.score import score

    (tmp_path / "truth.jsonl").write_text(json.dumps({"image": "q.png", "object": "tea"}) + "\n")
    (tmp_path / "pred.jsonl").write_text(json.dumps({"image": str(tmp_path / "q.png"), "object": "tea"}) + "\n")
    cfg = compose_config("score", ["ckpt=pretrained", f"predictions={tmp_path / 'pred.jsonl'}",
                                   f"truth={tmp_path / 'truth.jsonl'}", f"out={tmp_path / 'out'}"], tmp_path / "run")
    summary = score(cfg)
    assert cfg.ckpt == str(PRETRAINED) and summary["image_size"] == 100 and summary["rec_acc"] == 1.0


@needs_models
def test_bench_takes_the_keywords() -> None:
    from matl.evaluation.speed import load_model

    cfg = compose_config("bench", ["ckpt=pretrained_fast"])
    model, what = load_model(cfg)
    assert model is not None and str(PRETRAINED_FAST) in what and cfg.data.image_size == 100


@needs_models
def test_unseen_takes_the_keywords(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import matl.evaluation.unseen as unseen_module

    class Reached(Exception):
        pass

    def stop(cfg, train_data, file_size):  # the first step after the checkpoint is read
        raise Reached(file_size)

    monkeypatch.setattr(unseen_module, "_products", stop)
    cfg = compose_config("unseen", ["ckpt=pretrained_fast", "condition=clean", "methods=[matl]",
                                    f"out={tmp_path / 'out'}"], tmp_path / "run")
    with pytest.raises(Reached) as reached:
        unseen_module.unseen(cfg)
    assert reached.value.args == (100,)  # the shipped model's size


@needs_models
def test_eval_takes_the_keywords(tmp_path: Path, cache_dir: Path) -> None:
    """A 32 px run evaluated with ckpt=pretrained: the shipped 100 px file is what eval reads (and refuses)."""
    run = tmp_path / "run32"
    (run / ".hydra").mkdir(parents=True)
    cfg = compose_config("train", [*TINY, f"paths.cache_dir={cache_dir}", "logger=none"], run)
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, "-m", "matl.eval", f"run={run}", "ckpt=pretrained",
                           f"hydra.run.dir={tmp_path / 'h'}"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2 and len(errors) == 1, proc.stderr[-2000:]
    assert f"checkpoint {PRETRAINED} was trained at 100 px" in errors[0]


# --------------------------------------------------------------------------------- bad files
@pytest.mark.parametrize("make,reason", [
    (lambda p: p.write_text("not a checkpoint"), "not a torch checkpoint file"),
    (lambda p: torch.jit.save(torch.jit.script(torch.nn.Linear(2, 2)), str(p)), "a TorchScript file"),
    (lambda p: torch.save({"state_dict": {}, "obj": Path("x")}, p), "pickled Python objects"),
    (lambda p: p.write_bytes(PRETRAINED.read_bytes()[:20000]) if PRETRAINED.is_file() else pytest.skip(),
     "truncated or corrupt"),
])
def test_unreadable_files_are_named_without_torchs_advice(tmp_path: Path, make, reason: str) -> None:
    path = tmp_path / "model.ckpt"
    make(path)
    with pytest.raises(MatlError) as error:
        load_checkpoint(path)
    message = str(error.value)
    assert "\n" not in message and reason in message and "cannot be read safely" in message
    assert "weights_only` set to `False`" not in message and "ckpt=pretrained" in message


@pytest.mark.parametrize("payload,expected", [
    ({"weights": torch.zeros(2)}, "has no state_dict"),
    ({"state_dict": {"w": [1, 2]}}, "not a table of named tensors"),
    ({"state_dict": {}, "matl_image_size": "x", "matl_num_anchors": 4}, "not positive integers"),
    ({"state_dict": {}, "matl_image_size": 32, "matl_num_anchors": 4, "matl_config": {"model": {"x": 1}}},
     "not a matl model"),
    ({"state_dict": {}, "matl_image_size": 32, "matl_num_anchors": 4,
      "matl_config": {"model": {"_target_": "matl.models.feature.FeatureNet", "image_size": "${nothing.here}"}}},
     "cannot be built by this version of matl"),
])
def test_files_that_are_not_matl_checkpoints(tmp_path: Path, payload: dict, expected: str) -> None:
    torch.save(payload, tmp_path / "model.ckpt")
    with pytest.raises(MatlError, match=expected) as error:
        load_embedding_model(tmp_path / "model.ckpt")
    assert "\n" not in str(error.value)
    with pytest.raises(MatlError, match="is a folder"):
        load_checkpoint(tmp_path)
