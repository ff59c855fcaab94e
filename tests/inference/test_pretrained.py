"""The model shipped in the package: small, loads offline, and predict uses it when no ckpt= is given."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

import matl.inference.api
import matl.models.checkpoint
from matl import Recognizer
from matl.inference.files import predict
from matl.utils.errors import MatlError
from tests.conftest import compose_config
from tests.predict_helpers import make_files

SHIPPED = matl.inference.api.PRETRAINED
needs_model = pytest.mark.skipif(not SHIPPED.is_file(), reason=f"{SHIPPED} is not in this checkout")


@needs_model
def test_the_shipped_model_is_small_and_loads_offline() -> None:
    assert SHIPPED.stat().st_size < 10 * 2**20
    ckpt = torch.load(SHIPPED, map_location="cpu", weights_only=True)  # plain tensors and containers only
    assert set(ckpt) >= {"state_dict", "matl_config", "matl_image_size", "matl_num_anchors"}
    assert "optimizer_states" not in ckpt
    rec = Recognizer.pretrained()
    assert rec.image_size == ckpt["matl_image_size"] == 100 and rec.num_anchors == ckpt["matl_num_anchors"]
    # the shipped recipe (experiment=pretrained, fine-tuned by experiment=pretrained_occluded): input normalisation and
    # the alignment stage, trained with occluders
    model = ckpt["matl_config"]["model"]
    assert model["feature_net"]["input_norm"] == model["stn"]["regressor"]["input_norm"] == "channel"
    assert rec.model.align is not None and any(k.startswith("align.") for k in ckpt["state_dict"])
    assert ckpt["matl_config"]["data"]["occlude"]["_target_"] == "matl.data.occlusion.OccludeQueries"


@needs_model
def test_exporting_the_shipped_model_exports_its_alignment_stage(tmp_path: Path) -> None:
    from matl.inference.export import export

    info = export(compose_config("export", [f"ckpt={SHIPPED}", f"out={tmp_path / 'out'}"], tmp_path / "run"))
    assert "exported as align_net" in info["alignment_stage"] and info["files"]["align_net"] == "align_net.pt"
    assert info["max_abs_diff"]["align_net"] <= info["tolerance"] and (tmp_path / "out" / "align_net.pt").is_file()
    assert json.loads((tmp_path / "out" / "export.json").read_text())["alignment_stage"] == info["alignment_stage"]


@needs_model
def test_predict_without_ckpt_uses_the_shipped_model(tmp_path: Path) -> None:
    gallery, queries, _ = make_files(tmp_path)
    lines = {}
    for name, extra in (("default", []), ("explicit", [f"ckpt={SHIPPED}"])):
        out = tmp_path / f"{name}.jsonl"
        cfg = compose_config("predict", [f"gallery={gallery}", f"images={queries}", f"out={out}", "cache=false",
                                         *extra], tmp_path / name)
        predict(cfg)
        lines[name] = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(lines["default"]) == len(list(queries.iterdir()))
    strip = [{k: v for k, v in r.items() if k != "image"} for r in lines["default"]]
    assert strip == [{k: v for k, v in r.items() if k != "image"} for r in lines["explicit"]]
    # the Python API gives the same answers on the same files, answered in one batch as predict answers them (a query
    # answered alone can differ by the networks' float noise, which the flow pose's RANSAC and its rounds can amplify
    # on these smooth prints)
    rec = Recognizer.pretrained().enrol(gallery, cache=False)
    records = {Path(r["image"]).name: r for r in lines["default"]}
    paths = sorted(queries.iterdir())
    for path, match in zip(paths, rec.predict(paths), strict=True):
        record = records[path.name]
        assert match.object == record["object"] and np.allclose(match.H, record["H"], rtol=1e-4, atol=1e-4)


def test_predict_without_ckpt_and_without_a_shipped_model_is_one_line(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(matl.models.checkpoint, "PRETRAINED", tmp_path / "missing.ckpt")
    gallery, queries, _ = make_files(tmp_path)
    cfg = compose_config("predict", [f"gallery={gallery}", f"images={queries}", f"out={tmp_path / 'p.jsonl'}"],
                         tmp_path)
    with pytest.raises(MatlError, match=r"ckpt=\.\.\. is required: no pretrained model ships"):
        predict(cfg)
    assert not (tmp_path / "p.jsonl").exists()
    with pytest.raises(MatlError, match="no pretrained model ships"):
        Recognizer.pretrained()


FAST = matl.inference.api.PRETRAINED_FAST
needs_fast = pytest.mark.skipif(not FAST.is_file(), reason=f"{FAST} is not in this checkout")


@needs_fast
def test_the_fast_shipped_model_is_its_experiment_and_loads_by_name(tmp_path: Path) -> None:
    ckpt = torch.load(FAST, map_location="cpu", weights_only=True)
    assert FAST.stat().st_size < 2 * 2**20 and "optimizer_states" not in ckpt
    # experiment=pretrained_fast, fine-tuned by experiment=pretrained_fast_occluded: model=matl_camera_fast (regressor
    # at stride 4 on raw pixels, c()'s first conv at 16 channels), no alignment stage, trained with occluders
    recipe = compose_config("train", ["experiment=pretrained_fast_occluded"], tmp_path)
    model = ckpt["matl_config"]["model"]
    assert recipe.publish == "shipped_fast"
    assert ckpt["matl_config"]["data"]["occlude"]["_target_"] == "matl.data.occlusion.OccludeQueries"
    for part in ("stn", "feature_net"):
        assert model[part] == OmegaConf.to_container(recipe.model[part], resolve=True), part
    assert model["stn"]["regressor"]["strides"] == [4, 1] and model["feature_net"]["input_norm"] == "channel"
    assert model["feature_net"]["channels"] == [16, 128]
    assert not any(k.startswith("align.") for k in ckpt["state_dict"])
    rec = Recognizer.pretrained("fast")  # refined by default: its pose is the refinement's
    assert rec.image_size == 100 and rec.model.align is None and rec.refiner is not None
    assert Recognizer.pretrained("fast", refine=False).refiner is None
    with pytest.raises(MatlError, match="no shipped model is called 'tiny'"):
        Recognizer.pretrained("tiny")


@needs_fast
def test_ckpt_pretrained_fast_names_the_fast_model_on_the_command_line(tmp_path: Path) -> None:
    gallery, queries, _ = make_files(tmp_path)
    out = tmp_path / "fast.jsonl"
    cfg = compose_config("predict", [f"gallery={gallery}", f"images={queries}", f"out={out}", "cache=false",
                                     "ckpt=pretrained_fast"], tmp_path / "run")
    predict(cfg)
    assert cfg.ckpt == str(FAST) and len(out.read_text().splitlines()) == len(list(queries.iterdir()))


def test_a_missing_shipped_model_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(matl.models.checkpoint, "PRETRAINED_FAST", tmp_path / "missing.ckpt")
    with pytest.raises(MatlError, match=r"no pretrained model ships with this version of matl .*missing\.ckpt"):
        Recognizer.pretrained("fast")
