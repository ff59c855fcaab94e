"""The paper's tables and figures from run folders (``python -m matl.report`` is its command line).

* :mod:`matl.reporting.configs`: reading a saved config (tolerant keys, dataset names, fingerprints);
* :mod:`matl.reporting.rows`: which of the paper's rows a run is (:mod:`matl.paper`), its label;
* :mod:`matl.reporting.runs`: finding, reading and grouping run folders;
* :mod:`matl.reporting.tables`: Table 1 / Table 2 / Fig. 4 cells, markdown and ``table.csv`` rows;
* :mod:`matl.reporting.figures`: Fig. 2, Fig. 4 and Fig. 5 as PNG files;
* :mod:`matl.reporting.build`: the whole report (``report.md``, ``table.csv``, figures).
"""
