"""The paper's vocabulary, written once: the rows of Table 1 and Table 2, what defines each, and its numbers.

A row is named as its config file is, ``table1_f`` = ``conf/experiment/table1_f.yaml``. Each :class:`Row`
holds

* ``method``: the paper's label of the row (``Ours (multiple anchors, λ=10, N=4)``);
* ``settings``: what ``experiment=<name>`` composes to, in the terms of :data:`SETTING_KEYS`
  (``tests/test_paper.py`` composes every row and checks it gets exactly these: Hydra needs the
  yaml files, the test keeps them equal to this module);
* ``identity``: the settings a finished run is recognised by (``matl.report`` reads a run's row from
  its saved config, never from the ``experiment=`` it was launched with). The others follow from
  them or are unused by the row, e.g. ``lam`` without an STN;
* ``paper``: the published ``(mean, std)`` of ``rec_acc`` and ``pose_err`` per dataset column
  (``None``: n/a in the paper).

Plain Python only (no torch, no omegaconf): :func:`classify` takes a run's settings as a dict; turning
a saved config into that dict is ``matl.reporting.rows.paper_settings``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

Stat = tuple[float, float] | None  # (mean, std) published in the paper; None = n/a

# The settings that tell the paper's rows apart (the names a row's settings use):
SETTING_KEYS = (
    "model",            # the LightningModule class: MATLModule | STNClassifierModule
    "stn",              # whether the model has an STN s() (the TL model of row (b) has none)
    "N",                # anchors per plane
    "lam",              # lambda, the weight of the appearance loss
    "loss",             # the loss class: TripletLoss | NCELoss
    "num_negatives",    # M of the NCE loss
    "tau",              # tau of the NCE loss
    "anchors",          # the anchor class: FixedAnchors | RandomAnchors | RenderedRandomAnchors
    "stn_on_negative",  # whether the negative goes through the STN too
    "data",             # the dataset as matl.report names it, e.g. synthetic_ycb_table2/planar
    "baseline",         # a keypoint baseline's baseline= choice (rows evaluated by matl.eval)
)

# The paper's dataset columns, and which of our datasets stands for each (the synthetic stand-ins and
# the real meshes; the order is also the order of Fig. 4's panels).
DATASETS = ("ARC", "YCB", "APC")
DATASET_COLUMN = {"synthetic_arc": "ARC", "arc": "ARC", "synthetic_ycb": "YCB", "ycb/planar": "YCB",
                  "synthetic_apc": "APC", "apc": "APC"}
TABLE2_DATA = "synthetic_ycb_table2"  # Table 2's split of synthetic YCB; a run's data is <this>/<subset>
TABLE2_COLUMN = "YCB"                 # the column Table 2's published numbers are under

SEEDS = 9                   # the paper's 9 splits: a sweep's default seeds are range(0, SEEDS)
FIG4_N = (1, 2, 4, 6, 9)    # Fig. 4's numbers of anchors (row (f)'s configuration with each N)


@dataclass(frozen=True)
class Row:
    """One row of Table 1 or Table 2 (see the module docstring)."""

    table: int                                   # 1 | 2
    key: str                                     # a..j (Table 1), a..d (Table 2)
    method: str                                  # the paper's label
    settings: Mapping[str, Any]                  # what experiment=<name> composes to
    identity: tuple[str, ...]                    # the settings a run is recognised by
    paper: Mapping[str, tuple[Stat, Stat]]       # {column: (rec_acc, pose_err)}
    alternatives: Mapping[str, tuple[Any, ...]] = field(default_factory=dict)  # other values that still match
    command: str = "train"                       # train | eval (the keypoint baselines are evaluations)

    @property
    def name(self) -> str:
        """The ``experiment=`` name: ``table1_f``."""
        return f"table{self.table}_{self.key}"

    def matches(self, settings: Mapping[str, Any]) -> bool:
        """Whether a run with these settings is this row (every :attr:`identity` setting agrees)."""
        accepted = {key: (self.settings[key], *self.alternatives.get(key, ())) for key in self.identity}
        return all(any(_same(settings.get(key), value) for value in values) for key, values in accepted.items())


def _same(a: Any, b: Any) -> bool:
    """Equality where a flag only equals a flag (``1`` is not ``True``), and ``4 == 4.0``."""
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    return a == b


def _ours(**changes: Any) -> dict[str, Any]:
    """Row (f)'s settings with ``changes``: most rows are one change away from it."""
    return {"model": "MATLModule", "stn": True, "N": 4, "lam": 10.0, "loss": "TripletLoss",
            "anchors": "FixedAnchors", "stn_on_negative": True, **changes}


_OURS = tuple(_ours())  # the identity of row (f) and of the rows one change away from it


def _row(key: str, method: str, settings: dict[str, Any], paper: dict[str, tuple[Stat, Stat]],
         identity: tuple[str, ...] = _OURS, table: int = 1, **extra: Any) -> Row:
    return Row(table, key, method, settings, identity, paper, **extra)


def _columns(arc: tuple[Stat, Stat], ycb: tuple[Stat, Stat], apc: tuple[Stat, Stat]) -> dict[str, tuple[Stat, Stat]]:
    return dict(zip(DATASETS, (arc, ycb, apc), strict=True))


TABLE1: dict[str, Row] = {row.key: row for row in (
    _row("a", "[28] (single anchor, N=1)", _ours(N=1),
         _columns(((0.84, 0.01), (1.86, 0.01)), ((0.72, 0.01), (1.88, 0.01)), ((0.84, 0.01), (1.90, 0.01)))),
    # standard triplet learning: no STN, recognition only (lam is unused without an STN)
    _row("b", "TL [29]", {"model": "MATLModule", "stn": False, "N": 1, "lam": 10.0, "loss": "TripletLoss",
                          "anchors": "FixedAnchors"},
         _columns(((0.87, 0.01), None), ((0.78, 0.01), None), ((0.88, 0.01), None)), identity=("model", "stn", "N")),
    # the STN as a classifier (cross-entropy); N only sizes its evaluation gallery, lam is unused
    _row("c", "STN [15]", {"model": "STNClassifierModule", "stn": True, "N": 4, "lam": 10.0,
                           "anchors": "FixedAnchors"},
         _columns(((0.88, 0.02), (2.80, 0.16)), ((0.82, 0.02), (6.13, 0.01)), ((0.92, 0.04), (2.68, 0.53))),
         identity=("model", "N")),
    _row("d", "SIFT+RANSAC [20, 13]", {"baseline": "sift", "N": 4},
         _columns(((0.82, 0.02), (0.63, 0.05)), ((0.80, 0.03), (0.64, 0.19)), ((0.87, 0.01), (0.50, 0.02))),
         identity=("baseline", "N"), command="eval"),
    _row("e", "SuperPoint+RANSAC [12, 13]", {"baseline": "superpoint", "N": 4},
         _columns(((0.83, 0.01), (0.66, 0.03)), ((0.82, 0.01), (0.64, 0.03)), ((0.90, 0.01), (0.51, 0.03))),
         identity=("baseline", "N"), command="eval"),
    _row("f", "Ours (multiple anchors, λ=10, N=4)", _ours(),
         _columns(((0.93, 0.01), (0.66, 0.01)), ((0.84, 0.01), (0.60, 0.01)), ((0.93, 0.01), (0.46, 0.01)))),
    _row("g", "Ours (λ=0, N=4)", _ours(lam=0.0),
         _columns(((0.88, 0.01), (1.70, 0.02)), ((0.78, 0.01), (1.75, 0.03)), ((0.89, 0.01), (1.68, 0.04)))),
    # anchors=random warps the canonical image by random views; anchors=random_rendered renders them
    _row("h", "Ours (random-position anchors, λ=10, N=4)", _ours(anchors="RandomAnchors"),
         _columns(((0.87, 0.01), (1.64, 0.01)), ((0.74, 0.01), (1.65, 0.01)), ((0.91, 0.01), (1.59, 0.01))),
         alternatives={"anchors": ("RenderedRandomAnchors",)}),
    _row("i", "Ours (no STN in negative, λ=10, N=4)", _ours(stn_on_negative=False),
         _columns(((0.93, 0.01), (0.67, 0.03)), ((0.83, 0.01), (0.63, 0.01)), ((0.93, 0.01), (0.53, 0.01)))),
    # M=64, tau=0.07 are the row's values; a run is row (j) by its loss, whatever its M and tau
    _row("j", "Ours (NCE loss, λ=10, N=4)", _ours(loss="NCELoss", num_negatives=64, tau=0.07),
         _columns(((0.94, 0.01), (0.67, 0.02)), ((0.89, 0.01), (0.61, 0.02)), ((0.97, 0.01), (0.52, 0.02)))),
)}

# Table 2: row (f)'s configuration (N=4) and [28] (N=1) on the planar and non-planar objects of Table 2's split.
TABLE2: dict[str, Row] = {row.key: row for row in (
    _row(key, method, _ours(N=N, data=f"{TABLE2_DATA}/{subset}"), {TABLE2_COLUMN: paper}, (*_OURS, "data"), table=2)
    for key, method, N, subset, paper in (
        ("a", "Ours (planar)", 4, "planar", ((0.91, 0.02), (0.57, 0.03))),
        ("b", "[28] (planar)", 1, "planar", ((0.78, 0.02), (1.86, 0.04))),
        ("c", "Ours (non-planar)", 4, "nonplanar", ((0.81, 0.02), (0.68, 0.05))),
        ("d", "[28] (non-planar)", 1, "nonplanar", ((0.64, 0.01), (1.89, 0.03))),
    ))}

ROWS: dict[str, Row] = {row.name: row for row in (*TABLE1.values(), *TABLE2.values())}  # by experiment= name


def in_fig4_family(settings: Mapping[str, Any]) -> bool:
    """Whether a run is row (f)'s configuration with any N (a point of Fig. 4; rows (a) and (f) are N=1, 4)."""
    f = TABLE1["f"]
    return all(_same(settings.get(key), f.settings[key]) for key in f.identity if key != "N")


def classify(settings: Mapping[str, Any]) -> tuple[str | None, str | None, bool]:
    """``(Table 1 row, Table 2 row, in Fig. 4's family)`` of a run's settings (keys of :data:`SETTING_KEYS`).

    On Table 2's data, row (f)'s configuration with a Table 2 N is a Table 2 row (or none: another
    subset), never a Table 1 row or a Fig. 4 point; any other run is at most one Table 1 row.
    """
    family = in_fig4_family(settings)
    on_table2_data = str(settings.get("data") or "").startswith(TABLE2_DATA + "/")
    if family and on_table2_data and settings.get("N") in {row.settings["N"] for row in TABLE2.values()}:
        return None, next((r.key for r in TABLE2.values() if r.matches(settings)), None), False
    return next((r.key for r in TABLE1.values() if r.matches(settings)), None), None, family
