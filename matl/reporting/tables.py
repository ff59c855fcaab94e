"""The report's tables: cells of Table 1 / Table 2 / Fig. 4 from groups of runs, as markdown and as CSV rows.

A cell is the group with most seeds among those of its row, dataset column and *setting* (the
``scale=`` choice, image size, epochs and test-set size of a training; baselines are not trained and
join every setting of their image size and test set). Cells show ``mean ± sample std (k seeds)``
beside the paper's numbers (:mod:`matl.paper`).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Any

from matl import paper
from matl.metrics import METRIC_NAMES
from matl.reporting.runs import Group

# every metric of the metric collection, and the single-query time matl.eval adds
COLUMNS = (*METRIC_NAMES, "query_ms")
# the methods table: the columns a reader compares methods by (the median corner error, not the mean)
METHOD_COLUMNS = tuple(c for c in COLUMNS if c != "corner_err_px")
METHOD_HEADERS = {"corner_err_px_median": "median corner_err_px"}


# ------------------------------------------------------------------------------------ formatting
def fmt_stat(stat: tuple[float, float, int] | None, digits: int = 3) -> str:
    """``mean ± std (n)``; ``n/a`` without values."""
    if stat is None:
        return "n/a"
    mean, std, n = stat
    return f"{mean:.{digits}f} ± {std:.{digits}f} ({n})" if n > 1 else f"{mean:.{digits}f} (1)"


def fmt_paper(stat: paper.Stat) -> str:
    """A published ``(mean, std)`` as the paper prints it; ``n/a`` where it has none."""
    return "n/a" if stat is None else f"{stat[0]:.2f} ± {stat[1]:.2f}"


def setting_label(setting: tuple[Any, ...]) -> str:
    """``scale=cpu, 100 px, 8 epochs, 1000 test queries`` from a run's setting."""
    scale, size, epochs, test = setting
    parts = [f"scale={scale}"] if scale else ["no scale= preset"]
    parts += [f"{size} px", f"{epochs} epochs", f"{test} test queries"]
    return ", ".join(str(p) for p in parts)


def settings_of(groups: list[Group]) -> list[tuple[Any, ...]]:
    """The settings the tables are split by: those of trainings in a paper table or in Fig. 4."""
    found = {g.first.setting for g in groups if g.first.kind == "train"
             and (g.first.table1 or g.first.table2 or g.first.fig4)}
    if not found:  # only baselines: one table per (image size, test queries)
        found = {(None, g.first.setting[1], None, g.first.setting[3]) for g in groups if g.first.table1}
    return sorted(found, key=lambda s: tuple(str(x) for x in s))


# ------------------------------------------------------------------------------------ cells
@dataclass
class Cell:
    group: Group | None
    others: int            # how many other configurations matched the same cell


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


def table1_cells(groups: list[Group], setting: tuple[Any, ...]) -> dict[tuple[str, str], Cell]:
    cells = {}
    for row in paper.TABLE1:
        for column in paper.DATASETS:
            members = [g for g in groups if g.first.table1 == row and g.first.paper_column == column
                       and (g.first.setting == setting if g.first.kind == "train" else _baseline_matches(g, setting))]
            cells[(row, column)] = Cell(*_pick(members))
    return cells


def table2_cells(groups: list[Group], setting: tuple[Any, ...]) -> dict[str, Cell]:
    return {row: Cell(*_pick([g for g in groups if g.first.table2 == row and g.first.setting == setting]))
            for row in paper.TABLE2}


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
    order = {name: i for i, name in enumerate(paper.DATASET_COLUMN)}  # ARC, YCB, APC as the paper's panels
    return dict(sorted(series.items(), key=lambda kv: (order.get(kv[0], 99), kv[0])))


# ------------------------------------------------------------------------------------ markdown
def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _header(names: list[str]) -> list[str]:
    return [_row(names), "|" + "---|" * len(names)]


def table1_md(cells: dict[tuple[str, str], Cell]) -> list[str]:
    header = ["row", "method"]
    for column in paper.DATASETS:
        header += [f"{column} rec_acc", "(paper)", f"{column} pose_err", "(paper)"]
    lines = _header(header)
    notes = []
    for key, row in paper.TABLE1.items():
        cols = [f"({key})", row.method]
        for column in paper.DATASETS:
            cell = cells[(key, column)]
            rec = cell.group.stat("rec_acc") if cell.group else None
            pose = cell.group.stat("pose_err") if cell.group else None
            mark = "" if not cell.others else "*"
            published_rec, published_pose = row.paper[column]
            cols += [("—" if cell.group is None else fmt_stat(rec)) + mark, fmt_paper(published_rec),
                     ("—" if cell.group is None else fmt_stat(pose)) + mark, fmt_paper(published_pose)]
            if cell.others:
                notes.append(f"({key}) {column}: {cell.others} other configuration(s) match this cell; "
                             f"shown: {cell.group.first.label} ({cell.group.first.path.parent})")
        lines.append(_row(cols))
    return lines + ([""] + [f"\\* {n}" for n in notes] if notes else [])


def table2_md(cells: dict[str, Cell]) -> list[str]:
    lines = _header(["row", "method", "rec_acc", "(paper)", "pose_err", "(paper)"])
    for key, row in paper.TABLE2.items():
        group = cells[key].group
        published_rec, published_pose = row.paper[paper.TABLE2_COLUMN]
        lines.append(_row([
            f"({key})", row.method, "—" if group is None else fmt_stat(group.stat("rec_acc")), fmt_paper(published_rec),
            "—" if group is None else fmt_stat(group.stat("pose_err")), fmt_paper(published_pose)]))
    return lines


def fig4_md(series: dict[str, dict[int, Group]]) -> list[str]:
    metrics = ("rec_acc", "pose_err", "pose_acc_5px")
    lines = _header(["dataset", "N", *metrics])
    for dataset, points in series.items():
        for N in sorted(points):
            lines.append(_row([dataset, str(N), *[fmt_stat(points[N].stat(m)) for m in metrics]]))
    return lines


def methods_md(groups: list[Group]) -> list[str]:
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
    header = ["method", *[METHOD_HEADERS.get(c, c) for c in METHOD_COLUMNS], "seeds"]
    for (dataset, seeds, queries), members in sorted(by_queries.items(), key=lambda kv: tuple(map(str, kv[0]))):
        lines += [f"{dataset}, split seed(s) {seeds}, {queries} queries:", "", *_header(header)]
        for g in sorted(members, key=lambda g: (g.first.method or g.first.label)):
            lines.append(_row([g.first.method or g.first.label, *[fmt_stat(g.stat(m)) for m in METHOD_COLUMNS],
                               seeds]))
        lines.append("")
    return lines


def groups_md(groups: list[Group]) -> list[str]:
    """Every group with finished runs, all metric columns."""
    lines = _header(["config", "dataset", "kind", "runs", "seeds", *COLUMNS])
    for g in groups:
        if not g.runs:
            continue
        r = g.first
        lines.append(_row([r.label, r.dataset, r.kind, str(len(g.runs)), " ".join(map(str, g.seeds)),
                           *[fmt_stat(g.stat(c)) for c in COLUMNS]]))
    return lines


# ------------------------------------------------------------------------------------ CSV
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
        paper_rec: paper.Stat = None
        paper_pose: paper.Stat = None
        if run.table1 and run.paper_column:
            paper_rec, paper_pose = paper.TABLE1[run.table1].paper[run.paper_column]
        elif run.table2:
            paper_rec, paper_pose = paper.TABLE2[run.table2].paper[paper.TABLE2_COLUMN]
        row.update(paper_rec_acc_mean="" if paper_rec is None else paper_rec[0],
                   paper_rec_acc_std="" if paper_rec is None else paper_rec[1],
                   paper_pose_err_mean="" if paper_pose is None else paper_pose[0],
                   paper_pose_err_std="" if paper_pose is None else paper_pose[1])
        rows.append(row)
    return rows


CSV_FALLBACK_COLUMNS = ["kind", "dataset", "config"]  # table.csv's header when there is no group
