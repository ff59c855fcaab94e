"""Every config composes, the design card's command line resolves as written, and config names mean one thing."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import hydra
import pytest
import torch
from omegaconf import OmegaConf

from matl.utils.config import ConfigError, check_scale_data
from tests.conftest import CONF_DIR, compose_config

GROUP_CHOICES = {
    group: sorted(p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml") if not p.stem.startswith("_"))
    for group in ("data", "model", "loss", "anchors", "trainer", "logger", "callbacks")
}


@pytest.mark.parametrize("group,choice", [(g, c) for g, cs in GROUP_CHOICES.items() for c in cs])
def test_every_group_option_composes(group: str, choice: str, tmp_path: Path) -> None:
    cfg = compose_config("train", [f"{group}={choice}"], tmp_path)
    OmegaConf.resolve(cfg)  # every interpolation resolves
    assert cfg[group] is not None or choice == "none"


def test_design_card_command(tmp_path: Path) -> None:
    cfg = compose_config("train", ["loss=nce", "N=6"], tmp_path)
    OmegaConf.resolve(cfg)
    assert cfg.model.num_anchors == 6 and cfg.data.num_anchors == 6
    assert cfg.model.metric_loss._target_ == "matl.losses.NCELoss"
    assert cfg.model.num_negatives == 64 and cfg.model.metric_loss.tau == 0.07


def test_model_instantiates_with_paper_defaults(tmp_path: Path) -> None:
    cfg = compose_config("train", [], tmp_path)
    model = hydra.utils.instantiate(cfg.model)
    assert model.lam == 10.0 and model.num_anchors == 4
    assert model.feature_net.embedding_dim == 128
    configured = model.configure_optimizers()
    optimizer, scheduler = configured["optimizer"], configured["lr_scheduler"]["scheduler"]
    assert optimizer.defaults["lr"] == 0.01 and optimizer.defaults["momentum"] == 0.9
    # cosine decay over the run's epochs (docs/decisions.md); the paper's constant rate under scale=paper
    assert isinstance(scheduler, torch.optim.lr_scheduler.CosineAnnealingLR)
    assert scheduler.T_max == cfg.trainer.max_epochs
    paper = hydra.utils.instantiate(compose_config("train", ["scale=paper"], tmp_path).model)
    assert isinstance(paper.configure_optimizers(), torch.optim.SGD)
    tl = hydra.utils.instantiate(compose_config("train", ["model=tl"], tmp_path).model)
    assert tl.stn is None


# ------------------------------------------------------------------------------ query_source group
def test_query_source_group_sets_data_queries(tmp_path: Path) -> None:
    default = compose_config("train", [], tmp_path)
    assert default.data.queries == "warped"
    assert compose_config("train", ["query_source=warped"], tmp_path) == default
    rendered = compose_config("train", ["query_source=rendered"], tmp_path)
    assert rendered.data.queries == "rendered"
    assert rendered == compose_config("train", ["data.queries=rendered"], tmp_path)  # the same config
    datamodule = hydra.utils.instantiate(rendered.data)
    assert datamodule.queries == "rendered" and datamodule.views.views_per_plane == 30
    # eval keeps the run's own queries unless asked: the group only sets data.queries when chosen
    assert compose_config("eval", [], tmp_path).get("data") is None
    assert OmegaConf.to_container(compose_config("eval", ["query_source=rendered"], tmp_path).data) == {
        "queries": "rendered"}
    swapped = compose_config("eval", ["data=synthetic_apc", "query_source=rendered"], tmp_path)
    assert swapped.data.queries == "rendered" and swapped.data.source.catalog == "apc"


# --------------------------------------------------------------------------- scale x data parts
DATA_PARTS = Path(CONF_DIR) / "scale" / "data"
SCALES_WITH_PARTS = sorted({p.stem.split("_", 1)[0] for p in DATA_PARTS.glob("*.yaml")})
USER_DATA = {"images", "meshes"}  # the user's own photos or meshes: no paper size to give them
BENCHMARK_DATA = {"heldout"}  # matl.unseen's held-out products: never trained on (matl.train refuses them)


def test_scales_with_parts_have_one_per_shipped_dataset() -> None:
    assert SCALES_WITH_PARTS == ["cpu", "paper"]
    for scale in SCALES_WITH_PARTS:
        for data in set(GROUP_CHOICES["data"]) - USER_DATA - BENCHMARK_DATA:
            assert (DATA_PARTS / f"{scale}_{data}.yaml").is_file(), f"scale={scale} data={data}"


def test_missing_scale_data_part_is_a_clear_error(tmp_path: Path) -> None:
    check_scale_data({"scale": "paper", "data": "synthetic_ycb"})
    check_scale_data({"scale": "smoke", "data": "images"})  # smoke has no per-dataset parts
    check_scale_data({"scale": None, "data": "images"})
    check_scale_data({})
    with pytest.raises(ConfigError, match=r"scale=paper has no part for data=images: create "
                                          r"conf/scale/data/paper_images\.yaml"):
        check_scale_data({"scale": "paper", "data": "images"})
    for data in USER_DATA:  # a dataset without a part at cpu scale is refused there too
        with pytest.raises(ConfigError, match=f"scale=cpu has no part for data={data}"):
            check_scale_data({"scale": "cpu", "data": data})
    # the rule reads the files: a part added for the user's dataset makes the pair valid
    (tmp_path / "scale" / "data").mkdir(parents=True)
    (tmp_path / "scale" / "data" / "paper_synthetic_arc.yaml").write_text("train_triplets: 20000\n")
    with pytest.raises(ConfigError):
        check_scale_data({"scale": "paper", "data": "mine"}, tmp_path)
    (tmp_path / "scale" / "data" / "paper_mine.yaml").write_text("train_triplets: 100\n")
    check_scale_data({"scale": "paper", "data": "mine"}, tmp_path)


def test_train_refuses_a_missing_scale_data_part_in_one_line(tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "matl.train", "scale=paper", "data=images", f"data.source.root={tmp_path}",
           f"hydra.run.dir={tmp_path / 'run'}", "logger=none"]  # fmt: skip
    out = subprocess.run(cmd, cwd=Path(CONF_DIR).parent, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2, out.stderr[-2000:]
    assert out.stderr.strip().splitlines() == [
        "error: scale=paper has no part for data=images: create conf/scale/data/paper_images.yaml with the data "
        "keys this scale sets (e.g. train_triplets: <n>, as in paper_synthetic_arc.yaml)"]


# ------------------------------------------------------------------------------- experiment names
@pytest.mark.parametrize("preset", sorted(p.stem for p in (Path(CONF_DIR) / "experiment").glob("*.yaml")
                                          if p.stem.split("_", 1)[0] in ("cpu", "paper")))
def test_preset_names_say_their_scale_and_data(preset: str, tmp_path: Path) -> None:
    """``experiment=<scale>_<data>`` trains at that scale on that data, as conf/scale/data/<scale>_<data>.yaml
    is that pair's part: one name, one meaning."""
    scale, data = preset.split("_", 1)
    assert data in GROUP_CHOICES["data"]
    cfg = compose_config("train", [f"experiment={preset}"], tmp_path)
    reference = compose_config("train", [f"scale={scale}", f"data={data}"], tmp_path)
    assert cfg.data == reference.data and cfg.trainer == reference.trainer
