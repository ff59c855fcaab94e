"""Run folders and configs: a run's saved config, its checkpoints, a data group composed on its own."""

from __future__ import annotations

from pathlib import Path

import hydra
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from matl.utils.errors import CONF_DIR, MatlError


def hydra_choice(group: str) -> str | None:
    """The command line's choice for a config group (None outside a Hydra app)."""
    try:
        value = HydraConfig.get().runtime.choices.get(group)
    except ValueError:  # HydraConfig not set: called as a function, e.g. from tests
        return None
    return None if value in (None, "null") else str(value)


def load_run(run: str | Path) -> tuple[Path, DictConfig]:
    """A run folder and its saved config (``<run>/.hydra/config.yaml``)."""
    run_dir = Path(run).expanduser()
    if not run_dir.is_dir():
        raise MatlError(f"run={run_dir}: no such folder")
    path = run_dir / ".hydra" / "config.yaml"
    if not path.is_file():
        raise MatlError(f"run={run_dir} has no .hydra/config.yaml: eval needs the run's own saved config "
                        "(a folder written by python -m matl.train)")
    saved = OmegaConf.load(path)
    if not isinstance(saved, DictConfig) or "data" not in saved or "model" not in saved:
        raise MatlError(f"{path} has no data/model nodes: not a matl.train config")
    return run_dir, saved


def resolve_checkpoint(run_dir: Path | None, ckpt: str) -> Path:
    """``best`` / ``last`` inside the run's ``checkpoints/``, or a path."""
    if ckpt in ("best", "last"):
        if run_dir is None:
            raise MatlError(f"ckpt={ckpt} needs run=<run dir>")
        path = run_dir / "checkpoints" / f"{ckpt}.ckpt"
    else:
        path = Path(str(ckpt)).expanduser()
    if not path.is_file():
        raise MatlError(f"checkpoint {path} not found (ckpt=best|last|<path>)")
    return path


def compose_data_group(name: str) -> DictConfig:
    """The ``data=<name>`` node composed from ``conf/`` (a baseline with neither run= nor data=)."""
    overrides = [f"data={name}"]
    if GlobalHydra.instance().is_initialized():
        return hydra.compose(config_name="eval", overrides=overrides).data
    with hydra.initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra.compose(config_name="eval", overrides=overrides).data
