"""Where each method stands on the speed x accuracy plane: a PNG and a markdown table.

Input: one condition of ``matl.unseen``'s ``benchmark.json`` (``table[condition]``), i.e. per method
``rec_acc``, ``corner_err_px_median``, ``pose_acc_5px`` and ``query_ms``, all measured on the same query
files. :func:`plot_speed_accuracy` draws ``query_ms`` (log scale) against ``pose_acc_5px`` and against
``rec_acc``, one point per method; :func:`methods_table` lists the same numbers, one row per method.
``matl.unseen`` writes both for every condition whose methods were timed (``speed_accuracy.png`` and
``methods.md`` beside its ``unseen.json``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from matl.reporting.figures import _pyplot, _save
from matl.utils.errors import MatlError

__all__ = ["METHOD_LABELS", "methods_table", "plot_speed_accuracy", "timed_methods"]

# matl.unseen's method names -> what a reader calls them
METHOD_LABELS = {
    "matl": "MATL",
    "matl_refine": "MATL + refine",
    "sift": "SIFT+RANSAC",
    "sift_ecc": "SIFT+RANSAC+ECC",
    "lightglue": "ALIKED+LightGlue",
    "xfeat": "XFeat (MNN)",
    "xfeat_lighterglue": "XFeat+LighterGlue",
}
# the y axes of the figure: metric -> axis label
Y_METRICS = {"pose_acc_5px": "pose_acc_5px (recognised, corner error < 5 px)", "rec_acc": "rec_acc"}


def _number(value: Any) -> float | None:
    return None if value is None or not math.isfinite(float(value)) else float(value)


def timed_methods(table: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """The methods of ``table`` that have a finite positive ``query_ms`` (the ones the plane can place)."""
    return [m for m, row in table.items() if (_number(row.get("query_ms")) or 0.0) > 0.0]


def plot_speed_accuracy(table: Mapping[str, Mapping[str, Any]], path: str | Path, title: str) -> Path:
    """The speed x accuracy plane of one condition: x ``query_ms`` (log), y ``pose_acc_5px`` (left) and
    ``rec_acc`` (right), one labelled point per timed method; MATL's methods filled, the baselines hollow.

    Args:
        table: ``{method: {rec_acc, corner_err_px_median, pose_acc_5px, query_ms}}`` (``benchmark.json``'s
            ``table[condition]``).
        path: the PNG to write (its folder is created).
        title: the figure's title (which queries, which machine).

    Raises:
        MatlError: no method of ``table`` has a ``query_ms`` (``matl.unseen timing.queries=0``).
    """
    methods = timed_methods(table)
    if not methods:
        raise MatlError("no method has a query_ms to place on the speed x accuracy plane: time them (matl.unseen "
                        "timing.queries > 0)")
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(Y_METRICS), figsize=(5.2 * len(Y_METRICS), 4.2))
    xs = [float(table[m]["query_ms"]) for m in methods]
    for ax, (metric, label) in zip(axes, Y_METRICS.items(), strict=True):
        for m, x in zip(methods, xs, strict=True):
            y = _number(table[m].get(metric))
            if y is None:
                continue
            ours = m.startswith("matl")
            ax.scatter([x], [y], s=60, marker="o" if ours else "s", zorder=3,
                       facecolors="tab:blue" if ours else "none", edgecolors="tab:blue" if ours else "tab:red")
            ax.annotate(METHOD_LABELS.get(m, m), (x, y), textcoords="offset points", xytext=(6, 4), fontsize=8)
        ax.set_xscale("log")
        ax.set_xlim(min(xs) / 2.0, max(xs) * 4.0)  # room for the labels on the right
        ax.set_ylim(-0.02, 1.05)
        ax.set_xlabel("query_ms (batch of 1, log scale)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(title, fontsize=9)
    out = Path(path)
    _save(fig, out)
    return out


def methods_table(table: Mapping[str, Mapping[str, Any]], queries: int | None = None) -> str:
    """Markdown: one row per method (``rec_acc``, median ``corner_err_px``, ``pose_acc_5px``, ``query_ms``),
    fastest first; ``-`` where a value is missing."""
    def fmt(value: Any, digits: int) -> str:
        number = _number(value)
        return "-" if number is None else f"{number:.{digits}f}"

    order = sorted(table, key=lambda m: (_number(table[m].get("query_ms")) is None,
                                         _number(table[m].get("query_ms")) or 0.0))
    lines = ["| method | rec_acc | corner_err_px median | pose_acc_5px | query_ms |", "|---|---|---|---|---|"]
    for m in order:
        row = table[m]
        lines.append(f"| {METHOD_LABELS.get(m, m)} (`{m}`) | {fmt(row.get('rec_acc'), 3)} | "
                     f"{fmt(row.get('corner_err_px_median'), 2)} | {fmt(row.get('pose_acc_5px'), 3)} | "
                     f"{fmt(row.get('query_ms'), 1)} |")
    if queries is not None:
        lines.append(f"\n{queries} queries, every method on the same files.")
    return "\n".join(lines) + "\n"
