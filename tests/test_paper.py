"""The paper's experiments as configs: every row x scale composes to what the paper describes, the
scale presets and launchers compose, and nothing is submitted or trained here (composition only)."""

from __future__ import annotations

from pathlib import Path

import hydra
import pytest
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from tests.conftest import CONF_DIR, compose_config

TRAINED_ROWS = [f"table1_{r}" for r in "abcfghij"] + [f"table2_{r}" for r in "abcd"]
PRESETS = [f"{s}_{d}" for s in ("paper", "cpu") for d in ("arc", "ycb", "apc")]
SCALES = [None, "cpu", "paper", "smoke"]


def _short(target: str) -> str:
    return target.rsplit(".", 1)[-1]


def _summary(cfg) -> dict:
    """The settings that distinguish the paper's rows."""
    model = cfg.model
    return {
        "model": _short(model._target_), "N": cfg.N, "lam": cfg.lam,
        "stn": model.get("stn") is not None, "loss": _short(cfg.loss.fn._target_), "M": cfg.loss.num_negatives,
        "anchors": _short(cfg.anchors._target_), "negative": model.get("stn_on_negative"),
        "catalog": cfg.data.source.get("catalog"), "subset": cfg.data.source.get("subset"),
    }


EXPECTED = {
    "table1_a": dict(model="MATLModule", N=1, lam=10.0, stn=True, loss="TripletLoss", anchors="FixedAnchors",
                     negative=True),
    "table1_b": dict(model="MATLModule", N=1, stn=False, loss="TripletLoss"),
    "table1_c": dict(model="STNClassifierModule", N=4, stn=True),
    "table1_f": dict(model="MATLModule", N=4, lam=10.0, stn=True, loss="TripletLoss", anchors="FixedAnchors",
                     negative=True),
    "table1_g": dict(model="MATLModule", N=4, lam=0.0, stn=True, loss="TripletLoss", anchors="FixedAnchors"),
    "table1_h": dict(model="MATLModule", N=4, lam=10.0, anchors="RandomAnchors", negative=True),
    "table1_i": dict(model="MATLModule", N=4, lam=10.0, anchors="FixedAnchors", negative=False),
    "table1_j": dict(model="MATLModule", N=4, lam=10.0, loss="NCELoss", M=64, negative=True),
    "table2_a": dict(N=4, lam=10.0, catalog="ycb_table2", subset="planar"),
    "table2_b": dict(N=1, lam=10.0, catalog="ycb_table2", subset="planar"),
    "table2_c": dict(N=4, lam=10.0, catalog="ycb_table2", subset="nonplanar"),
    "table2_d": dict(N=1, lam=10.0, catalog="ycb_table2", subset="nonplanar"),
}


def test_every_experiment_file_is_known() -> None:
    files = sorted(p.stem for p in (Path(CONF_DIR) / "experiment").glob("*.yaml"))
    assert files == sorted([*TRAINED_ROWS, "table1_d", "table1_e", *PRESETS])


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("row", TRAINED_ROWS)
def test_rows_compose_with_every_scale(row: str, scale: str | None, tmp_path: Path) -> None:
    cfg = compose_config("train", [f"experiment={row}", *([f"scale={scale}"] if scale else [])], tmp_path)
    OmegaConf.resolve(cfg)
    summary = _summary(cfg)
    for key, value in EXPECTED[row].items():
        assert summary[key] == value, (row, scale, key)
    if row == "table1_j":  # M=64 negatives drawn from the batch need 3 * batch - 2 >= 64
        assert cfg.loss.fn.tau == 0.07 and 3 * cfg.data.batch_size - 2 >= 64
    # the model really builds (catches keys a scale would add to a model that does not take them)
    model = hydra.utils.instantiate(cfg.model)
    assert model.num_anchors == cfg.N if hasattr(model, "num_anchors") else True


@pytest.mark.parametrize("model", ["matl", "matl_fast", "tl", "stn_classifier"])
def test_paper_scale_sets_the_papers_model_behaviour(model: str, tmp_path: Path) -> None:
    cfg = compose_config("train", ["scale=paper", f"model={model}"], tmp_path)
    OmegaConf.resolve(cfg)
    assert cfg.trainer.max_epochs == 100 and cfg.trainer.accelerator == "gpu"
    assert cfg.model.optimizer.lr == 0.01 and cfg.model.optimizer.momentum == 0.9
    assert cfg.model.scheduler is None  # the paper's constant rate
    assert cfg.data.image_size == 100 and cfg.data.test_queries == 1000
    if model == "tl":
        assert cfg.model.stn is None  # no STN appears from the scale
    else:
        assert cfg.model.stn.iterations == 1
    if model == "stn_classifier":
        assert "appearance" not in cfg.model
    else:
        assert cfg.model.appearance == "forward" and cfg.model.appearance_levels == 1
    # the CPU defaults stay the defaults (docs/decisions.md)
    default = compose_config("train", [f"model={model}"], tmp_path)
    if model == "matl":
        assert default.model.appearance == "symmetric" and default.model.stn.iterations == 2


@pytest.mark.parametrize("data,paper,cpu", [("synthetic_arc", 20000, 4000), ("synthetic_ycb", 25000, 5000),
                                            ("synthetic_apc", 10000, 2000), ("synthetic_ycb_table2", 25000, 5000)])
def test_scale_triplets_per_dataset(data: str, paper: int, cpu: int, tmp_path: Path) -> None:
    assert compose_config("train", ["scale=paper", f"data={data}"], tmp_path).data.train_triplets == paper
    assert compose_config("train", ["scale=cpu", f"data={data}"], tmp_path).data.train_triplets == cpu


@pytest.mark.parametrize("preset", PRESETS)
def test_presets(preset: str, tmp_path: Path) -> None:
    scale, dataset = preset.split("_")
    cfg = compose_config("train", [f"experiment={preset}"], tmp_path)
    OmegaConf.resolve(cfg)
    assert cfg.data.source.catalog == dataset and cfg.N == 4 and cfg.lam == 10.0
    assert cfg.trainer.max_epochs == (100 if scale == "paper" else 8)
    triplets = {"arc": 20000, "ycb": 25000, "apc": 10000}[dataset]
    assert cfg.data.train_triplets == (triplets if scale == "paper" else triplets // 5)


def test_command_line_wins_over_presets(tmp_path: Path) -> None:
    cfg = compose_config("train", ["experiment=paper_arc", "scale=cpu", "data=synthetic_apc", "trainer=default"],
                         tmp_path)
    assert cfg.data.source.catalog == "apc" and cfg.data.train_triplets == 2000 and cfg.trainer.max_epochs == 8
    assert cfg.model.appearance == "symmetric"  # scale=cpu keeps the CPU model defaults
    cfg = compose_config("train", ["experiment=table1_f", "N=9"], tmp_path)
    assert cfg.N == 9 and cfg.model.num_anchors == 9


@pytest.mark.parametrize("row,baseline", [("table1_d", "SiftRansacMatcher"), ("table1_e", "SuperPointRansacMatcher")])
def test_baseline_rows_are_evaluations(row: str, baseline: str, tmp_path: Path) -> None:
    cfg = compose_config("eval", [f"experiment={row}", "data=synthetic_ycb", "seed=3"], tmp_path)
    assert _short(cfg.baseline._target_) == baseline and cfg.N == 4 and cfg.seed == 3
    with pytest.raises(ConfigCompositionException, match="baseline"):
        compose_config("train", [f"experiment={row}"], tmp_path)


@pytest.mark.parametrize("sweep,params", [
    ("table1", {"experiment": "table1_a,table1_b,table1_c,table1_f,table1_g,table1_h,table1_i,table1_j",
                "seed": "range(0,9)"}),
    ("table2", {"experiment": "table2_a,table2_b,table2_c,table2_d", "seed": "range(0,9)"}),
    ("fig4", {"N": "1,2,4,6,9", "seed": "range(0,9)"}),
])
def test_sweep_presets(sweep: str, params: dict, tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir
    from hydra.types import RunMode

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", [f"+sweep={sweep}", "scale=cpu"], return_hydra_config=True)
    assert cfg.hydra.mode == RunMode.MULTIRUN
    assert dict(cfg.hydra.sweeper.params) == params
    if sweep == "fig4":
        assert cfg.hydra.runtime.choices.experiment == "table1_f"


def test_slurm_launcher_composes_without_submitting(tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", ["hydra/launcher=slurm", "trainer=ddp", "trainer.devices=4", "trainer.num_nodes=2",
                                "hydra.launcher.partition=gpu", "hydra.launcher.timeout_min=90"],
                      return_hydra_config=True)
    assert cfg.hydra.runtime.choices["hydra/launcher"] == "slurm"
    launcher = hydra.utils.instantiate(cfg.hydra.launcher)  # constructs the launcher; submits nothing
    assert type(launcher).__name__ == "SlurmLauncher"
    params = launcher.params
    assert params["partition"] == "gpu" and params["timeout_min"] == 90
    assert params["gpus_per_node"] == 4 and params["tasks_per_node"] == 4 and params["nodes"] == 2
    assert params["max_num_timeout"] > 0  # requeue on timeout; resume=auto continues the job


def test_joblib_launcher_composes(tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"], return_hydra_config=True)
    assert cfg.hydra.launcher.n_jobs == 2 and "joblib" in cfg.hydra.launcher._target_.lower()


@pytest.mark.parametrize("trainer", ["ddp", "ddp_multinode", "ddp_cpu"])
def test_ddp_trainers_compose(trainer: str, tmp_path: Path) -> None:
    cfg = compose_config("train", [f"trainer={trainer}"], tmp_path)
    assert _short(cfg.trainer.strategy._target_) == "DDPStrategy"
    backend = cfg.trainer.strategy.process_group_backend
    assert backend == ("gloo" if trainer == "ddp_cpu" else "nccl")
    assert cfg.trainer.num_nodes == (2 if trainer == "ddp_multinode" else 1)
    if trainer == "ddp_cpu":  # builds on any machine (no process is started before fit)
        built = hydra.utils.instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
        assert built.world_size == 2 and type(built.strategy).__name__ == "DDPStrategy"
