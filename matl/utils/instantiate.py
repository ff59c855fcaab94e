"""Building objects from ``_target_`` config nodes, with a config mistake reported as one line."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import hydra
from omegaconf import DictConfig

from matl.utils.errors import MatlError

if TYPE_CHECKING:
    import lightning as L


def instantiate_list(cfg: DictConfig | None) -> list[Any]:
    """Instantiate every ``_target_`` node of a dict config (callbacks, loggers)."""
    if not cfg:
        return []
    return [hydra.utils.instantiate(node) for node in cfg.values() if node is not None and "_target_" in node]


def instantiate_node(node: DictConfig, key: str) -> Any:
    """``hydra.utils.instantiate(node)``; a constructor's rejection of a config value becomes one line.

    Constructors check their arguments (``ValueError``: an unknown catalog, a negative ``lam``) and
    Python checks their names (``TypeError``: ``+data.foo=1``); those are the user's to fix, so they
    are reported as ``error: <key>: <reason>``. Anything else keeps its traceback (a bug).
    """
    from hydra.errors import InstantiationException

    try:
        return hydra.utils.instantiate(node)
    except InstantiationException as error:
        cause = error.__cause__
        user_fixable = isinstance(cause, (MatlError, ValueError, ImportError)) or (
            isinstance(cause, TypeError) and "argument" in str(cause))
        if cause is None or not user_fixable:
            raise
        reason = " ".join(str(cause).split()) or type(cause).__name__
        raise MatlError(f"{key}: {reason}") from error


def build(cfg: DictConfig) -> tuple[L.LightningDataModule, L.LightningModule]:
    """The datamodule and model of a train config (shared by train, eval and bench)."""
    datamodule = instantiate_node(cfg.data, "data")
    model = instantiate_node(cfg.model, "model")
    return datamodule, model
