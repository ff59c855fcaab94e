"""``python -m matl.report <run or multirun dirs...> [--out DIR] [--fig2 DATA] [--fig5 SINGLE MATL]``.

Aggregates ``matl.train`` runs (``metrics.json``) and ``matl.eval`` runs (``eval.json``) found below
the given folders into the paper's tables and figures:

* **Table 1** (rows (a)-(j), columns ``rec_acc`` / ``pose_err`` per dataset ARC, YCB, APC) and
  **Table 2** (planar / non-planar synthetic YCB), mean ± std over seeds, the paper's numbers beside
  ours. A run's row is read from its *configuration* (its ``.hydra/config.yaml``), not from the
  ``experiment=`` it was launched with: ``experiment=table1_f N=2`` is a Fig. 4 point, not row (f).
  Rows (d) and (e) are ``matl.eval`` baseline runs (``experiment=table1_d|table1_e``).
* **Fig. 4** (``fig4.png``): ``rec_acc`` and ``pose_err`` against N, for the row-(f) configuration
  with any N (rows (a) and (f) are its N=1 and N=4 points).
* **Fig. 5** (``fig5.png``): from ``--fig5 SINGLE.ckpt MATL.ckpt``, or from a row (a) and a row (f)
  run found in the folders (same dataset and setting, preferably the same seed).
* **Fig. 2** (``fig2.png``): with ``--fig2 <data>``, the appearance loss against in-plane rotation of
  one canonical image of that catalog (no runs needed).

Runs are grouped by their full configuration minus the seed (and paths, loggers, resume keys),
so runs that differ in anything else never share a cell; a group's seeds are its samples (one run
per seed: a seed run twice counts once, the newest). Tables are split by *setting* (the ``scale=``
choice, image size, epochs and test-set size). Failed jobs (``failed.json``) and unfinished ones
are listed, never averaged. Writes ``report.md``, ``table.csv`` (one row per group, numeric mean
and std columns) and the PNG figures into ``--out`` (default: the first folder).

The work is done by :mod:`matl.reporting` (``runs``: finding, reading and grouping run folders;
``rows``: which paper row a run is; ``tables``: markdown and CSV; ``figures``; ``build``: the whole
report); the paper's rows, their settings and published numbers are :mod:`matl.paper`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from matl.reporting.runs import find_runs
from matl.utils.errors import MatlError, user_errors


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m matl.report", description=__doc__.split("\n")[0])
    parser.add_argument("dirs", nargs="*", type=Path, help="run or multirun folders of matl.train / matl.eval")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: the first dir)")
    parser.add_argument("--fig5", nargs=2, type=Path, metavar=("SINGLE_CKPT", "MATL_CKPT"), default=None,
                        help="Fig. 5 from these checkpoints (default: a row a and a row f run found in the dirs)")
    parser.add_argument("--no-fig5", action="store_true", help="do not look for checkpoints for Fig. 5")
    parser.add_argument("--fig2", metavar="DATA", default=None,
                        help="draw Fig. 2 from this catalog (a data= choice, e.g. synthetic_arc)")
    parser.add_argument("--fig2-plane", default=None, help="plane index or object/plane (default: a planar object)")
    parser.add_argument("--fig2-size", type=int, default=100, help="image size of Fig. 2's canonical image")
    parser.add_argument("--cache-dir", default=None, help="canonical-image cache (default: $MATL_CACHE_DIR or "
                                                          ".cache/matl)")
    args = parser.parse_args(argv)
    if not args.dirs and not args.fig2 and not args.fig5:
        parser.error("give run folders, --fig2 DATA or --fig5 SINGLE MATL")
    return args


def main(argv: list[str] | None = None) -> int:
    """Write the report; a user error (a missing folder, no runs, a bad --fig2-plane) exits 2 with one line."""
    args = parse_args(argv)
    out = args.out or (args.dirs[0] if args.dirs else Path("outputs/report"))
    with user_errors():
        try:
            if args.dirs and not find_runs(args.dirs) and not args.fig2:
                raise MatlError(f"no metrics.json, eval.json or run folder under {', '.join(map(str, args.dirs))}")
            # imported once the command line is checked: the tables' metric names come from matl.metrics (torch)
            from matl.reporting.build import build_report

            report = build_report(args.dirs, out, fig5=args.fig5, auto_fig5=not args.no_fig5, fig2_data=args.fig2,
                                  fig2_plane=args.fig2_plane, fig2_size=args.fig2_size, cache_dir=args.cache_dir)
        except FileNotFoundError as error:  # e.g. a --fig5 checkpoint or a catalog's files
            raise MatlError(str(error)) from None
    print((out / "report.md").read_text())
    print("wrote " + ", ".join(str(p) for p in report.files))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
