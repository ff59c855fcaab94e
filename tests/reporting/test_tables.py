"""The report's cell formats and columns."""

from __future__ import annotations

from matl.metrics import METRIC_NAMES
from matl.reporting.tables import COLUMNS, METHOD_COLUMNS, fmt_paper, fmt_stat, setting_label


def test_cell_formats() -> None:
    assert fmt_stat((0.91, 0.01, 3)) == "0.910 ± 0.010 (3)"
    assert fmt_stat((0.91, 0.0, 1)) == "0.910 (1)"
    assert fmt_stat(None) == "n/a"
    assert fmt_paper((0.93, 0.01)) == "0.93 ± 0.01" and fmt_paper(None) == "n/a"
    assert setting_label(("cpu", 100, 8, 1000)) == "scale=cpu, 100 px, 8 epochs, 1000 test queries"
    assert setting_label((None, 32, 1, 48)) == "no scale= preset, 32 px, 1 epochs, 48 test queries"


def test_columns_are_the_metric_collections_names_and_query_ms() -> None:
    assert COLUMNS[:-1] == METRIC_NAMES and COLUMNS[-1] == "query_ms"
    assert METHOD_COLUMNS == ("rec_acc", "pose_err", "corner_err_px_median", "pose_acc_5px", "query_ms")
