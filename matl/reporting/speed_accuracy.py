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

from matl.reporting.figures import _pyplot
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
    ``rec_acc`` (right), one point per timed method (a shared legend below); MATL's methods filled circles,
    the baselines hollow markers.

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
    fig, axes = plt.subplots(1, len(Y_METRICS), figsize=(5.2 * len(Y_METRICS), 4.6))
    xs = [float(table[m]["query_ms"]) for m in methods]
    colours = plt.get_cmap("tab10").colors
    for ax, (metric, label) in zip(axes, Y_METRICS.items(), strict=True):
        ys = []
        for i, (m, x) in enumerate(zip(methods, xs, strict=True)):
            y = _number(table[m].get(metric))
            if y is None:
                continue
            ys.append(y)
            ours = m.startswith("matl")  # MATL's methods filled circles, the baselines hollow markers
            colour = colours[i % len(colours)]
            ax.scatter([x], [y], s=70, marker="o" if ours else "sD^vP*X"[i % 7], zorder=3, linewidths=1.5,
                       facecolors=colour if ours else "none", edgecolors=colour, label=METHOD_LABELS.get(m, m))
        ax.set_xscale("log")
        ax.set_xlim(min(xs) / 2.0, max(xs) * 2.0)
        low = min(ys, default=0.0)
        ax.set_ylim(max(0.0, low - 0.1), 1.02)  # the methods' range, not all of [0, 1]
        ax.set_xlabel("query_ms (batch of 1, log scale)")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(4, len(labels)), fontsize=8, frameon=False)
    fig.subplots_adjust(bottom=0.27)
    fig.suptitle(title, fontsize=9)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=150)  # not tight_layout: it would drop the room kept for the legend
    plt.close(fig)
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
