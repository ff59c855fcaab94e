"""The unseen-products benchmark's results: each condition's scores and breakdown, and the benchmark table.

:func:`score_condition` scores one method's predictions of a condition (:mod:`matl.evaluation.score`'s
metrics) on its headline queries (:func:`headline_queries`), per query, and per group of
:func:`breakdown_groups` (``occluded``: hidden-fraction bin, occluder, floor, input); :func:`benchmark_table`
makes ``benchmark.json`` and ``benchmark.md`` of every condition's ``unseen.json`` (:mod:`matl.evaluation.unseen`).
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Any

from matl.evaluation.score import match_predictions, read_truth, score
from matl.utils.errors import MatlError

# -------------------------------------------------------------------------------------- breakdown
BREAKDOWN_METRICS = ("rec_acc", "corner_err_px_median", "pose_acc_5px")
BREAKDOWN_GROUPS = ("hidden_fraction", "occluder", "floor", "input")
QUERY_FIELDS = ("hidden_fraction", "occluder", "floor", "rgba")  # copied from the truth into per_query.csv


def headline_queries(truth: list[dict[str, Any]]) -> list[int]:
    """Indices of the truth records whose metrics are a condition's headline (its row of the table): the RGB
    queries of a condition that mixes RGB and RGBA files (``occluded``; ``rgba`` true in the truth), else all."""
    rgb = [i for i, t in enumerate(truth) if not t.get("rgba", False)]
    return rgb if rgb else list(range(len(truth)))


def bin_labels(edges: list[float]) -> list[str]:
    """Labels of the hidden-fraction bins with upper ``edges`` (increasing), and of the one beyond the last:
    ``[0.2, 0.35, 0.5]`` -> ``<=0.20``, ``0.20-0.35``, ``0.35-0.50``, ``>0.50``."""
    return ([f"<={edges[0]:.2f}"] + [f"{a:.2f}-{b:.2f}" for a, b in itertools.pairwise(edges)]
            + [f">{edges[-1]:.2f}"])


def hidden_bin(fraction: float, edges: list[float]) -> str:
    """The label of the bin (:func:`bin_labels`) a hidden fraction falls in; an upper edge belongs to its bin."""
    labels = bin_labels(edges)
    return next((label for edge, label in zip(edges, labels, strict=False) if fraction <= edge), labels[-1])


def breakdown_groups(truth: list[dict[str, Any]], headline: list[int], edges: list[float]
                     ) -> dict[str, dict[str, list[int]]]:
    """The breakdown of a condition whose truth records carry ``hidden_fraction`` (``occluded``; else ``{}``): the
    headline queries by hidden-fraction bin (every bin up to the last edge listed, empty or not), occluder kind and
    floor; every query by input (``rgb``, ``rgba``). Values: indices into ``truth``."""
    if not any("hidden_fraction" in t for t in truth):
        return {}
    from matl.data.occluders import OCCLUDER_KINDS

    by_bin: dict[str, list[int]] = {label: [] for label in bin_labels(edges)[:-1]}
    by_kind: dict[str, list[int]] = {}
    by_floor: dict[str, list[int]] = {}
    for i in headline:
        by_bin.setdefault(hidden_bin(float(truth[i]["hidden_fraction"]), edges), []).append(i)
        by_kind.setdefault(str(truth[i]["occluder"]), []).append(i)
        by_floor.setdefault(str(truth[i]["floor"]), []).append(i)
    by_input: dict[str, list[int]] = {"rgb": [], "rgba": []}
    for i, t in enumerate(truth):
        by_input["rgba" if t.get("rgba") else "rgb"].append(i)
    kinds = sorted(by_kind, key=lambda k: OCCLUDER_KINDS.index(k) if k in OCCLUDER_KINDS else len(OCCLUDER_KINDS))
    return {"hidden_fraction": by_bin, "occluder": {k: by_kind[k] for k in kinds},
            "floor": dict(sorted(by_floor.items())), "input": by_input}


def _read_predictions(path: Path) -> list[dict[str, Any]]:
    try:
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except (OSError, json.JSONDecodeError) as error:
        raise MatlError(f"predictions={path} cannot be read: {' '.join(str(error).split())}") from None


def score_condition(predictions: Path, truth: Path, headline: list[int], groups: dict[str, dict[str, list[int]]],
                    image_size: int, gallery_fill: float = 1.0, query_fill: float = 1.0
                    ) -> tuple[dict[str, Any], list[dict[str, Any]], dict[str, dict[str, dict[str, Any]]]]:
    """Score one method's predictions of a condition (:func:`matl.evaluation.score.score`, its metrics).

    Returns:
        ``(summary, rows, groups)``: the summary of the ``headline`` queries (indices into ``truth``'s lines), the
        per-query rows of every query, and per group and label of ``groups`` its ``num_queries`` and
        :data:`BREAKDOWN_METRICS` (None for an empty label).
    """
    labelled = read_truth(truth)
    base = Path(truth).expanduser().parent.resolve()
    matched = match_predictions(labelled, _read_predictions(Path(predictions)), base)

    def scored(indices: list[int]) -> tuple[dict[str, Any], list[dict[str, Any]]]:
        return score([labelled[i] for i in indices], [matched[i] for i in indices], image_size, gallery_fill,
                     query_fill, base)

    every, rows = score(labelled, matched, image_size, gallery_fill, query_fill, base)
    summary = every if len(headline) == len(labelled) else scored(headline)[0]
    summary.update(predictions=str(predictions), truth=str(truth))
    by_group: dict[str, dict[str, dict[str, Any]]] = {}
    for group, labels in groups.items():
        by_group[group] = {}
        for label, indices in labels.items():
            metrics = scored(indices)[0] if indices else {}
            by_group[group][label] = {"num_queries": len(indices), **{k: metrics.get(k) for k in BREAKDOWN_METRICS}}
    return summary, rows, by_group


def breakdown_result(groups: dict[str, dict[str, list[int]]], scored: dict[str, dict[str, dict[str, dict]]],
                     edges: list[float], headline: str) -> dict[str, Any]:
    """``unseen.json``'s ``breakdown``: per group and label, ``num_queries`` and each method's metrics."""
    out: dict[str, Any] = {
        "queries": (f"hidden_fraction, occluder and floor: the headline ({headline}) queries; input: every query"),
        "hidden_fraction_bins": edges, "metrics": list(BREAKDOWN_METRICS)}
    for group, labels in groups.items():
        out[group] = {label: {"num_queries": len(indices),
                              "methods": {m: {k: s[group][label][k] for k in BREAKDOWN_METRICS}
                                          for m, s in scored.items()}}
                      for label, indices in labels.items()}
    return out


# ------------------------------------------------------------------------------------------ table
TABLE_METRICS = ("rec_acc", "corner_err_px_median", "pose_acc_5px", "query_ms")


def _cell(metrics: dict[str, Any]) -> str:
    def fmt(value: Any, digits: int) -> str:
        return "-" if value is None else f"{float(value):.{digits}f}"

    return " / ".join([fmt(metrics.get("rec_acc"), 3), fmt(metrics.get("corner_err_px_median"), 1),
                       fmt(metrics.get("pose_acc_5px"), 3), fmt(metrics.get("query_ms"), 1)])


def benchmark_table(results: dict[str, dict[str, Any]], methods: list[str], command: str) -> tuple[dict, str]:
    """``benchmark.json``'s content and ``benchmark.md``: one row per condition, one column per method,
    each cell ``rec_acc / median corner_err_px / pose_acc_5px / query_ms``."""
    table = {c: {m: {k: r["methods"][m].get(k) for k in TABLE_METRICS} for m in methods} for c, r in results.items()}
    first = next(iter(results.values()))
    data = {"command": command, "conditions": list(results), "methods": methods, "table": table,
            "columns": list(TABLE_METRICS), "num_queries": {c: r["num_queries"] for c, r in results.items()},
            "num_objects": first["num_objects"], "num_planes": first["num_planes"], "image_size": first["image_size"],
            "checkpoint": first["checkpoint"], "data": first["data"], "query_seed": first["query_seed"],
            "timing": first["timing"]}
    lines = [f"Never-seen products: {first['num_objects']} products, {first['num_planes']} planes, "
             f"checkpoint `{first['checkpoint']}`.", "",
             f"`{command}`" if command else "(called as a function)", "",
             "Each cell: rec_acc / median corner_err_px (at the model's "
             f"{first['image_size']} px) / pose_acc_5px / query_ms (batch of 1).", "",
             "| condition | queries | " + " | ".join(methods) + " |",
             "|---|---|" + "---|" * len(methods)]
    for condition, row in table.items():
        lines.append(f"| {condition} | {results[condition]['num_queries']} | "
                     + " | ".join(_cell(row[m]) for m in methods) + " |")
    headlines = {c: r.get("headline") for c, r in results.items() if r.get("headline") not in (None, "all")}
    if headlines:
        lines += ["", "Rows of " + ", ".join(f"{c} count its {h.upper()} queries only" for c, h in headlines.items())
                  + " (the breakdown below has the others)."]
    for condition, result in results.items():
        breakdown = result.get("breakdown")
        if not breakdown:
            continue
        data.setdefault("breakdown", {})[condition] = breakdown
        lines += ["", f"{condition} broken down ({breakdown['queries']}); each cell: rec_acc / median corner_err_px / "
                  "pose_acc_5px.", "", "| group | queries | " + " | ".join(methods) + " |",
                  "|---|---|" + "---|" * len(methods)]
        for group in BREAKDOWN_GROUPS:
            for label, entry in breakdown.get(group, {}).items():
                cells = (_cell({**entry["methods"].get(m, {}), "query_ms": None}).rsplit(" / ", 1)[0] for m in methods)
                lines.append(f"| {group} {label} | {entry['num_queries']} | " + " | ".join(cells) + " |")
    return data, "\n".join(lines) + "\n"


def write_speed_accuracy(data: dict[str, Any], folders: dict[str, Path], out: Path) -> dict[str, str]:
    """``speed_accuracy.png`` and ``methods.md`` (:mod:`matl.reporting.speed_accuracy`) beside each condition's
    ``unseen.json`` whose methods were timed; returns their paths relative to ``out`` per condition."""
    from matl.reporting.speed_accuracy import methods_table, plot_speed_accuracy, timed_methods

    written = {}
    timing = data.get("timing") or {}
    for condition, table in data["table"].items():
        if not timed_methods(table):
            continue
        n = data["num_queries"][condition]
        title = (f"{data['num_objects']} never-seen products, condition {condition}, {n} queries; query_ms: median "
                 f"of {timing.get('queries')} single queries at {timing.get('threads')} thread(s)")
        png = plot_speed_accuracy(table, folders[condition] / "speed_accuracy.png", title)
        (folders[condition] / "methods.md").write_text(methods_table(table, n))
        written[condition] = str(png.relative_to(out))
    return written
