"""Everything ``python -m matl.report`` writes: ``report.md``, ``table.csv`` and the figures' PNGs.

:func:`build_report` finds and groups the runs (:mod:`matl.reporting.runs`), writes one Table 1,
Table 2 and Fig. 4 per setting (:mod:`matl.reporting.tables`), Fig. 5 from two checkpoints (given,
or a row (a) and a row (f) run found among the runs) and, on request, Fig. 2 from a catalog
(:mod:`matl.reporting.figures`), then the methods table, every group, failed and unfinished runs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from matl import paper
from matl.reporting.runs import Group, find_runs, group_runs, load_run
from matl.reporting.tables import (
    CSV_FALLBACK_COLUMNS,
    csv_rows,
    fig4_md,
    fig4_series,
    groups_md,
    methods_md,
    setting_label,
    settings_of,
    table1_cells,
    table1_md,
    table2_cells,
    table2_md,
)
from matl.utils.io import atomic_write, write_csv


@dataclass
class Report:
    """What :func:`build_report` produced (paths of the files written)."""

    out: Path
    files: list[Path]
    groups: list[Group]
    warnings: list[str]


def find_fig5_pair(groups: list[Group]) -> tuple[Path, Path] | None:
    """Checkpoints of a row (a) and a row (f) run of one dataset and setting, the same seed when possible."""
    rank = {column: i for i, column in enumerate(paper.DATASETS)}  # ARC first, as the paper's Fig. 5
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
             "docs/datasets.md unless the run used the real meshes; absolute numbers are not expected to match "
             "the paper's, the ordering of the rows is what the reproduction checks.", ""]
    for setting in settings_of(groups):
        cells1 = table1_cells(groups, setting)
        if any(c.group for c in cells1.values()):
            lines += [f"## Table 1 ({setting_label(setting)})", "", *table1_md(cells1), ""]
        cells2 = table2_cells(groups, setting)
        if any(c.group for c in cells2.values()):
            lines += [f"## Table 2 ({setting_label(setting)})", "", "Synthetic YCB, Table 2 split "
                      "(11 simple objects / 23 non-planar).", "", *table2_md(cells2), ""]
        series = fig4_series(groups, setting)
        if series:
            from matl.reporting.figures import Point, plot_fig4

            name = "fig4.png" if not any(p.name == "fig4.png" for p in files) else f"fig4_{len(files)}.png"
            points = {d: {n: {m: Point(*s) for m in ("rec_acc", "pose_err") if (s := g.stat(m)) is not None}
                          for n, g in pts.items()} for d, pts in series.items()}
            files.append(plot_fig4(points, out / name))
            lines += [f"## Fig. 4 ({setting_label(setting)}): performance against N", "", f"![Fig. 4]({name})", "",
                      *fig4_md(series), ""]
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
        from matl.reporting.figures import write_fig2

        path, caption = write_fig2(out / "fig2.png", fig2_data, fig2_plane, fig2_size, cache_dir)
        files.append(path)
        lines += ["## Fig. 2: appearance loss against in-plane rotation", "", caption, "", "![Fig. 2](fig2.png)", ""]

    lines += methods_md(groups)
    lines += ["## All groups", "", *groups_md(groups)]
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
    with atomic_write(report_md) as f:
        f.write("\n".join(lines) + "\n")
    rows = csv_rows(groups)
    table_csv = out / "table.csv"
    write_csv(table_csv, rows, list(rows[0]) if rows else CSV_FALLBACK_COLUMNS)
    return Report(out, [report_md, table_csv, *files], groups, warnings)
