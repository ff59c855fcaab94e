"""Run folders of ``matl.train`` and ``matl.eval``: finding them, reading one, and grouping them by configuration.

A run folder holds ``.hydra/config.yaml`` (its saved config) and, once it ended, ``metrics.json``
(a training), ``eval.json`` (an evaluation) or ``failed.json`` (a job of a sweep that failed). Runs are
grouped by their full configuration minus the seed (and paths, loggers, resume keys:
:data:`matl.reporting.configs.IGNORED_KEYS`), so runs that differ in anything else never share a table
cell; a group's seeds are its samples (a seed run twice counts once, the newest).
"""

from __future__ import annotations

import json
import math
import statistics
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from matl.paper import DATASET_COLUMN
from matl.reporting.configs import config_container, dataset_name, fingerprint, hydra_choices, select, short
from matl.reporting.rows import baseline_row, classify_training, describe, evaluation_method
from matl.utils.errors import MatlError

RESULT_FILES = ("metrics.json", "eval.json", "failed.json")


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
        """The paper's dataset column (ARC, YCB, APC) this run's dataset stands for, else None."""
        return DATASET_COLUMN.get(self.dataset)

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
            raise MatlError(f"{root} does not exist; pass run or multirun folders of matl.train/eval")
        for name in RESULT_FILES:
            found.update(p.parent for p in root.rglob(name) if ".submitit" not in p.parts)
        found.update(p.parent for p in root.rglob(".hydra") if (p / "config.yaml").is_file())
    return sorted(found)


def load_run(path: Path) -> Run:
    """Read one run folder (see :class:`Run`).

    Its config is read leniently (any ``.hydra/config.yaml``, or none for a folder with only a
    result file): unlike :func:`matl.utils.runs.load_run`, which wants a finished training's config,
    this reads evaluations and failed or unfinished jobs too.
    """
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
    is_eval = (path / "eval.json").is_file() or select(cfg, "task_name") == "eval"
    container = config_container(cfg) if cfg is not None else {"run": path.name}
    if is_eval:
        baseline = metrics.get("baseline") or choices.get("baseline")
        if baseline is None and select(cfg, "baseline._target_") is not None:  # a run without eval.json
            baseline = short(select(cfg, "baseline._target_"))
        kind = "baseline" if (metrics.get("evaluated") == "baseline" or (not metrics and baseline)) else "eval"
        data = select(cfg, "data")
        dataset = dataset_name(data, choices.get("data") or metrics.get("data") or select(cfg, "default_data"))
        seed = metrics.get("seed", select(cfg, "seed"))
        N = metrics.get("N", select(cfg, "N"))
        setting: tuple[Any, ...] = (None, metrics.get("image_size", select(cfg, "data.image_size", 100)), None,
                                    metrics.get("num_queries", select(cfg, "data.test_queries", 1000)))
        fp = fingerprint({**container, "N": N, "baseline_name": baseline, "dataset": dataset,
                          "evaluated_run": metrics.get("run")})
        run = Run(path, status, kind, metrics, seed, dataset, describe(cfg, kind, metrics), fp, setting,
                  reason=reason, mtime=mtime)
        if kind == "baseline":
            run.table1 = baseline_row(str(baseline), N)
        run.method = evaluation_method(kind, metrics, str(baseline))
        return run
    dataset = dataset_name(select(cfg, "data"), choices.get("data"))
    setting = (choices.get("scale"), select(cfg, "data.image_size"), select(cfg, "trainer.max_epochs"),
               select(cfg, "data.test_queries"))
    run = Run(path, status, "train", metrics, metrics.get("seed", select(cfg, "seed")), dataset,
              describe(cfg, "train", metrics), fingerprint(container), setting, reason=reason, mtime=mtime)
    if cfg is not None:
        run.table1, run.table2, family = classify_training(cfg, dataset)
        if family:
            run.fig4 = (fingerprint(config_container(cfg, ("seed", "N")), drop=("N",)), int(select(cfg, "N")))
    return run


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
