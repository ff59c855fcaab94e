"""Reading a run's saved configuration: keys that may not resolve, dataset names, and config fingerprints.

A run folder's ``.hydra/config.yaml`` is read as saved (never re-composed). Its interpolations may need
Hydra's runtime (``${hydra:runtime.output_dir}``), so every read here is tolerant: :func:`select` gives
the default for a key that does not resolve outside its own app.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

# config keys that never tell runs apart (the seed is what a group averages over)
IGNORED_KEYS = ("seed", "paths", "hydra", "ckpt_path", "resume", "test", "task_name", "logger", "callbacks",
                "run", "ckpt", "device", "timing_queries", "default_data")


def short(target: Any) -> Any:
    """``matl.models.module.MATLModule`` -> ``MATLModule`` (``matl.`` and ``torch.`` targets); others as they are."""
    return target.rsplit(".", 1)[-1] if isinstance(target, str) and target.startswith(("matl.", "torch.")) else target


def select(cfg: DictConfig | None, key: str, default: Any = None) -> Any:
    """``cfg.<key>`` (a dotted key), ``default`` when it is missing, null or does not resolve here."""
    if cfg is None:
        return default
    try:
        return OmegaConf.select(cfg, key, default=default, throw_on_missing=False)
    except Exception:  # an interpolation that only resolves inside its own app (e.g. ${hydra:...})
        return default


def number(value: Any) -> float | None:
    """``value`` as a float, None when it is not a number."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def dataset_name(data: DictConfig | None, choice: str | None = None) -> str:
    """A dataset's name as the ``data=`` choice spells it, plus its subset and query kind when not the default."""
    source = select(data, "source")
    target = str(select(source, "_target_", "") or "").rsplit(".", 1)[-1]
    catalog = select(source, "catalog")
    if target == "SyntheticCatalog" and catalog:
        name = f"synthetic_{catalog}"
    elif choice:
        name = str(choice)
    else:
        name = {"YCBSource": "ycb", "APCSource": "apc", "ARCSource": "arc", "MeshFolderSource": "meshes",
                "ImageFolderSource": "images"}.get(target, target or "?")
    subset = select(source, "subset")
    default_subset = "planar" if name == "synthetic_ycb" else "all"
    if name == "synthetic_ycb_table2" or (subset and subset != default_subset):
        name += f"/{subset or 'all'}"
    queries = select(data, "queries")
    if queries not in (None, "warped"):
        name += f"+{queries}"
    return name


def config_container(cfg: DictConfig, constants: Iterable[str] = ("seed",)) -> dict[str, Any]:
    """A run's config as plain containers, each top-level node resolved where it can be, so two runs whose
    settings resolve alike group together however they were written (``T_max: 8`` and
    ``T_max: ${trainer.max_epochs}`` with 8 epochs). A node that needs Hydra's runtime (the run folder)
    stays unresolved. The top-level ``constants`` (default: ``seed``) are set to 0 first: nodes that copy
    them (``data.seed: ${seed}``) must not split one configuration's seeds into groups."""
    cfg = cfg.copy()
    with open_dict(cfg):
        for key in constants:
            if key in cfg:
                cfg[key] = 0
    unresolved = OmegaConf.to_container(cfg, resolve=False)
    container: dict[str, Any] = {}
    for key in cfg:
        try:
            container[str(key)] = OmegaConf.to_container(cfg[key], resolve=True) if OmegaConf.is_config(cfg[key]) \
                else OmegaConf.select(cfg, str(key))
        except Exception:  # e.g. ${hydra:runtime.output_dir} outside a Hydra app
            container[str(key)] = unresolved[key]
    return container


def fingerprint(container: Any, drop: Iterable[str] = ()) -> str:
    """Short hash of a config container without :data:`IGNORED_KEYS` (and ``drop``)."""
    if isinstance(container, dict):
        container = {k: v for k, v in container.items() if k not in IGNORED_KEYS and k not in set(drop)}
        trainer = container.get("trainer")
        if isinstance(trainer, dict):
            container["trainer"] = {k: v for k, v in trainer.items() if k != "default_root_dir"}
    text = json.dumps(container, sort_keys=True, default=str)
    return hashlib.sha1(text.encode()).hexdigest()[:10]


def hydra_choices(run_dir: Path) -> dict[str, Any]:
    """The config group choices of a run (``<run>/.hydra/hydra.yaml``); empty when it has none."""
    hydra_file = run_dir / ".hydra" / "hydra.yaml"
    if not hydra_file.is_file():
        return {}
    return dict(OmegaConf.select(OmegaConf.load(hydra_file), "hydra.runtime.choices", default={}) or {})
