"""Which of the paper's rows a run is, and how a run is named for humans.

A run's row is read from its saved *configuration*, not from the ``experiment=`` it was launched
with (``experiment=table1_f N=2`` is a Fig. 4 point, not row (f)): :func:`paper_settings` turns the
config into the settings of :mod:`matl.paper`, whose :func:`matl.paper.classify` names the row.
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from matl import paper
from matl.reporting.configs import dataset_name, hydra_choices, number, select, short
from matl.utils.errors import MatlError
from matl.utils.runs import load_run as load_training_run

# an evaluated keypoint baseline (its baseline= choice) -> its method name: the paper's rows, and one beyond them
BASELINE_METHODS = {**{row.settings["baseline"]: row.method for row in paper.TABLE1.values() if row.command == "eval"},
                    "lightglue": "ALIKED+LightGlue+RANSAC (beyond the paper)"}


def paper_settings(cfg: DictConfig, dataset: str) -> dict[str, Any]:
    """A training config's settings in :mod:`matl.paper`'s terms (:data:`matl.paper.SETTING_KEYS`, no baseline).

    ``dataset`` is the run's dataset as :func:`matl.reporting.configs.dataset_name` names it.
    """
    return {
        "model": short(select(cfg, "model._target_")),
        "stn": select(cfg, "model.stn") is not None,
        "N": select(cfg, "N"),
        "lam": number(select(cfg, "lam")),
        "loss": short(select(cfg, "loss.fn._target_")),
        "num_negatives": select(cfg, "loss.num_negatives"),
        "tau": select(cfg, "loss.fn.tau"),
        "anchors": short(select(cfg, "anchors._target_")),
        "stn_on_negative": select(cfg, "model.stn_on_negative", True),  # the model's default: through the STN
        "data": dataset,
    }


def classify_training(cfg: DictConfig, dataset: str) -> tuple[str | None, str | None, bool]:
    """``(Table 1 row, Table 2 row, in Fig. 4's family)`` of a training config (:func:`matl.paper.classify`).

    A run trained beyond the paper's recipe (camera-like positives ``data.augment``, the alignment stage
    ``model.align``, the foreground appearance loss) is no paper row: ``(None, None, False)``.
    """
    if beyond_paper(cfg):
        return None, None, False
    return paper.classify(paper_settings(cfg, dataset))


def beyond_paper(cfg: DictConfig) -> list[str]:
    """The settings of a training config that go beyond the paper's recipe (empty for a paper row)."""
    found = []
    if select(cfg, "data.augment") is not None:
        found.append("augment=camera")
    if select(cfg, "model.align") is not None:
        found.append("align")
    if select(cfg, "model.appearance_mask", "none") not in (None, "none"):
        found.append(f"appearance_mask={select(cfg, 'model.appearance_mask')}")
    norms = sorted({str(select(cfg, key, "none")) for key in ("model.feature_net.input_norm",
                                                               "model.stn.regressor.input_norm")} - {"None", "none"})
    if norms:
        found.append("input_norm=" + "/".join(norms))
    return found


def baseline_row(baseline: str, N: Any) -> str | None:
    """The Table 1 row of an evaluated keypoint baseline (``sift`` with N=4 is row (d)), else None."""
    return paper.classify({"baseline": baseline, "N": N})[0]


def describe(cfg: DictConfig | None, kind: str, metrics: dict[str, Any]) -> str:
    """The settings that tell a group apart, e.g. ``MATLModule, N=4, lam=10.0, TripletLoss, FixedAnchors``."""
    if kind == "baseline":
        return f"baseline={metrics.get('baseline') or select(cfg, 'baseline._target_', '?')}, N={metrics.get('N')}"
    parts = []
    model = short(select(cfg, "model._target_"))
    if model:
        parts.append(str(model) + (" (no STN)" if model == "MATLModule" and select(cfg, "model.stn") is None else ""))
    for key, name in (("N", "N"), ("lam", "lam"), ("loss.fn._target_", "loss"), ("anchors._target_", "anchors"),
                      ("model.stn_on_negative", "stn_on_negative"), ("model.appearance", "appearance"),
                      ("model.appearance_levels", "levels"), ("model.stn.iterations", "stn_steps")):
        value = select(cfg, key)
        if value is not None:
            parts.append(f"{name}={short(value)}")
    parts += beyond_paper(cfg) if cfg is not None else []
    if kind == "eval":
        parts.append(f"eval of {metrics.get('run') or '?'}")
    return ", ".join(parts)


def evaluation_method(kind: str, metrics: dict[str, Any], baseline: str) -> str:
    """The method a ``matl.eval`` run evaluated, named as in Table 1 where it is a Table 1 row.

    A checkpoint evaluation is named from the evaluated training run's own saved config (its row of
    Table 1, else its distinguishing settings); ``+ refinement`` marks ``refine=true``.
    """
    if kind == "baseline":
        name = BASELINE_METHODS.get(baseline, baseline)
        return f"{name}, N={metrics.get('N')}" if metrics.get("N") not in (None, 4) else name
    name = f"eval of {metrics.get('run') or '?'}"
    if metrics.get("run"):
        try:
            run_dir, cfg = load_training_run(str(metrics["run"]))
        except MatlError:  # the evaluated run moved or is gone: named by its folder
            pass
        else:
            row = classify_training(cfg, dataset_name(select(cfg, "data"), hydra_choices(run_dir).get("data")))[0]
            name = f"({row}) {paper.TABLE1[row].method}" if row else describe(cfg, "train", {})
    return name + (" + refinement" if metrics.get("refine") else "")
