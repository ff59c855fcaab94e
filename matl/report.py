"""``python -m matl.report <run or multirun dirs...> [--out DIR] [--fig2 DATA] [--fig5 SINGLE MATL]``.

Aggregates ``matl.train`` runs (``metrics.json``) and ``matl.eval`` runs (``eval.json``) found below
the given folders into the paper's tables and figures:

* **Table 1** (rows (a)-(j), columns ``rec_acc`` / ``pose_err`` per dataset ARC, YCB, APC) and
  **Table 2** (planar / non-planar synthetic YCB), mean ± std over seeds, the paper's numbers beside
  ours. A run's row is read from its *configuration* (its ``.hydra/config.yaml``), not from the
  ``experiment=`` it was launched with: ``experiment=table1_f N=2`` is a Fig. 4 point, not row (f).
  Rows (d) and (e) are ``matl.eval`` baseline runs (``experiment=table1_d|table1_e``).
* **Fig. 4** (``fig4.png``): ``rec_acc`` and ``pose_err`` against N, for the row-(f) configuration
  with any N (rows (a) and (f) are its N=1 and N=4 points).
* **Fig. 5** (``fig5.png``): from ``--fig5 SINGLE.ckpt MATL.ckpt``, or from a row (a) and a row (f)
  run found in the folders (same dataset and setting, preferably the same seed).
* **Fig. 2** (``fig2.png``): with ``--fig2 <data>``, the appearance loss against in-plane rotation of
  one canonical image of that catalog (no runs needed).

Runs are grouped by their full configuration minus the seed (and paths, loggers, resume keys),
so runs that differ in anything else never share a cell; a group's seeds are its samples (one run
per seed: a seed run twice counts once, the newest). Tables are split by *setting* (the ``scale=``
choice, image size, epochs and test-set size). Failed jobs (``failed.json``) and unfinished ones
are listed, never averaged. Writes ``report.md``, ``table.csv`` (one row per group, numeric mean
and std columns) and the PNG figures into ``--out`` (default: the first folder).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import os
import statistics
import sys
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

COLUMNS = ("rec_acc", "pose_err", "corner_err_px", "corner_err_px_median", "pose_acc_5px", "query_ms")
RESULT_FILES = ("metrics.json", "eval.json", "failed.json")
PAPER_DATASETS = ("ARC", "YCB", "APC")
# our dataset names -> the paper's column (synthetic stand-ins and the user's real meshes)
PAPER_COLUMN = {"synthetic_arc": "ARC", "arc": "ARC", "synthetic_ycb": "YCB", "ycb/planar": "YCB",
                "synthetic_apc": "APC", "apc": "APC"}

Stat = tuple[float, float] | None  # (mean, std) of the paper, None = n/a
# Table 1 of the paper: row -> (method, {dataset: (rec_acc, pose_err)})
PAPER_TABLE1: dict[str, tuple[str, dict[str, tuple[Stat, Stat]]]] = {
    "a": ("[28] (single anchor, N=1)", {"ARC": ((0.84, 0.01), (1.86, 0.01)), "YCB": ((0.72, 0.01), (1.88, 0.01)),
                                        "APC": ((0.84, 0.01), (1.90, 0.01))}),
    "b": ("TL [29]", {"ARC": ((0.87, 0.01), None), "YCB": ((0.78, 0.01), None), "APC": ((0.88, 0.01), None)}),
    "c": ("STN [15]", {"ARC": ((0.88, 0.02), (2.80, 0.16)), "YCB": ((0.82, 0.02), (6.13, 0.01)),
                       "APC": ((0.92, 0.04), (2.68, 0.53))}),
    "d": ("SIFT+RANSAC [20, 13]", {"ARC": ((0.82, 0.02), (0.63, 0.05)), "YCB": ((0.80, 0.03), (0.64, 0.19)),
                                   "APC": ((0.87, 0.01), (0.50, 0.02))}),
    "e": ("SuperPoint+RANSAC [12, 13]", {"ARC": ((0.83, 0.01), (0.66, 0.03)), "YCB": ((0.82, 0.01), (0.64, 0.03)),
                                         "APC": ((0.90, 0.01), (0.51, 0.03))}),
    "f": ("Ours (multiple anchors, λ=10, N=4)", {"ARC": ((0.93, 0.01), (0.66, 0.01)),
                                                 "YCB": ((0.84, 0.01), (0.60, 0.01)),
                                                 "APC": ((0.93, 0.01), (0.46, 0.01))}),
    "g": ("Ours (λ=0, N=4)", {"ARC": ((0.88, 0.01), (1.70, 0.02)), "YCB": ((0.78, 0.01), (1.75, 0.03)),
                              "APC": ((0.89, 0.01), (1.68, 0.04))}),
    "h": ("Ours (random-position anchors, λ=10, N=4)", {"ARC": ((0.87, 0.01), (1.64, 0.01)),
                                                        "YCB": ((0.74, 0.01), (1.65, 0.01)),
                                                        "APC": ((0.91, 0.01), (1.59, 0.01))}),
    "i": ("Ours (no STN in negative, λ=10, N=4)", {"ARC": ((0.93, 0.01), (0.67, 0.03)),
                                                   "YCB": ((0.83, 0.01), (0.63, 0.01)),
                                                   "APC": ((0.93, 0.01), (0.53, 0.01))}),
    "j": ("Ours (NCE loss, λ=10, N=4)", {"ARC": ((0.94, 0.01), (0.67, 0.02)), "YCB": ((0.89, 0.01), (0.61, 0.02)),
                                         "APC": ((0.97, 0.01), (0.52, 0.02))}),
}
# Table 2 of the paper: row -> (method, rec_acc, pose_err)
PAPER_TABLE2: dict[str, tuple[str, Stat, Stat]] = {
    "a": ("Ours (planar)", (0.91, 0.02), (0.57, 0.03)),
    "b": ("[28] (planar)", (0.78, 0.02), (1.86, 0.04)),
    "c": ("Ours (non-planar)", (0.81, 0.02), (0.68, 0.05)),
    "d": ("[28] (non-planar)", (0.64, 0.01), (1.89, 0.03)),
}
BASELINE_ROWS = {"sift": "d", "superpoint": "e"}
BASELINE_METHODS = {"sift": "SIFT+RANSAC [20, 13]", "superpoint": "SuperPoint+RANSAC [12, 13]",
                    "lightglue": "ALIKED+LightGlue+RANSAC (beyond the paper)"}
# config keys that never tell runs apart (the seed is what a group averages over)
IGNORED_KEYS = ("seed", "paths", "hydra", "ckpt_path", "resume", "test", "task_name", "logger", "callbacks",
                "run", "ckpt", "device", "timing_queries", "default_data")


# ------------------------------------------------------------------------------------ one run
@dataclass
class Run:
    """One run folder: what it is, its metrics and its place in the paper's tables."""

    path: Path
    status: str                      # done | failed | incomplete
    kind: str                        # train | baseline | eval (a checkpoint re-evaluated)
    metrics: dict[str, Any]
    seed: int | None
    dataset: str                     # synthetic_arc, synthetic_ycb_table2/planar, ...
    label: str                       # the distinguishing settings, for humans
    fingerprint: str                 # the configuration minus the seed
    setting: tuple[Any, ...] = ()    # (scale, image size, epochs, test queries) of a training
    table1: str | None = None        # a..j
    table2: str | None = None        # a..d
    fig4: tuple[str, int] | None = None   # (fingerprint without N, N) of the row-(f) family
    reason: str | None = None        # a failed run's one-line reason
    mtime: float = 0.0
    method: str | None = None        # an evaluation's method name for the methods table

    @property
    def paper_column(self) -> str | None:
        return PAPER_COLUMN.get(self.dataset)

    @property
    def checkpoint(self) -> Path | None:
        rel = self.metrics.get("checkpoint")
        for path in ([self.path / rel] if rel else []) + [self.path / "checkpoints" / "best.ckpt"]:
            if path.is_file():
                return path
        return None


def find_runs(roots: Sequence[Path]) -> list[Path]:
    """Run folders below ``roots``: those with results or a failure, and started ones (``.hydra/``)."""
    found: set[Path] = set()
    for root in roots:
        if not root.exists():
            raise FileNotFoundError(f"{root} does not exist; pass run or multirun folders of matl.train/eval")
        for name in RESULT_FILES:
            found.update(p.parent for p in root.rglob(name) if ".submitit" not in p.parts)
        found.update(p.parent for p in root.rglob(".hydra") if (p / "config.yaml").is_file())
    return sorted(found)


def _short(target: Any) -> Any:
    return target.rsplit(".", 1)[-1] if isinstance(target, str) and target.startswith(("matl.", "torch.")) else target


def _select(cfg: DictConfig | None, key: str, default: Any = None) -> Any:
    if cfg is None:
        return default
    try:
        return OmegaConf.select(cfg, key, default=default, throw_on_missing=False)
    except Exception:  # an interpolation that only resolves inside its own app (e.g. ${hydra:...})
        return default


def dataset_name(data: DictConfig | None, choice: str | None = None) -> str:
    """A dataset's name as the ``data=`` choice spells it, plus its subset and query kind when not the default."""
    source = _select(data, "source")
    target = str(_select(source, "_target_", "") or "").rsplit(".", 1)[-1]
    catalog = _select(source, "catalog")
    if target == "SyntheticCatalog" and catalog:
        name = f"synthetic_{catalog}"
    elif choice:
        name = str(choice)
    else:
        name = {"YCBSource": "ycb", "APCSource": "apc", "ARCSource": "arc", "MeshFolderSource": "meshes",
                "ImageFolderSource": "images"}.get(target, target or "?")
    subset = _select(source, "subset")
    default_subset = "planar" if name == "synthetic_ycb" else "all"
    if name == "synthetic_ycb_table2" or (subset and subset != default_subset):
        name += f"/{subset or 'all'}"
    queries = _select(data, "queries")
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


def _num(value: Any) -> float | None:
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def classify_training(cfg: DictConfig, dataset: str) -> tuple[str | None, str | None, bool]:
    """``(Table 1 row, Table 2 row, in Fig. 4's family)`` of a training config (see the module docstring)."""
    model = _short(_select(cfg, "model._target_"))
    N, lam = _select(cfg, "N"), _num(_select(cfg, "lam"))
    if model == "STNClassifierModule":
        return ("c" if N == 4 else None), None, False
    if model != "MATLModule":
        return None, None, False
    if _select(cfg, "model.stn") is None:
        return ("b" if N == 1 else None), None, False
    loss = _short(_select(cfg, "loss.fn._target_"))
    anchors = _short(_select(cfg, "anchors._target_"))
    negative = _select(cfg, "model.stn_on_negative", True)
    triplet, fixed = loss == "TripletLoss", anchors == "FixedAnchors"
    family = triplet and fixed and negative is True and lam == 10.0
    if dataset.startswith("synthetic_ycb_table2/") and family and N in (1, 4):
        subset = dataset.split("/", 1)[1]
        rows = {("planar", 4): "a", ("planar", 1): "b", ("nonplanar", 4): "c", ("nonplanar", 1): "d"}
        return None, rows.get((subset, N)), False
    row = None
    if family and N in (1, 4):
        row = "a" if N == 1 else "f"
    elif N == 4 and triplet and fixed and negative is True and lam == 0.0:
        row = "g"
    elif N == 4 and triplet and anchors in ("RandomAnchors", "RenderedRandomAnchors") and negative is True \
            and lam == 10.0:
        row = "h"
    elif N == 4 and triplet and fixed and negative is False and lam == 10.0:
        row = "i"
    elif N == 4 and loss == "NCELoss" and fixed and negative is True and lam == 10.0:
        row = "j"
    return row, None, family


def describe(cfg: DictConfig | None, kind: str, metrics: dict[str, Any]) -> str:
    """The settings that tell a group apart, e.g. ``MATLModule, N=4, lam=10.0, TripletLoss, FixedAnchors``."""
    if kind == "baseline":
        return f"baseline={metrics.get('baseline') or _select(cfg, 'baseline._target_', '?')}, N={metrics.get('N')}"
    parts = []
    model = _short(_select(cfg, "model._target_"))
    if model:
        parts.append(str(model) + (" (no STN)" if model == "MATLModule" and _select(cfg, "model.stn") is None else ""))
    for key, name in (("N", "N"), ("lam", "lam"), ("loss.fn._target_", "loss"), ("anchors._target_", "anchors"),
                      ("model.stn_on_negative", "stn_on_negative"), ("model.appearance", "appearance"),
                      ("model.appearance_levels", "levels"), ("model.stn.iterations", "stn_steps")):
        value = _select(cfg, key)
        if value is not None:
            parts.append(f"{name}={_short(value)}")
    if kind == "eval":
        parts.append(f"eval of {metrics.get('run') or '?'}")
    return ", ".join(parts)


def hydra_choices(run_dir: Path) -> dict[str, Any]:
    """The config group choices of a run (``<run>/.hydra/hydra.yaml``); empty when it has none."""
    hydra_file = run_dir / ".hydra" / "hydra.yaml"
    if not hydra_file.is_file():
        return {}
    return dict(OmegaConf.select(OmegaConf.load(hydra_file), "hydra.runtime.choices", default={}) or {})


def evaluation_method(kind: str, metrics: dict[str, Any], baseline: str) -> str:
    """The method a ``matl.eval`` run evaluated, named as in Table 1 where it is a Table 1 row.

    A checkpoint evaluation is named from the evaluated training run's own saved config (its row of
    Table 1, else its distinguishing settings); ``+ refinement`` marks ``refine=true``.
    """
    if kind == "baseline":
        name = BASELINE_METHODS.get(baseline, baseline)
        return f"{name}, N={metrics.get('N')}" if metrics.get("N") not in (None, 4) else name
    name = f"eval of {metrics.get('run') or '?'}"
    cfg_file = Path(str(metrics.get("run"))) / ".hydra" / "config.yaml"
    if metrics.get("run") and cfg_file.is_file():
        cfg = OmegaConf.load(cfg_file)
        choices = hydra_choices(cfg_file.parent.parent)
        row = classify_training(cfg, dataset_name(_select(cfg, "data"), choices.get("data")))[0]
        name = f"({row}) {PAPER_TABLE1[row][0]}" if row else describe(cfg, "train", {})
    return name + (" + refinement" if metrics.get("refine") else "")


def load_run(path: Path) -> Run:
    """Read one run folder (see :class:`Run`)."""
    cfg_file = path / ".hydra" / "config.yaml"
    cfg = OmegaConf.load(cfg_file) if cfg_file.is_file() else None
    choices = hydra_choices(path)
    metrics: dict[str, Any] = {}
    status, reason, mtime = "incomplete", None, 0.0
    for name in ("eval.json", "metrics.json"):
        if (path / name).is_file():
            metrics, status, mtime = json.loads((path / name).read_text()), "done", (path / name).stat().st_mtime
            break
    else:
        if (path / "failed.json").is_file():
            failed = json.loads((path / "failed.json").read_text())
            status, reason, mtime = "failed", str(failed.get("reason", "?")), (path / "failed.json").stat().st_mtime
    is_eval = (path / "eval.json").is_file() or _select(cfg, "task_name") == "eval"
    container = config_container(cfg) if cfg is not None else {"run": path.name}
    if is_eval:
        baseline = metrics.get("baseline") or choices.get("baseline")
        if baseline is None and _select(cfg, "baseline._target_") is not None:  # a run without eval.json
            baseline = _short(_select(cfg, "baseline._target_"))
        kind = "baseline" if (metrics.get("evaluated") == "baseline" or (not metrics and baseline)) else "eval"
        data = _select(cfg, "data")
        dataset = dataset_name(data, choices.get("data") or metrics.get("data") or _select(cfg, "default_data"))
        seed = metrics.get("seed", _select(cfg, "seed"))
        N = metrics.get("N", _select(cfg, "N"))
        setting: tuple[Any, ...] = (None, metrics.get("image_size", _select(cfg, "data.image_size", 100)), None,
                                    metrics.get("num_queries", _select(cfg, "data.test_queries", 1000)))
        fp = fingerprint({**container, "N": N, "baseline_name": baseline, "dataset": dataset,
                          "evaluated_run": metrics.get("run")})
        run = Run(path, status, kind, metrics, seed, dataset, describe(cfg, kind, metrics), fp, setting,
                  reason=reason, mtime=mtime)
        if kind == "baseline" and N == 4:
            run.table1 = BASELINE_ROWS.get(str(baseline))
        run.method = evaluation_method(kind, metrics, str(baseline))
        return run
    dataset = dataset_name(_select(cfg, "data"), choices.get("data"))
    setting = (choices.get("scale"), _select(cfg, "data.image_size"), _select(cfg, "trainer.max_epochs"),
               _select(cfg, "data.test_queries"))
    run = Run(path, status, "train", metrics, metrics.get("seed", _select(cfg, "seed")), dataset,
              describe(cfg, "train", metrics), fingerprint(container), setting, reason=reason, mtime=mtime)
    if cfg is not None:
        run.table1, run.table2, family = classify_training(cfg, dataset)
        if family:
            run.fig4 = (fingerprint(config_container(cfg, ("seed", "N")), drop=("N",)), int(_select(cfg, "N")))
    return run


# ------------------------------------------------------------------------------------ groups
@dataclass
class Group:
    """Runs of one configuration (all seeds): the unit of a table cell."""

    runs: list[Run]                                   # done runs, one per seed (the newest)
    failed: list[Run] = field(default_factory=list)
    incomplete: list[Run] = field(default_factory=list)
    duplicates: int = 0                               # older runs of an already counted seed

    @property
    def first(self) -> Run:
        return (self.runs or self.failed or self.incomplete)[0]

    @property
    def seeds(self) -> list[Any]:
        return sorted((r.seed for r in self.runs if r.seed is not None), key=str)

    def values(self, metric: str) -> list[float]:
        out = []
        for run in self.runs:
            value = run.metrics.get(metric)
            out.append(float(value) if value is not None else math.nan)
        return out

    def stat(self, metric: str) -> tuple[float, float, int] | None:
        """``(mean, sample std, n)`` over the seeds with a finite value; None when there are none."""
        values = [v for v in self.values(metric) if math.isfinite(v)]
        if not values:
            return None
        std = statistics.stdev(values) if len(values) > 1 else 0.0
        return statistics.mean(values), std, len(values)


def group_runs(runs: Iterable[Run]) -> list[Group]:
    """Group by (kind, dataset, configuration); per seed keep the newest finished run."""
    buckets: dict[tuple[str, str, str], list[Run]] = defaultdict(list)
    for run in runs:
        buckets[(run.kind, run.dataset, run.fingerprint)].append(run)
    groups = []
    for members in buckets.values():
        done = sorted((r for r in members if r.status == "done"), key=lambda r: r.mtime, reverse=True)
        kept: dict[Any, Run] = {}
        duplicates = 0
        for run in done:
            key = run.seed if run.seed is not None else id(run)
            if key in kept:
                duplicates += 1
            else:
                kept[key] = run
        done_seeds = set(kept)
        groups.append(Group(runs=sorted(kept.values(), key=lambda r: str(r.seed)),
                            failed=[r for r in members if r.status == "failed" and r.seed not in done_seeds],
                            incomplete=[r for r in members if r.status == "incomplete" and r.seed not in done_seeds],
                            duplicates=duplicates))
    return sorted(groups, key=lambda g: (g.first.kind, g.first.dataset, g.first.label))


# ------------------------------------------------------------------------------------ formatting
def fmt_stat(stat: tuple[float, float, int] | None, digits: int = 3) -> str:
    """``mean ± std (n)``; ``n/a`` without values."""
    if stat is None:
        return "n/a"
    mean, std, n = stat
    return f"{mean:.{digits}f} ± {std:.{digits}f} ({n})" if n > 1 else f"{mean:.{digits}f} (1)"


def fmt_paper(stat: Stat) -> str:
    return "n/a" if stat is None else f"{stat[0]:.2f} ± {stat[1]:.2f}"


def mean_std(values: list[float]) -> str:
    """``mean ± std`` of the finite values (kept for callers of the first version)."""
    values = [v for v in values if v is not None and not math.isnan(v)]
    if not values:
        return "n/a"
    if len(values) == 1:
        return f"{values[0]:.3f}"
    return f"{statistics.mean(values):.3f} ± {statistics.stdev(values):.3f}"


def setting_label(setting: tuple[Any, ...]) -> str:
    scale, size, epochs, test = setting
    parts = [f"scale={scale}"] if scale else ["no scale= preset"]
    parts += [f"{size} px", f"{epochs} epochs", f"{test} test queries"]
    return ", ".join(str(p) for p in parts)


def _pick(groups: list[Group]) -> tuple[Group | None, int]:
    """The group with most seeds, and how many other configurations competed for the same cell."""
    candidates = [g for g in groups if g.runs]
    if not candidates:
        return None, 0
    best = max(candidates, key=lambda g: (len(g.runs), g.first.mtime))
    return best, len(candidates) - 1


def _baseline_matches(group: Group, setting: tuple[Any, ...]) -> bool:
    """Baselines are not trained: they join every setting with the same image size and test queries."""
    return group.first.setting[1] == setting[1] and group.first.setting[3] == setting[3]


@dataclass
class Cell:
    group: Group | None
    others: int


def table1_cells(groups: list[Group], setting: tuple[Any, ...]) -> dict[tuple[str, str], Cell]:
    cells = {}
    for row in PAPER_TABLE1:
        for column in PAPER_DATASETS:
            members = [g for g in groups if g.first.table1 == row and g.first.paper_column == column
                       and (g.first.setting == setting if g.first.kind == "train" else _baseline_matches(g, setting))]
            cells[(row, column)] = Cell(*_pick(members))
    return cells


def table2_cells(groups: list[Group], setting: tuple[Any, ...]) -> dict[str, Cell]:
    return {row: Cell(*_pick([g for g in groups if g.first.table2 == row and g.first.setting == setting]))
            for row in PAPER_TABLE2}


def fig4_series(groups: list[Group], setting: tuple[Any, ...]) -> dict[str, dict[int, Group]]:
    """``{dataset: {N: group}}`` of Fig. 4's family (row f's configuration with any N) in a setting."""
    families: dict[tuple[str, str], dict[int, Group]] = defaultdict(dict)
    for group in groups:
        run = group.first
        if run.fig4 is None or not group.runs or run.setting != setting:
            continue
        family, N = run.fig4
        current = families[(run.dataset, family)].get(N)
        if current is None or len(group.runs) > len(current.runs):
            families[(run.dataset, family)][N] = group
    series: dict[str, dict[int, Group]] = {}
    for (dataset, _), points in sorted(families.items(), key=lambda kv: -len(kv[1])):
        if dataset not in series and len(points) >= 2:  # one family per dataset: the one with most N values
            series[dataset] = points
    order = {name: i for i, name in enumerate(["synthetic_arc", "arc", "synthetic_ycb", "ycb/planar", "synthetic_apc",
                                               "apc"])}
    return dict(sorted(series.items(), key=lambda kv: (order.get(kv[0], 99), kv[0])))


# ------------------------------------------------------------------------------------ report
def settings_of(groups: list[Group]) -> list[tuple[Any, ...]]:
    found = {g.first.setting for g in groups if g.first.kind == "train"
             and (g.first.table1 or g.first.table2 or g.first.fig4)}
    if not found:  # only baselines: one table per (image size, test queries)
        found = {(None, g.first.setting[1], None, g.first.setting[3]) for g in groups if g.first.table1}
    return sorted(found, key=lambda s: tuple(str(x) for x in s))


def _table1_md(cells: dict[tuple[str, str], Cell]) -> list[str]:
    header = ["row", "method"]
    for column in PAPER_DATASETS:
        header += [f"{column} rec_acc", "(paper)", f"{column} pose_err", "(paper)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    notes = []
    for row, (method, paper) in PAPER_TABLE1.items():
        cols = [f"({row})", method]
        for column in PAPER_DATASETS:
            cell = cells[(row, column)]
            rec = cell.group.stat("rec_acc") if cell.group else None
            pose = cell.group.stat("pose_err") if cell.group else None
            mark = "" if not cell.others else "*"
            cols += [("—" if cell.group is None else fmt_stat(rec)) + mark, fmt_paper(paper[column][0]),
                     ("—" if cell.group is None else fmt_stat(pose)) + mark, fmt_paper(paper[column][1])]
            if cell.others:
                notes.append(f"({row}) {column}: {cell.others} other configuration(s) match this cell; "
                             f"shown: {cell.group.first.label} ({cell.group.first.path.parent})")
        lines.append("| " + " | ".join(cols) + " |")
    return lines + ([""] + [f"\\* {n}" for n in notes] if notes else [])


def _table2_md(cells: dict[str, Cell]) -> list[str]:
    header = ["row", "method", "rec_acc", "(paper)", "pose_err", "(paper)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row, (method, rec_paper, pose_paper) in PAPER_TABLE2.items():
        group = cells[row].group
        lines.append("| " + " | ".join([
            f"({row})", method, "—" if group is None else fmt_stat(group.stat("rec_acc")), fmt_paper(rec_paper),
            "—" if group is None else fmt_stat(group.stat("pose_err")), fmt_paper(pose_paper)]) + " |")
    return lines


def _fig4_md(series: dict[str, dict[int, Group]]) -> list[str]:
    lines = ["| dataset | N | rec_acc | pose_err | pose_acc_5px |", "|---|---|---|---|---|"]
    for dataset, points in series.items():
        for N in sorted(points):
            g = points[N]
            lines.append(f"| {dataset} | {N} | {fmt_stat(g.stat('rec_acc'))} | {fmt_stat(g.stat('pose_err'))} | "
                         f"{fmt_stat(g.stat('pose_acc_5px'))} |")
    return lines


def _methods_md(groups: list[Group]) -> list[str]:
    """Every evaluated method (``matl.eval`` of checkpoints and baselines), per dataset and query set."""
    evals = [g for g in groups if g.runs and g.first.kind in ("eval", "baseline")]
    if not evals:
        return []
    lines = ["## Methods on the same test queries (matl.eval)", "",
             "One row per evaluated method; rows of one table share their test queries (dataset, split seed, "
             "number of queries). n/a: the method has no pose. query_ms: median of single-query calls, "
             "batch of 1, gallery of all anchors.", ""]
    by_queries: dict[tuple[str, str, Any], list[Group]] = defaultdict(list)
    for g in evals:
        by_queries[(g.first.dataset, " ".join(map(str, g.seeds)), g.first.metrics.get("num_queries"))].append(g)
    header = ["method", "rec_acc", "pose_err", "median corner_err_px", "pose_acc_5px", "query_ms", "seeds"]
    for (dataset, seeds, queries), members in sorted(by_queries.items(), key=lambda kv: tuple(map(str, kv[0]))):
        lines += [f"{dataset}, split seed(s) {seeds}, {queries} queries:", "",
                  "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for g in sorted(members, key=lambda g: (g.first.method or g.first.label)):
            cols = [g.first.method or g.first.label]
            cols += [fmt_stat(g.stat(m)) for m in ("rec_acc", "pose_err", "corner_err_px_median", "pose_acc_5px",
                                                    "query_ms")]
            lines.append("| " + " | ".join([*cols, seeds]) + " |")
        lines.append("")
    return lines


def csv_rows(groups: list[Group]) -> list[dict[str, Any]]:
    """``table.csv``: one row per group, numeric mean / std columns, its role in the paper's tables."""
    rows = []
    for group in groups:
        run = group.first
        row: dict[str, Any] = {
            "kind": run.kind, "dataset": run.dataset, "config": run.label, "fingerprint": run.fingerprint,
            "setting": setting_label(run.setting) if run.kind == "train" else "",
            "table1_row": run.table1 or "", "table2_row": run.table2 or "",
            "fig4_N": run.fig4[1] if run.fig4 else "", "runs": len(group.runs),
            "seeds": " ".join(str(s) for s in group.seeds), "failed": len(group.failed),
            "incomplete": len(group.incomplete), "folder": str(run.path.parent)}
        for column in COLUMNS:
            stat = group.stat(column)
            row[f"{column}_mean"] = "" if stat is None else f"{stat[0]:.6g}"
            row[f"{column}_std"] = "" if stat is None else f"{stat[1]:.6g}"
        paper_rec: Stat = None
        paper_pose: Stat = None
        if run.table1 and run.paper_column:
            paper_rec, paper_pose = PAPER_TABLE1[run.table1][1][run.paper_column]
        elif run.table2:
            _, paper_rec, paper_pose = PAPER_TABLE2[run.table2]
        row.update(paper_rec_acc_mean="" if paper_rec is None else paper_rec[0],
                   paper_rec_acc_std="" if paper_rec is None else paper_rec[1],
                   paper_pose_err_mean="" if paper_pose is None else paper_pose[0],
                   paper_pose_err_std="" if paper_pose is None else paper_pose[1])
        rows.append(row)
    return rows


@dataclass
class Report:
    """What :func:`build_report` produced (paths of the files written)."""

    out: Path
    files: list[Path]
    groups: list[Group]
    warnings: list[str]


def find_fig5_pair(groups: list[Group]) -> tuple[Path, Path] | None:
    """Checkpoints of a row (a) and a row (f) run of one dataset and setting, the same seed when possible."""
    rank = {column: i for i, column in enumerate(PAPER_DATASETS)}  # ARC first, as the paper's Fig. 5
    rows_f = sorted((g for g in groups if g.first.table1 == "f" and g.first.kind == "train"),
                    key=lambda g: rank.get(g.first.paper_column or "", len(rank)))
    for f_group in rows_f:
        for a_group in [g for g in groups if g.first.table1 == "a" and g.first.kind == "train"
                        and g.first.dataset == f_group.first.dataset and g.first.setting == f_group.first.setting]:
            a_runs = {r.seed: r for r in a_group.runs if r.checkpoint}
            f_runs = [r for r in f_group.runs if r.checkpoint]
            same = [r for r in f_runs if r.seed in a_runs]
            if same:
                return a_runs[same[0].seed].checkpoint, same[0].checkpoint  # type: ignore[return-value]
            if f_runs and a_runs:
                return next(iter(a_runs.values())).checkpoint, f_runs[0].checkpoint  # type: ignore[return-value]
    return None


def build_report(dirs: Sequence[Path], out: Path, fig5: Sequence[Path] | None = None, auto_fig5: bool = True,
                 fig2_data: str | None = None, fig2_plane: str | None = None, fig2_size: int = 100,
                 cache_dir: str | None = None) -> Report:
    """Everything ``python -m matl.report`` does; returns the files written."""
    out.mkdir(parents=True, exist_ok=True)
    runs = [load_run(p) for p in find_runs(list(dirs))]
    groups = group_runs(runs)
    files: list[Path] = []
    warnings: list[str] = []
    lines = ["# matl report", "", "Sources: " + (", ".join(f"`{d}`" for d in dirs) or "none"), "",
             "Cells: mean ± sample std over seeds, (k) = number of seeds; — = no run; "
             "(paper) = the paper's Table 1 / Table 2. Our datasets are the synthetic stand-ins of "
             "DESIGN §4 unless the run used the real meshes; absolute numbers are not expected to match "
             "the paper's, the ordering of the rows is what the reproduction checks.", ""]
    for setting in settings_of(groups):
        cells1 = table1_cells(groups, setting)
        if any(c.group for c in cells1.values()):
            lines += [f"## Table 1 ({setting_label(setting)})", "", *_table1_md(cells1), ""]
        cells2 = table2_cells(groups, setting)
        if any(c.group for c in cells2.values()):
            lines += [f"## Table 2 ({setting_label(setting)})", "", "Synthetic YCB, Table 2 split "
                      "(11 simple objects / 23 non-planar).", "", *_table2_md(cells2), ""]
        series = fig4_series(groups, setting)
        if series:
            from matl.reporting.figures import Point, plot_fig4

            name = "fig4.png" if not any(p.name == "fig4.png" for p in files) else f"fig4_{len(files)}.png"
            points = {d: {n: {m: Point(*s) for m in ("rec_acc", "pose_err") if (s := g.stat(m)) is not None}
                          for n, g in pts.items()} for d, pts in series.items()}
            files.append(plot_fig4(points, out / name))
            lines += [f"## Fig. 4 ({setting_label(setting)}): performance against N", "", f"![Fig. 4]({name})", "",
                      *_fig4_md(series), ""]
    pair = tuple(fig5) if fig5 else (find_fig5_pair(groups) if auto_fig5 else None)
    if pair:
        try:
            from matl.reporting.figures import fig5_panels, plot_fig5

            files.append(plot_fig5(fig5_panels(pair[0], pair[1]), out / "fig5.png"))
            lines += ["## Fig. 5: qualitative examples", "", f"Single-anchor checkpoint `{pair[0]}`, MATL checkpoint "
                      f"`{pair[1]}`.", "", "![Fig. 5](fig5.png)", ""]
        except Exception as error:  # a figure must not cost the tables; say why it is missing
            if fig5:
                raise
            warnings.append(f"Fig. 5 skipped: {type(error).__name__}: {error}")
    if fig2_data:
        path, caption = write_fig2(out / "fig2.png", fig2_data, fig2_plane, fig2_size, cache_dir)
        files.append(path)
        lines += ["## Fig. 2: appearance loss against in-plane rotation", "", caption, "", "![Fig. 2](fig2.png)", ""]

    lines += _methods_md(groups)
    header = ["config", "dataset", "kind", "runs", "seeds", *COLUMNS]
    lines += ["## All groups", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for g in groups:
        if not g.runs:
            continue
        r = g.first
        lines.append("| " + " | ".join([r.label, r.dataset, r.kind, str(len(g.runs)), " ".join(map(str, g.seeds)),
                                        *[fmt_stat(g.stat(c)) for c in COLUMNS]]) + " |")
    failed = [r for g in groups for r in g.failed]
    incomplete = [r for g in groups for r in g.incomplete]
    if failed:
        lines += ["", "## Failed runs (not averaged)", ""] + [f"- `{r.path}`: {r.reason}" for r in failed]
    if incomplete:
        lines += ["", "## Unfinished runs (no metrics yet)", ""] + [f"- `{r.path}`" for r in incomplete]
    duplicates = sum(g.duplicates for g in groups)
    if duplicates:
        warnings.append(f"{duplicates} older run(s) of an already counted seed were ignored (newest kept)")
    if warnings:
        lines += ["", "## Notes", ""] + [f"- {w}" for w in warnings]
    report_md = out / "report.md"
    report_md.write_text("\n".join(lines) + "\n")
    rows = csv_rows(groups)
    table_csv = out / "table.csv"
    with table_csv.open("w", newline="") as f:
        fieldnames = list(rows[0]) if rows else ["kind", "dataset", "config"]
        writer = csv.DictWriter(f, fieldnames=fieldnames)
        writer.writeheader()
        writer.writerows(rows)
    return Report(out, [report_md, table_csv, *files], groups, warnings)


# ------------------------------------------------------------------------------------ Fig. 2
def write_fig2(path: Path, data: str, plane: str | None, image_size: int, cache_dir: str | None) -> tuple[Path, str]:
    """Fig. 2 from the ``data=<data>`` catalog's canonical image of ``plane`` (index or ``object/plane``;
    default: the first plane of the first planar object, the paper's "book")."""
    import hydra
    import torch

    from matl.data.canonical import load_canonical
    from matl.reporting.figures import appearance_vs_rotation, local_minima, plot_fig2
    from matl.utils.runs import compose_data_group

    source = hydra.utils.instantiate(compose_data_group(data).source)
    cache = cache_dir or os.environ.get("MATL_CACHE_DIR") or ".cache/matl"
    canonical = load_canonical(source, image_size, cache)
    index = pick_plane(canonical, plane)
    image = torch.from_numpy(canonical.images[index]).permute(2, 0, 1).float().div(255.0)
    angles = torch.arange(-180.0, 180.0 + 1e-9, 2.0, dtype=torch.float64)
    values = appearance_vs_rotation(image, angles)
    label = canonical.plane_label(index)
    plot_fig2(angles.tolist(), values.tolist(), path, f"{data}: {label} ({image_size} px)", image)
    with path.with_suffix(".csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["rotation_deg", "appearance_loss"])
        writer.writerows([f"{a:.1f}", f"{v:.6f}"] for a, v in zip(angles.tolist(), values.tolist(), strict=True))
    minima = ", ".join(f"{a:+.0f}° ({v:.4f})" for a, v in local_minima(angles.tolist(), values.tolist()))
    return path, (f"`{label}` of `{data}` at {image_size} px, rotated about its centre; L^a = mean L1 "
                  f"(Eq. 1). Local minima: {minima}. Data: `fig2.csv`.")


def pick_plane(canonical: Any, plane: str | None) -> int:
    """A plane index from ``plane`` (an index, or ``object/plane``), default the first planar object's first plane."""
    from matl.utils.errors import MatlError

    if plane is None:
        for index in range(canonical.num_planes):
            if canonical.object_shapes[int(canonical.plane_object[index])] == "planar":
                return index
        return 0
    if plane.isdigit():
        if int(plane) >= canonical.num_planes:
            raise MatlError(f"--fig2-plane {plane}: the catalog has {canonical.num_planes} planes")
        return int(plane)
    labels = [canonical.plane_label(i) for i in range(canonical.num_planes)]
    if plane not in labels:
        raise MatlError(f"--fig2-plane {plane!r} is not a plane of the catalog (e.g. {labels[0]!r})")
    return labels.index(plane)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m matl.report", description=__doc__.split("\n")[0])
    parser.add_argument("dirs", nargs="*", type=Path, help="run or multirun folders of matl.train / matl.eval")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: the first dir)")
    parser.add_argument("--fig5", nargs=2, type=Path, metavar=("SINGLE_CKPT", "MATL_CKPT"), default=None,
                        help="Fig. 5 from these checkpoints (default: a row a and a row f run found in the dirs)")
    parser.add_argument("--no-fig5", action="store_true", help="do not look for checkpoints for Fig. 5")
    parser.add_argument("--fig2", metavar="DATA", default=None,
                        help="draw Fig. 2 from this catalog (a data= choice, e.g. synthetic_arc)")
    parser.add_argument("--fig2-plane", default=None, help="plane index or object/plane (default: a planar object)")
    parser.add_argument("--fig2-size", type=int, default=100, help="image size of Fig. 2's canonical image")
    parser.add_argument("--cache-dir", default=None, help="canonical-image cache (default: $MATL_CACHE_DIR or "
                                                          ".cache/matl)")
    args = parser.parse_args(argv)
    if not args.dirs and not args.fig2 and not args.fig5:
        parser.error("give run folders, --fig2 DATA or --fig5 SINGLE MATL")
    out = args.out or (args.dirs[0] if args.dirs else Path("outputs/report"))
    from matl.utils.errors import MatlError

    try:
        if args.dirs and not find_runs(args.dirs) and not args.fig2:
            print(f"error: no metrics.json, eval.json or run folder under {', '.join(map(str, args.dirs))}",
                  file=sys.stderr)
            return 2
        report = build_report(args.dirs, out, fig5=args.fig5, auto_fig5=not args.no_fig5, fig2_data=args.fig2,
                              fig2_plane=args.fig2_plane, fig2_size=args.fig2_size, cache_dir=args.cache_dir)
    except (FileNotFoundError, MatlError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print((out / "report.md").read_text())
    print("wrote " + ", ".join(str(p) for p in report.files))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
