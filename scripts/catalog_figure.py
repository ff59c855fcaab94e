"""One figure and table of accuracy and query time against gallery size from several catalogue runs (docs/catalog.md).

    python -m matl.unseen ckpt=pretrained condition=catalog 'catalog_sizes=[20,200,2000]' ... out=runs/cat_small
    python -m matl.unseen ckpt=pretrained condition=catalog 'catalog_sizes=[10000]' ... out=runs/cat_10k
    python scripts/catalog_figure.py runs/cat_small/catalog.json runs/cat_10k/catalog.json --out docs/img/catalog.png

Reads each run's ``catalog.json`` (finished runs only), puts their rows in one list by gallery size (a size in two
runs is an error: which one is meant?), and draws them with the benchmark's own plot
(:func:`matl.evaluation.catalog.plot_catalog`); the merged table (:func:`~matl.evaluation.catalog.catalog_table`,
each run's command above it) is printed.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from matl.evaluation.catalog import catalog_table, catalog_title, plot_catalog


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="catalog.json files of finished catalogue runs")
    parser.add_argument("--out", type=Path, required=True, help="the figure to write (.png)")
    args = parser.parse_args()
    rows, commands, title = [], [], None
    for path in args.runs:
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as error:
            raise SystemExit(f"catalog_figure: {path} cannot be read as a catalogue run's catalog.json ({error}): "
                             "pass <out>/catalog.json of python -m matl.unseen condition=catalog") from None
        if not data.get("complete"):
            raise SystemExit(f"catalog_figure: {path} is from an unfinished run: let it finish or run it again")
        commands.append(data["command"])
        rows += data["rows"]
        title = title or catalog_title(data["catalog"]["lookalike_share"], data["queries"], data["timing"]["threads"])
    sizes = [r["products"] for r in rows]
    twice = sorted({n for n in sizes if sizes.count(n) > 1})
    if twice:
        raise SystemExit(f"catalog_figure: {', '.join(map(str, twice))} products come from more than one run: pass "
                         "one run per size")
    rows.sort(key=lambda r: r["products"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    plot_catalog(rows, args.out, title)
    table = catalog_table(rows, "").splitlines()[1:]  # its first line names one command: here each run's
    print("\n".join([f"`{command}`" for command in commands] + table))


if __name__ == "__main__":
    main()
