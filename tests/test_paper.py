"""The paper's vocabulary (matl.paper) against the configs: every row x scale composes to exactly its settings
in matl/paper.py and is recognised as that row; the scale presets, sweeps and launchers compose. Nothing
is submitted or trained here (composition only)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import hydra
import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from matl import paper
from matl.reporting.configs import dataset_name
from matl.reporting.rows import paper_settings
from tests.conftest import CONF_DIR, compose_config

TRAINED_ROWS = [name for name, row in paper.ROWS.items() if row.command == "train"]
EVALUATED_ROWS = [name for name, row in paper.ROWS.items() if row.command == "eval"]
# row (f) at a scale on a dataset: experiment=<scale>_<data group>
PRESETS = [f"{s}_synthetic_{c}" for s in ("paper", "cpu") for c in ("arc", "ycb", "apc")]
SCALES = [None, "cpu", "paper", "smoke"]


def _short(target: str) -> str:
    return target.rsplit(".", 1)[-1]


def test_every_experiment_file_is_known() -> None:
    files = sorted(p.stem for p in (Path(CONF_DIR) / "experiment").glob("*.yaml"))
    # the shipped models' recipes
    shipped = ["pretrained", "pretrained_occluded", "pretrained_fast", "pretrained_fast_occluded"]
    assert files == sorted([*paper.ROWS, *PRESETS, *shipped])
    assert list(TRAINED_ROWS) == [f"table1_{r}" for r in "abcfghij"] + [f"table2_{r}" for r in "abcd"]
    assert list(EVALUATED_ROWS) == ["table1_d", "table1_e"]


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("name", TRAINED_ROWS)
def test_rows_compose_to_their_settings_with_every_scale(name: str, scale: str | None, tmp_path: Path) -> None:
    row = paper.ROWS[name]
    cfg = compose_config("train", [f"experiment={name}", *([f"scale={scale}"] if scale else [])], tmp_path)
    OmegaConf.resolve(cfg)
    settings = paper_settings(cfg, dataset_name(cfg.data))
    assert {key: settings[key] for key in row.settings} == dict(row.settings), (name, scale)
    # ... and the report recognises the composed run as this row (rows (a) and (f) are also Fig. 4 points)
    expected = (row.key, None, row.key in "af") if row.table == 1 else (None, row.key, False)
    assert paper.classify(settings) == expected, (name, scale)
    if name == "table1_j":  # M=64 negatives drawn from the batch need 3 * batch - 2 >= 64
        assert 3 * cfg.data.batch_size - 2 >= cfg.loss.num_negatives
    # the model really builds (catches keys a scale would add to a model that does not take them)
    model = hydra.utils.instantiate(cfg.model)
    assert model.num_anchors == cfg.N if hasattr(model, "num_anchors") else True


@pytest.mark.parametrize("name,matcher", [("table1_d", "SiftRansacMatcher"), ("table1_e", "SuperPointRansacMatcher")])
def test_baseline_rows_are_evaluations(name: str, matcher: str, tmp_path: Path) -> None:
    row = paper.ROWS[name]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("eval", [f"experiment={name}", "data=synthetic_ycb", "seed=3"], return_hydra_config=True)
    assert (cfg.hydra.runtime.choices.baseline, cfg.N) == (row.settings["baseline"], row.settings["N"])
    assert _short(cfg.baseline._target_) == matcher and cfg.seed == 3
    assert paper.classify({"baseline": row.settings["baseline"], "N": cfg.N}) == (row.key, None, False)
    with pytest.raises(ConfigCompositionException, match="baseline"):
        compose_config("train", [f"experiment={name}"], tmp_path)


def test_rows_are_told_apart_by_their_identity() -> None:
    for row in paper.ROWS.values():
        assert set(row.settings) <= set(paper.SETTING_KEYS) and set(row.identity) <= set(row.settings), row.name
        assert paper.classify(row.settings)[row.table - 1] == row.key  # no earlier row claims its settings
    f = dict(paper.TABLE1["f"].settings)
    assert paper.classify({**f, "anchors": "RenderedRandomAnchors"}) == ("h", None, False)
    assert paper.classify({**f, "num_negatives": 32, "loss": "NCELoss"}) == ("j", None, False)  # any M
    assert paper.classify({**f, "N": 2}) == (None, None, True)  # a Fig. 4 point only
    assert paper.classify({**f, "stn_on_negative": 1}) == (None, None, False)  # a flag is a bool, not 1
    assert paper.classify({**f, "model": "STNClassifierModule"}) == ("c", None, False)  # N=4 is all (c) needs
    assert paper.classify({"model": "MATLModule", "stn": False, "N": 1, "lam": 0.0}) == ("b", None, False)
    # on Table 2's data: row (f)'s configuration is Table 2 (or nothing), never Table 1 or Fig. 4
    assert paper.classify({**f, "N": 1, "data": "synthetic_ycb_table2/nonplanar"}) == (None, "d", False)
    assert paper.classify({**f, "data": "synthetic_ycb_table2/all"}) == (None, None, False)
    assert paper.classify({**f, "N": 2, "data": "synthetic_ycb_table2/planar"}) == (None, None, True)
    assert paper.classify({**f, "lam": 0.0, "data": "synthetic_ycb_table2/planar"}) == ("g", None, False)
    assert paper.classify({"baseline": "sift", "N": 2}) == (None, None, False)


def test_published_numbers() -> None:
    """Spot checks against the paper's Table 1 and Table 2, and their shape: every column, n/a only for TL's pose."""
    assert paper.TABLE1["f"].paper == {"ARC": ((0.93, 0.01), (0.66, 0.01)), "YCB": ((0.84, 0.01), (0.60, 0.01)),
                                       "APC": ((0.93, 0.01), (0.46, 0.01))}
    assert paper.TABLE1["c"].paper["YCB"] == ((0.82, 0.02), (6.13, 0.01))
    assert paper.TABLE1["j"].method == "Ours (NCE loss, λ=10, N=4)"
    assert paper.TABLE2["d"].paper == {"YCB": ((0.64, 0.01), (1.89, 0.03))}
    assert paper.TABLE2["a"].method == "Ours (planar)"
    assert list(paper.TABLE1) == list("abcdefghij") and list(paper.TABLE2) == list("abcd")
    for row in paper.TABLE1.values():
        assert tuple(row.paper) == paper.DATASETS
        assert all((pose is None) == (row.key == "b") and rec is not None for rec, pose in row.paper.values())
    assert set(paper.DATASET_COLUMN.values()) == set(paper.DATASETS)


def test_paper_imports_nothing_heavy() -> None:
    code = "import sys, matl.paper; print(sorted({'torch', 'numpy', 'omegaconf', 'hydra'} & set(sys.modules)))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0 and done.stdout.strip() == "[]", done.stderr


@pytest.mark.parametrize("model", ["matl", "matl_fast", "matl_camera", "tl", "stn_classifier"])
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


@pytest.mark.parametrize("data,at_paper,at_cpu", [
    ("synthetic_arc", 20000, 4000), ("synthetic_ycb", 25000, 5000),
    ("synthetic_apc", 10000, 2000), ("synthetic_ycb_table2", 25000, 5000)])
def test_scale_triplets_per_dataset(data: str, at_paper: int, at_cpu: int, tmp_path: Path) -> None:
    assert compose_config("train", ["scale=paper", f"data={data}"], tmp_path).data.train_triplets == at_paper
    assert compose_config("train", ["scale=cpu", f"data={data}"], tmp_path).data.train_triplets == at_cpu


@pytest.mark.parametrize("preset", PRESETS)
def test_presets(preset: str, tmp_path: Path) -> None:
    scale, _, data = preset.partition("_")
    cfg = compose_config("train", [f"experiment={preset}"], tmp_path)
    OmegaConf.resolve(cfg)
    catalog = data.removeprefix("synthetic_")
    assert cfg.data.source.catalog == catalog and dataset_name(cfg.data) == data
    assert paper.classify(paper_settings(cfg, data)) == ("f", None, True)
    assert cfg.trainer.max_epochs == (100 if scale == "paper" else 8)
    triplets = {"arc": 20000, "ycb": 25000, "apc": 10000}[catalog]
    assert cfg.data.train_triplets == (triplets if scale == "paper" else triplets // 5)


def test_command_line_wins_over_presets(tmp_path: Path) -> None:
    overrides = ["experiment=paper_synthetic_arc", "scale=cpu", "data=synthetic_apc", "trainer=default"]
    cfg = compose_config("train", overrides, tmp_path)
    assert cfg.data.source.catalog == "apc" and cfg.data.train_triplets == 2000 and cfg.trainer.max_epochs == 8
    assert cfg.model.appearance == "symmetric"  # scale=cpu keeps the CPU model defaults
    cfg = compose_config("train", ["experiment=table1_f", "N=9"], tmp_path)
    assert cfg.N == 9 and cfg.model.num_anchors == 9


@pytest.mark.parametrize("sweep,rows", [("table1", paper.TABLE1), ("table2", paper.TABLE2), ("fig4", None)])
def test_sweep_presets(sweep: str, rows: dict[str, paper.Row] | None) -> None:
    from hydra.types import RunMode

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", [f"+sweep={sweep}", "scale=cpu"], return_hydra_config=True)
    assert cfg.hydra.mode == RunMode.MULTIRUN
    seeds = f"range(0,{paper.SEEDS})"
    if rows is None:  # Fig. 4: row (f) with every N of the figure
        assert dict(cfg.hydra.sweeper.params) == {"N": ",".join(map(str, paper.FIG4_N)), "seed": seeds}
        assert cfg.hydra.runtime.choices.experiment == paper.TABLE1["f"].name
    else:  # every trained row of the table (rows (d) and (e) are evaluations)
        trained = ",".join(row.name for row in rows.values() if row.command == "train")
        assert dict(cfg.hydra.sweeper.params) == {"experiment": trained, "seed": seeds}


def test_slurm_launcher_composes_without_submitting(tmp_path: Path) -> None:
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
