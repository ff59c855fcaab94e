"""Open-set recognition on held-out products: some products are left out of the gallery.

``python -m matl.unseen leave_out=0.5`` enrols only part of the never-seen products and queries
all of them. Queries of enrolled products must keep their label (``known`` and correct); queries
of left-out products must be answered ``known=False``. :func:`open_set_summary` scores a run's
predictions against that truth at the threshold predict used, and over every threshold of the
statistic for the trade-off curve (:func:`plot_open_set`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def open_set_summary(truth: Sequence[dict[str, Any]], predictions: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Precision / recall of "unknown" and the enrolled products' accuracy, at the run's threshold and over all.

    Args:
        truth: one record per query: ``image``, ``object`` and ``enrolled`` (False for a left-out product).
        predictions: predict's records by ``image``.
    Returns:
        ``rec_acc_closed`` (enrolled queries, nearest product, no rejection), ``rec_acc_known``
        (enrolled queries answered known and right), ``unknown_recall`` (left-out queries answered
        unknown), ``unknown_precision`` (answers "unknown" that are left-out products), the counts,
        and ``curve``: those numbers at each threshold of the statistic.
    """
    enrolled = np.array([bool(t["enrolled"]) for t in truth])
    found = [predictions.get(t["image"]) for t in truth]
    if not any(enrolled) or all(enrolled):
        raise ValueError("an open-set summary needs queries of both enrolled and left-out products")
    nearest_right = np.array([p is not None and p["nearest_object"] == t["object"] for p, t in zip(found, truth,
                                                                                                    strict=True)])
    known = np.array([p is not None and bool(p["known"]) for p in found])
    statistic = np.array([np.inf if p is None or p.get("statistic") is None else float(p["statistic"])
                          for p in found])

    def at(accept: np.ndarray) -> dict[str, float]:
        rejected = ~accept
        tp = int((rejected & ~enrolled).sum())
        return {"rec_acc_known": float((accept & nearest_right)[enrolled].mean()),
                "unknown_recall": tp / int((~enrolled).sum()),
                "unknown_precision": tp / int(rejected.sum()) if rejected.any() else 1.0}

    chosen = at(known)
    thresholds = np.unique(statistic[np.isfinite(statistic)])
    curve = [{"threshold": float(t), **at(statistic <= t)} for t in thresholds]
    return {"rec_acc_closed": float(nearest_right[enrolled].mean()), **chosen,
            "num_enrolled_queries": int(enrolled.sum()), "num_left_out_queries": int((~enrolled).sum()),
            "curve": curve}


def plot_open_set(summary: dict[str, Any], path: Path, title: str = "open set on held-out products") -> Path:
    """The trade-off: enrolled products' accuracy against the share of left-out products rejected."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curve = summary["curve"]
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot([c["unknown_recall"] for c in curve], [c["rec_acc_known"] for c in curve], "-", label="all thresholds")
    ax.plot([summary["unknown_recall"]], [summary["rec_acc_known"]], "o", color="C3", label="chosen threshold")
    ax.axhline(summary["rec_acc_closed"], color="grey", ls="--", lw=1, label="closed set")
    ax.set_xlabel("left-out products' queries answered unknown (recall)")
    ax.set_ylabel("enrolled products' rec_acc")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    ax.set_title(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
