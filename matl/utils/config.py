"""Config validation before any work: one clear line per problem, naming the key and valid values.

Every entry point calls :func:`validate_config` on its composed config before data or models are
built (train, render, eval on the run's saved config and on its own, predict), so a typo costs a
second, not a rendered dataset. Rules apply to the keys a config has: ``N`` is checked in a train
config, ``gallery_fill`` in a predict config. Unknown *group options* (``data=foo``) and unknown
keys never reach this module: Hydra rejects them while composing, and
:func:`matl.utils.errors.hydra_errors` turns its report into one line.

Only omegaconf is imported here: validation must stay cheap.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from matl.utils.errors import CONF_DIR, MatlError

#: the synthetic catalogs ``data.source.catalog`` can name, defined here so that validation reads them without
#: importing matl.data.catalog (seconds), which builds them: apc, arc and ycb are compositions of the paper's
#: datasets (matl.data.catalog.products.CATALOG_COMPOSITIONS); ycb_table2 is ycb split for Table 2 (11 simple and
#: 23 non-planar objects)
SYNTHETIC_CATALOGS = ("apc", "arc", "ycb", "ycb_table2")


class ConfigError(MatlError, ValueError):
    """A config value is invalid; the message names the key and what would be valid.

    A :class:`MatlError`, so entry points report it as one line (exit 2); still a ``ValueError``
    for callers that catch that.
    """


_MISSING = object()


def _get(cfg: DictConfig, dotted: str, default: Any = None) -> Any:
    """``cfg.<dotted>`` resolved; ``default`` if a part is absent or cannot be resolved in this config; a
    mandatory value left unset (``???``) is a :class:`ConfigError` naming the key."""
    node: Any = cfg
    for part in dotted.split("."):
        if not isinstance(node, DictConfig) or part not in node:
            return default
        try:
            node = node[part]
        except MissingMandatoryValue:
            raise ConfigError(f"{dotted} is not set: pass {dotted}=<value>") from None
        except OmegaConfBaseException:
            # e.g. data.num_anchors=${N} in render's config, which has no N and never reads it: a
            # value that cannot be resolved here is not checked here (its user resolves it or fails)
            return default
    return node


# ----------------------------------------------------------------------------------------- checks
def is_int(v: Any) -> bool:
    """An int that is not a bool (True is an int to Python, not to a user)."""
    return isinstance(v, int) and not isinstance(v, bool)  # True is an int to Python, not to a user


def is_number(v: Any) -> bool:
    """A finite int or float that is not a bool."""
    return (isinstance(v, (int, float)) and not isinstance(v, bool)) and math.isfinite(float(v))


def int_at_least(low: int) -> Callable[[Any], bool]:
    return lambda v: is_int(v) and v >= low


def number_at_least(low: float) -> Callable[[Any], bool]:
    return lambda v: is_number(v) and v >= low


def number_above(low: float) -> Callable[[Any], bool]:
    return lambda v: is_number(v) and v > low


def one_of(*values: Any) -> Callable[[Any], bool]:
    # `v is x or v == x` keeps True from matching 1 (and the reverse)
    return lambda v: any(v is x or (type(v) is type(x) and v == x) for x in values)


def fraction(v: Any) -> bool:
    return is_number(v) and 0.0 < v <= 1.0


def fraction_or_zero(v: Any) -> bool:
    return is_number(v) and 0 <= v <= 1


def is_bool(v: Any) -> bool:
    return isinstance(v, bool)


@dataclass(frozen=True)
class Rule:
    """``key`` must satisfy ``check`` when it is present and not null; ``valid`` is said to the user."""

    key: str
    check: Callable[[Any], bool]
    valid: str
    nullable: bool = True


RULES: tuple[Rule, ...] = (
    # the design card's short keys
    Rule("N", int_at_least(1), "an integer >= 1, the number of anchors per plane (e.g. N=4)"),
    Rule("lam", number_at_least(0), "a number >= 0, the appearance-loss weight (paper: lam=10)"),
    Rule("seed", int_at_least(0), "an integer >= 0 (it selects the split)"),
    Rule("test", is_bool, "true or false"),
    Rule("optimized_metric", one_of("val/score", "val/rec_acc", "val/pose_acc_5px"),
         "val/score, val/rec_acc or val/pose_acc_5px (checkpoint selection maximises it)"),
    # loss
    Rule("loss.fn.tau", number_above(0), "a number > 0, the NCE temperature (paper: 0.07)"),
    Rule("loss.fn.margin", number_at_least(0), "a number >= 0, the triplet margin (e.g. 0.2)"),
    Rule("loss.num_negatives", int_at_least(1), "an integer >= 1, M negatives per positive (paper: 64)"),
    # data
    Rule("data.image_size", int_at_least(16), "an integer >= 16, the model image side (paper: 100)"),
    Rule("data.batch_size", int_at_least(1), "an integer >= 1"),
    Rule("data.eval_batch_size", int_at_least(1), "an integer >= 1"),
    Rule("data.train_triplets", int_at_least(1), "an integer >= 1"),
    Rule("data.val_queries", int_at_least(1), "an integer >= 1"),
    Rule("data.test_queries", int_at_least(1), "an integer >= 1"),
    Rule("data.queries", one_of("warped", "rendered"), "warped (paper) or rendered (mesh-based data)"),
    Rule("data.source.fill", fraction, "a fraction in (0, 1] of the image the plane covers (catalogs: 0.6)"),
    Rule("data.source.supersample", int_at_least(1), "an integer >= 1"),
    Rule("data.source.subset", one_of("all", "planar", "nonplanar"), "all, planar or nonplanar"),
    Rule("data.occlude.p", fraction_or_zero, "a probability in [0, 1], the share of occluded training images"),
    Rule("data.occlude.leak_p", fraction_or_zero, "a probability in [0, 1]"),
    # model
    Rule("model.anchor_choice", one_of("feature", "appearance"), "feature (paper) or appearance"),
    Rule("model.stn.iterations", int_at_least(1), "an integer >= 1 (paper: 1)"),
    Rule("model.stn.max_condition", number_above(1), "a number > 1 (default 1e4)"),
    Rule("model.optimizer.lr", number_above(0), "a number > 0 (paper: 0.01)"),
    Rule("model.appearance_levels", int_at_least(1), "an integer >= 1 (paper: 1)"),
    # trainer and callbacks
    Rule("trainer.max_epochs", lambda v: is_int(v) and (v >= 1 or v == -1), "an integer >= 1 (or -1 with max_steps)"),
    Rule("trainer.accelerator", one_of("cpu", "gpu", "cuda", "mps", "tpu", "auto"), "cpu, gpu, cuda, mps, tpu or auto"),
    Rule("trainer.deterministic", one_of(True, False, "warn"), "true, false or warn"),
    Rule("callbacks.model_checkpoint.last_every_n_train_steps", int_at_least(0),
         "an integer >= 0 (0: last.ckpt only at the end of each epoch)"),
    # eval / predict
    Rule("device", one_of("cpu", "cuda", "auto"), "cpu, cuda or auto"),
    Rule("batch_size", int_at_least(1), "an integer >= 1"),
    Rule("gallery_fill", fraction, "a fraction in (0, 1]"),
    Rule("query_fill", fraction, "a fraction in (0, 1]"),
    Rule("timing_queries", int_at_least(0), "an integer >= 0"),
    Rule("foreground.retry_insets", lambda v: isinstance(v, (list, tuple, ListConfig)) and all(
        is_number(f) and 0 <= f < 0.5 for f in v),
         "a list of fractions of the crop's side in [0, 0.5) (foreground=grabcut: above 0), or []"),
    Rule("image_size", int_at_least(16), "an integer >= 16, or null (the checkpoint's size)"),
)

# The places that must hold the data's image size: the networks are built for it.
SIZE_KEYS = ("model.image_size", "model.stn.image_size", "model.stn.regressor.image_size",
             "model.feature_net.image_size")


def _show(value: Any) -> str:
    return repr(value) if isinstance(value, str) else str(value)


def check_scale_data(choices: Mapping[str, Any], conf_dir: Path = CONF_DIR) -> None:
    """A scale with per-dataset parts (``conf/scale/data/<scale>_<data>.yaml``, e.g. the paper's
    triplet counts) must have one for the chosen data: ``train.yaml`` includes the part with
    ``optional``, which would otherwise skip a missing one without a word (``scale=paper data=images``
    training at the default size). ``choices`` are the config groups' choices (Hydra's
    ``runtime.choices``); a scale without any per-dataset part (``smoke``) is not checked."""
    scale, data = choices.get("scale"), choices.get("data")
    if scale in (None, "null") or data in (None, "null"):
        return
    parts = conf_dir / "scale" / "data"
    if not any(parts.glob(f"{scale}_*.yaml")) or (parts / f"{scale}_{data}.yaml").is_file():
        return
    raise ConfigError(f"scale={scale} has no part for data={data}: create conf/scale/data/{scale}_{data}.yaml with "
                      f"the data keys this scale sets (e.g. train_triplets: <n>, as in {scale}_synthetic_arc.yaml)")


def _hydra_choices() -> dict[str, Any]:
    """The running Hydra app's config-group choices; empty outside one (a config composed in a test)."""
    from hydra.core.hydra_config import HydraConfig

    return dict(HydraConfig.get().runtime.choices) if HydraConfig.initialized() else {}


def validate_config(cfg: DictConfig) -> None:
    """Check the values every entry point relies on; raise :class:`ConfigError` on the first problem."""
    task = cfg.get("task_name") if isinstance(cfg, DictConfig) else None
    if task == "train":
        check_scale_data(_hydra_choices())
    for rule in RULES:
        value = _get(cfg, rule.key, _MISSING)
        if value is _MISSING:
            continue
        if value is None:
            if rule.key in ("N", "lam", "seed") and task == "train":
                raise ConfigError(f"{rule.key} is required: use {rule.valid}")
            continue
        if not rule.check(value):
            raise ConfigError(f"{rule.key}={_show(value)} is invalid: use {rule.valid}")

    target = str(_get(cfg, "data.source._target_") or "")
    catalog = _get(cfg, "data.source.catalog")
    if target.endswith("SyntheticCatalog") and catalog not in SYNTHETIC_CATALOGS:
        raise ConfigError(f"data.source.catalog={_show(catalog)} is invalid: use one of "
                          f"{', '.join(SYNTHETIC_CATALOGS)} (or pick a dataset with data=<name>)")

    size = _get(cfg, "data.image_size")
    for key in SIZE_KEYS:
        other = _get(cfg, key)
        if size is not None and other is not None and other != size:
            raise ConfigError(f"{key}={other} differs from data.image_size={size}: the networks are built for the "
                              f"data's size (leave {key} at its default ${{data.image_size}})")
    N = _get(cfg, "N")
    for key in ("model.num_anchors", "data.num_anchors"):
        other = _get(cfg, key)
        if N is not None and other is not None and other != N:
            raise ConfigError(f"{key}={other} differs from N={N}: set the number of anchors with N=<n> only")

    M = _get(cfg, "loss.num_negatives")
    batch = _get(cfg, "data.batch_size")
    if M is not None and batch is not None and M > 1 and 3 * batch - 2 < M:
        raise ConfigError(f"loss.num_negatives={M} needs data.batch_size >= {(M + 4) // 3}: negatives are "
                          f"drawn from the batch (got data.batch_size={batch})")
    triplets = _get(cfg, "data.train_triplets")
    if task == "train" and triplets is not None and batch is not None and triplets < batch:
        raise ConfigError(f"data.train_triplets={triplets} < data.batch_size={batch}: an epoch would have no "
                          "batch (incomplete batches are dropped); lower data.batch_size")

    source = _get(cfg, "data.source")
    if isinstance(source, DictConfig):
        missing = sorted(OmegaConf.missing_keys(source))
        if missing:  # full keys when the node has a parent (data.source.root), relative otherwise
            key = missing[0] if missing[0].startswith("data.source.") else f"data.source.{missing[0]}"
            raise ConfigError(f"{key} is not set: pass {key}=<path> (see docs/datasets.md)")

    init_from = _get(cfg, "init_from")
    if task == "train" and init_from not in (None, "", "pretrained", "pretrained_fast"):
        path = Path(str(init_from)).expanduser()
        if not path.is_file():
            raise ConfigError(f"init_from={path}: no such checkpoint file (a model to start from: a checkpoint path, "
                              "pretrained or pretrained_fast)")
    ckpt_path = _get(cfg, "ckpt_path")
    if task == "train" and ckpt_path not in (None, ""):
        path = Path(str(ckpt_path)).expanduser()
        if not path.is_file():
            raise ConfigError(f"ckpt_path={path}: no such checkpoint file (e.g. <run>/checkpoints/last.ckpt)")
